"""Shared bits of the benchmark scripts: output folder, JSON, figure helpers."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

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


def add_refine_option(ap) -> None:
    """--refine: the triangle rig's [detect] refine for the run."""
    ap.add_argument(
        "--refine",
        choices=("lines", "pixels"),
        default="lines",
        help="the rig's [detect] refine (pixels: the edges fitted to the pixels)",
    )


def run_record() -> dict:
    """What every result file starts with: the command, the machine and the date."""
    from visvec.bench.triangle import machine

    return {"command": command(), "machine": machine(), "date": time.strftime("%Y-%m-%d")}


def summarise(out) -> dict:
    """An Outcome's summary with the RMS of error/sigma per axis (ok rows)."""
    s = out.summary()
    if out.n_ok:
        z = np.array(out.err_deg) / np.array(out.sigma_deg)
        rms = np.sqrt(np.mean(z**2, axis=0)).round(2).tolist()
        s["z_rms"] = dict(zip(("yaw", "pitch", "roll"), rms, strict=True))
    return s


def pyplot():
    """matplotlib's pyplot drawing to files (no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
