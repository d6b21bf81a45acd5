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
    z: np.ndarray | None = None  # (n_ok, k) errors over their sigmas

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
        np.divide(E, S, out=np.full_like(E, np.nan), where=S > 0),
    )


# the calibration test of a sigma (a Gaussian puts 0.27 % beyond 3 sigma): at most
# twice that share of (ok row, quantity) pairs beyond 3 sigma, and none beyond 5
GAUSS_BEYOND_3 = 0.0027


def frame_errors(
    rows: Sequence[Row], truth: dict[int, np.ndarray], names: Sequence[str] = ANGLES
) -> list[dict[str, object]]:
    """One dict per row with a truth: frame, time_s, status, and for an ok row each
    quantity's error (``err_<name>``, yaw and heading wrapped to +-180) and the error
    over its sigma (``z_<name>``); empty for the others."""
    wrap = [i for i, k in enumerate(names) if k in WRAPPED]
    out = []
    for r in rows:
        if r.frame not in truth:
            continue
        d: dict[str, object] = {"frame": r.frame, "time_s": round(r.time_s, 6),
                                "status": str(r.status)}  # fmt: skip
        if r.ok:
            e = r.values() - truth[r.frame]
            e[wrap] = wrap_deg(e[wrap])
            s = r.sigmas()
            for i, k in enumerate(names):
                d[f"err_{k}"] = float(e[i])
            for i, k in enumerate(names):
                d[f"z_{k}"] = float(e[i] / s[i]) if s[i] > 0 else None
        else:
            d.update({f"err_{k}": None for k in names})
            d.update({f"z_{k}": None for k in names})
        out.append(d)
    return out


def summary_dict(
    rows: Sequence[Row], stats: ErrorStats | None, names: Sequence[str]
) -> dict[str, object]:
    """The run's figures as JSON: rows, ok share, statuses and reasons; with a truth,
    per quantity RMS, mean, std, max |error|, mean sigma, the shares beyond 3 and 5
    sigma and whether the sigmas pass the calibration test."""
    from collections import Counter

    statuses = Counter(str(r.status) for r in rows)
    reasons = Counter(r.reason for r in rows if not r.ok)
    n = len(rows)
    out: dict[str, object] = {
        "rows": n,
        "ok": statuses.get("ok", 0),
        "ok_share": statuses.get("ok", 0) / n if n else None,
        "statuses": dict(statuses),
        "reasons": dict(reasons.most_common()),
    }
    if stats is None:
        return out

    def nums(a) -> dict[str, float | None]:
        return {k: (float(v) if np.isfinite(v) else None) for k, v in zip(names, a, strict=True)}

    truth: dict[str, object] = {
        "frames_with_truth": stats.n_frames,
        "ok_with_truth": stats.n_ok,
        "rms": nums(stats.rms),
        "mean": nums(stats.mean),
        "std": nums(stats.std),
        "max_abs": nums(stats.max_abs),
        "mean_sigma": nums(stats.mean_sigma),
        "within_3sigma_every_axis": stats.within_3sigma if stats.n_ok else None,
    }
    if stats.z is not None and len(stats.z):
        az = np.abs(stats.z[np.isfinite(stats.z)])
        beyond3 = float(np.mean(az > 3.0)) if len(az) else None
        truth["beyond_3sigma_share"] = beyond3
        truth["beyond_5sigma_count"] = int(np.sum(az > 5.0))
        truth["sigma_calibrated"] = bool(
            beyond3 is not None and beyond3 <= 2 * GAUSS_BEYOND_3 and not np.any(az > 5.0)
        )
    out["truth"] = truth
    return out
