"""Output rows (SPEC section 4): column names and formatting of one frame's result."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visvec.data import AttitudeSolution, Status
from visvec.rotations import euler_rates_from_body, matrix_to_euler, matrix_to_quat

ATTITUDE_COLUMNS = (
    "frame",
    "time_s",
    "status",
    "yaw_deg",
    "pitch_deg",
    "roll_deg",
    "qw",
    "qx",
    "qy",
    "qz",
    "sigma_yaw_deg",
    "sigma_pitch_deg",
    "sigma_roll_deg",
    "rms_px",
    "n_points",
    "latency_ms",
    "warnings",
)


@dataclass(frozen=True)
class AttitudeRow:
    """One output row of an attitude mode; numeric fields are nan unless status is ok."""

    frame: int
    time_s: float
    status: Status
    euler_deg: np.ndarray  # (3,) yaw, pitch, roll
    q_nb: np.ndarray  # (4,) w, x, y, z
    sigma_deg: np.ndarray  # (3,) yaw, pitch, roll
    rms_px: float
    n_points: int
    latency_ms: float
    warnings: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return self.status is Status.OK

    def as_dict(self) -> dict[str, object]:
        """Column name -> value; None for the empty numeric fields of a non-ok row."""
        ok = self.ok

        def num(x: float, nd: int) -> float | None:
            return round(float(x), nd) if ok and math.isfinite(x) else None

        d: dict[str, object] = {
            "frame": self.frame,
            "time_s": round(self.time_s, 6),
            "status": str(self.status),
        }
        for k, v in zip(("yaw_deg", "pitch_deg", "roll_deg"), self.euler_deg, strict=True):
            d[k] = num(v, 6)
        for k, v in zip(("qw", "qx", "qy", "qz"), self.q_nb, strict=True):
            d[k] = num(v, 9)
        for k, v in zip(
            ("sigma_yaw_deg", "sigma_pitch_deg", "sigma_roll_deg"), self.sigma_deg, strict=True
        ):
            d[k] = num(v, 6)
        d["rms_px"] = num(self.rms_px, 4)
        d["n_points"] = self.n_points
        d["latency_ms"] = round(self.latency_ms, 3)
        d["warnings"] = ";".join(dict.fromkeys(self.warnings))
        return d


def attitude_row(
    frame: int,
    time_s: float,
    sol: AttitudeSolution | None,
    status: Status,
    warnings: tuple[str, ...],
    latency_ms: float = 0.0,
    n_points: int = 0,
) -> AttitudeRow:
    """Build the row of one frame from its solution (None when there is none)."""
    nan3 = np.full(3, np.nan)
    if sol is None or status is not Status.OK:
        return AttitudeRow(
            frame,
            time_s,
            status,
            nan3,
            np.full(4, np.nan),
            nan3,
            sol.rms_px if sol is not None else math.nan,
            sol.n_points if sol is not None else n_points,
            latency_ms,
            warnings,
        )
    e = np.array(matrix_to_euler(sol.R_nb))
    J = euler_rates_from_body(*e)
    sigma = np.sqrt(np.clip(np.diag(J @ sol.cov_b @ J.T), 0.0, None))
    return AttitudeRow(
        frame,
        time_s,
        status,
        np.degrees(e),
        matrix_to_quat(sol.R_nb),
        np.degrees(sigma),
        sol.rms_px,
        sol.n_points,
        latency_ms,
        warnings,
    )
