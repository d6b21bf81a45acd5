"""Shared bits of the benchmark scripts: output folder, JSON, figure helpers."""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"
CONFIGS = ROOT / "configs"


def save_json(name: str, data: dict) -> Path:
    OUT.mkdir(exist_ok=True)
    p = OUT / f"{name}.json"
    p.write_text(json.dumps(data, indent=2))
    return p


def command() -> str:
    return "python " + " ".join(
        [
            str(Path(sys.argv[0]).relative_to(ROOT))
            if Path(sys.argv[0]).is_absolute()
            else sys.argv[0],
            *sys.argv[1:],
        ]
    )
