"""Writing a rendered sequence: numbered PNG frames and their truth.csv."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from visvec.imageio import write_image


def write_sequence(
    out_dir: str | Path,
    columns: Sequence[str],
    times: np.ndarray,
    frame_at: Callable[[float], tuple[np.ndarray, list[str]]],
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Write ``frame_NNNN.png`` for each time and ``truth.csv`` (``columns``: frame,
    file, time_s, then the values ``frame_at(t)`` returns, already formatted, with the
    image). Returns the path of truth.csv."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = out / "truth.csv"
    width = max(4, len(str(len(times) - 1)))
    with open(truth, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(columns)
        for i, t in enumerate(times):
            img, values = frame_at(float(t))
            name = f"frame_{i:0{width}d}.png"
            write_image(out / name, img)
            wr.writerow([i, name, f"{t:.6f}", *values])
            if progress is not None:
                progress(i)
    return truth
