"""Error statistics of output rows against a truth file (``batch --truth``).

The quantities compared are the row type's main values: yaw, pitch, roll (deg) for
attitude rows, wx, wy, wz (deg/s) for rate rows. Yaw is compared modulo 360 degrees.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.errors import InputFileError
from visvec.output import Row

ANGLES = ("yaw_deg", "pitch_deg", "roll_deg")
RATES = ("wx_dps", "wy_dps", "wz_dps")
WRAPPED = ("yaw_deg", "heading_deg")


def read_truth(path: str | Path, names: Sequence[str] = ANGLES) -> dict[int, np.ndarray]:
    """frame -> true values of the columns ``names``, from a `visvec simulate` truth file."""
    path = Path(path)
    out: dict[int, np.ndarray] = {}
    try:
        fh = open(path, newline="", encoding="utf-8")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the truth file ({exc.strerror})") from None
    with fh:
        try:
            reader = csv.DictReader(fh)
            need = {"frame", *names}
            if not reader.fieldnames or not need <= set(reader.fieldnames):
                raise InputFileError(
                    f"{path}: truth file needs columns {sorted(need)}; found {reader.fieldnames}"
                )
            for line, row in enumerate(reader, start=2):
                try:
                    v = np.array([float(row[k]) for k in names])
                    k = int(row["frame"])
                except (TypeError, ValueError):
                    v = None
                if v is None or not np.all(np.isfinite(v)):
                    raise InputFileError(
                        f"{path}: line {line}: expected finite numbers in frame,{','.join(names)}"
                    )
                out[k] = v
        except UnicodeDecodeError:
            raise InputFileError(f"{path}: not a UTF-8 text file") from None
        except csv.Error as exc:
            raise InputFileError(f"{path}: not a CSV file ({exc})") from None
    if not out:
        raise InputFileError(f"{path}: the truth file has no rows")
    return out


@dataclass(frozen=True)
class ErrorStats:
    """Per-quantity error statistics over the ok rows (units of the columns)."""

    names: tuple[str, ...]
    n_frames: int
    n_ok: int
    rms: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    max_abs: np.ndarray
    mean_sigma: np.ndarray
    within_3sigma: float  # fraction of ok rows with every quantity within 3 sigma

    def lines(self) -> list[str]:
        out = [
            f"frames {self.n_frames}, ok {self.n_ok} "
            f"({100 * self.n_ok / max(self.n_frames, 1):.1f}%)"
        ]
        if self.n_ok:
            for i, name in enumerate(self.names):
                unit = name.rsplit("_", 1)[1]
                out.append(
                    f"{name.rsplit('_', 1)[0]:>7}: rms {self.rms[i]:.5g} {unit}, mean "
                    f"{self.mean[i]:+.3g}, std {self.std[i]:.3g}, max |err| "
                    f"{self.max_abs[i]:.3g}, mean sigma {self.mean_sigma[i]:.3g}"
                )
            out.append(f"ok rows within 3 sigma on every axis: {100 * self.within_3sigma:.1f}%")
        return out


def wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def error_stats(
    rows: Sequence[Row], truth: dict[int, np.ndarray], names: Sequence[str] = ANGLES
) -> ErrorStats:
    """Compare rows with the truth (frames missing from the truth are skipped)."""
    errs, sig = [], []
    n = 0
    wrap = [i for i, k in enumerate(names) if k in WRAPPED]
    for r in rows:
        if r.frame not in truth:
            continue
        n += 1
        if r.ok:
            e = r.values() - truth[r.frame]
            e[wrap] = wrap_deg(e[wrap])
            errs.append(e)
            sig.append(r.sigmas())
    names = tuple(names)
    if not errs:
        nan = np.full(len(names), np.nan)
        return ErrorStats(names, n, 0, nan, nan, nan, nan, nan, float("nan"))
    E, S = np.array(errs), np.array(sig)
    within = float(np.mean(np.all(np.abs(E) <= 3 * S, axis=1)))
    return ErrorStats(
        names,
        n,
        len(E),
        np.sqrt((E**2).mean(axis=0)),
        E.mean(axis=0),
        E.std(axis=0),
        np.abs(E).max(axis=0),
        S.mean(axis=0),
        within,
    )
