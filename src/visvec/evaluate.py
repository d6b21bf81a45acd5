"""Error statistics of attitude rows against a truth file (``batch --truth``)."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.errors import InputFileError
from visvec.output import AttitudeRow

ANGLES = ("yaw_deg", "pitch_deg", "roll_deg")


def read_truth(path: str | Path) -> dict[int, np.ndarray]:
    """frame -> (3,) true yaw, pitch, roll in degrees, from a `visvec simulate` truth file."""
    path = Path(path)
    out: dict[int, np.ndarray] = {}
    try:
        fh = open(path, newline="")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the truth file ({exc.strerror})") from None
    with fh:
        reader = csv.DictReader(fh)
        need = {"frame", *ANGLES}
        if not reader.fieldnames or not need <= set(reader.fieldnames):
            raise InputFileError(
                f"{path}: truth file needs columns {sorted(need)}; found {reader.fieldnames}"
            )
        for line, row in enumerate(reader, start=2):
            try:
                out[int(row["frame"])] = np.array([float(row[k]) for k in ANGLES])
            except (TypeError, ValueError):
                raise InputFileError(
                    f"{path}: line {line}: expected numbers in frame,{','.join(ANGLES)}"
                ) from None
    return out


@dataclass(frozen=True)
class ErrorStats:
    """Per-axis error statistics (yaw, pitch, roll) in degrees over the ok rows."""

    n_frames: int
    n_ok: int
    rms_deg: np.ndarray
    mean_deg: np.ndarray
    max_abs_deg: np.ndarray
    within_3sigma: float  # fraction of ok rows with every axis within 3 sigma

    def lines(self) -> list[str]:
        out = [
            f"frames {self.n_frames}, ok {self.n_ok} "
            f"({100 * self.n_ok / max(self.n_frames, 1):.1f}%)"
        ]
        if self.n_ok:
            for name, i in (("yaw", 0), ("pitch", 1), ("roll", 2)):
                out.append(
                    f"{name:>5}: rms {self.rms_deg[i]:.4f} deg, mean {self.mean_deg[i]:+.4f}, "
                    f"max |err| {self.max_abs_deg[i]:.4f}"
                )
            out.append(f"ok rows within 3 sigma on every axis: {100 * self.within_3sigma:.1f}%")
        return out


def wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def error_stats(rows: Sequence[AttitudeRow], truth: dict[int, np.ndarray]) -> ErrorStats:
    """Compare rows with the truth (frames missing from the truth are skipped)."""
    errs, sig = [], []
    n = 0
    for r in rows:
        if r.frame not in truth:
            continue
        n += 1
        if r.ok:
            e = r.euler_deg - truth[r.frame]
            e[0] = wrap_deg(e[0])
            errs.append(e)
            sig.append(r.sigma_deg)
    if not errs:
        nan = np.full(3, np.nan)
        return ErrorStats(n, 0, nan, nan, nan, float("nan"))
    E, S = np.array(errs), np.array(sig)
    within = float(np.mean(np.all(np.abs(E) <= 3 * S, axis=1)))
    return ErrorStats(
        n, len(E), np.sqrt((E**2).mean(axis=0)), E.mean(axis=0), np.abs(E).max(axis=0), within
    )
