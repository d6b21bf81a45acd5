"""Output rows (docs/reference.md, Output rows): column names and formatting of one
frame's result."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from visvec.data import AttitudeSolution, Status
from visvec.rotations import euler_jacobian_terms, matrix_to_euler, matrix_to_quat

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
    "time_unix",
)


RATE_COLUMNS = (
    "frame",
    "time_s",
    "status",
    "wx_dps",
    "wy_dps",
    "wz_dps",
    "sigma_wx_dps",
    "sigma_wy_dps",
    "sigma_wz_dps",
    "rms_px",
    "n_points",
    "latency_ms",
    "warnings",
    "time_unix",
)

PLANAR_COLUMNS = (
    "frame",
    "time_s",
    "status",
    "x_mm",
    "y_mm",
    "heading_deg",
    "sigma_x_mm",
    "sigma_y_mm",
    "sigma_heading_deg",
    "rms_px",
    "n_points",
    "latency_ms",
    "warnings",
    "time_unix",
)


# the decimals of an attitude row's quantities: angles, quaternion, sigmas
_ATTITUDE_DECIMALS = (6, 6, 6, 9, 9, 9, 9, 6, 6, 6)


def _floats(a) -> list[float]:
    """An array's values as Python floats (rounded and formatted faster than numpy's)."""
    return np.asarray(a).tolist()


@dataclass(frozen=True)
class Row:
    """What every output row has; numeric fields are nan unless status is ok.

    Subclasses name their columns and list their quantities (name, value, decimals)
    in column order.
    """

    frame: int
    time_s: float
    status: Status
    rms_px: float
    n_points: int
    latency_ms: float
    warnings: tuple[str, ...]
    # the frame's absolute time (s since 1970, UTC): the capture clock of a live source,
    # a recording's own where it has them; nan where neither is known
    time_unix: float = math.nan
    # the covariance of values() (their units squared), where the solver has one
    cov: np.ndarray | None = None

    columns: ClassVar[tuple[str, ...]] = ()
    value_columns: ClassVar[tuple[str, ...]] = ()  # the values a truth file holds

    @property
    def ok(self) -> bool:
        return self.status is Status.OK

    @property
    def reason(self) -> str:
        """Why a row is not ok, as counted in a run's notes: its warning codes, or its
        status when it has none."""
        return ";".join(self.warnings) or self.status.value

    def quantities(self) -> list[tuple[str, float, int]]:
        raise NotImplementedError

    def values(self) -> np.ndarray:
        """The row's main quantities (the ones a truth file holds), in column order."""
        raise NotImplementedError

    def sigmas(self) -> np.ndarray:
        """1-sigma of :meth:`values` where the row has one."""
        raise NotImplementedError

    def fields(self) -> list[object]:
        """The row's values in column order (``columns``), rounded as written; None for
        the empty numeric fields of a non-ok row."""
        isfinite = math.isfinite
        out: list[object] = [self.frame, round(self.time_s, 6), self.status.value]
        if self.status is Status.OK:
            out += [round(v, nd) if isfinite(v) else None for _, v, nd in self.quantities()]
            rms = float(self.rms_px)
            out.append(round(rms, 4) if isfinite(rms) else None)
        else:
            out += [None] * (len(self.columns) - 7)
        w = self.warnings
        out += [
            self.n_points,
            round(self.latency_ms, 3),
            (w[0] if len(w) == 1 else ";".join(dict.fromkeys(w))) if w else "",
            round(self.time_unix, 6) if isfinite(self.time_unix) else None,
        ]
        return out

    def as_dict(self) -> dict[str, object]:
        """Column name -> value (`fields`); None for the empty numeric fields of a
        non-ok row."""
        return dict(zip(self.columns, self.fields(), strict=True))

    @classmethod
    def cov_columns(cls) -> tuple[str, ...]:
        """The covariance's columns (``--covariance``): its upper triangle,
        ``cov_<a>_<b>`` for the values a, b (their units squared or multiplied)."""
        names = [c.rsplit("_", 1)[0] for c in cls.value_columns]
        return tuple(f"cov_{names[i]}_{names[j]}" for i in range(3) for j in range(i, 3))

    def cov_dict(self) -> dict[str, float | None]:
        """The covariance's columns of this row (empty unless ok and known)."""
        cols = self.cov_columns()
        if not self.ok or self.cov is None or not np.all(np.isfinite(self.cov)):
            return dict.fromkeys(cols)
        vals = [float(self.cov[i, j]) for i in range(3) for j in range(i, 3)]
        return {c: float(f"{v:.6g}") for c, v in zip(cols, vals, strict=True)}


@dataclass(frozen=True)
class AttitudeRow(Row):
    """One output row of an attitude mode (triangle, markers, fused attitude).

    Attributes
    ----------
    frame, time_s, status, rms_px, n_points, latency_ms, warnings, time_unix, cov
        As every row (`Row`): the frame's number and time (s), its status, the fit's
        RMS residual (px), the points used, the time spent (ms), the warnings, the
        absolute time (s since 1970) and the values' covariance (deg^2).
    euler_deg : ndarray, shape (3,)
        Yaw, pitch, roll (deg, Z-Y-X of R_NB).
    q_nb : ndarray, shape (4,)
        The same attitude as a quaternion (w, x, y, z; w >= 0).
    sigma_deg : ndarray, shape (3,)
        The 1-sigma of yaw, pitch, roll (deg).
    """

    euler_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # yaw,pitch,roll
    q_nb: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))  # w, x, y, z
    sigma_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    columns: ClassVar[tuple[str, ...]] = ATTITUDE_COLUMNS
    value_columns: ClassVar[tuple[str, ...]] = ATTITUDE_COLUMNS[3:6]

    def quantities(self) -> list[tuple[str, float, int]]:
        v = _floats(self.euler_deg) + _floats(self.q_nb) + _floats(self.sigma_deg)
        return list(zip(ATTITUDE_COLUMNS[3:13], v, _ATTITUDE_DECIMALS, strict=True))

    def values(self) -> np.ndarray:
        return self.euler_deg

    def sigmas(self) -> np.ndarray:
        return self.sigma_deg


@dataclass(frozen=True)
class RateRow(Row):
    """One output row of the starfield mode: angular rate in the camera frame C."""

    w_dps: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    sigma_dps: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    columns: ClassVar[tuple[str, ...]] = RATE_COLUMNS
    value_columns: ClassVar[tuple[str, ...]] = RATE_COLUMNS[3:6]

    def quantities(self) -> list[tuple[str, float, int]]:
        out = [(k, v, 7) for k, v in zip(RATE_COLUMNS[3:6], _floats(self.w_dps), strict=True)]
        out += [(k, v, 7) for k, v in zip(RATE_COLUMNS[6:9], _floats(self.sigma_dps), strict=True)]
        return out

    def values(self) -> np.ndarray:
        return self.w_dps

    def sigmas(self) -> np.ndarray:
        return self.sigma_dps


@dataclass(frozen=True)
class PoseRow(Row):
    """One output row of the lamps mode: the body origin's position in N (mm) and the
    heading (rotation about n3, deg)."""

    pose: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # x, y, heading
    sigma: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    columns: ClassVar[tuple[str, ...]] = PLANAR_COLUMNS
    value_columns: ClassVar[tuple[str, ...]] = PLANAR_COLUMNS[3:6]

    def quantities(self) -> list[tuple[str, float, int]]:
        out = [(k, v, 4) for k, v in zip(PLANAR_COLUMNS[3:6], _floats(self.pose), strict=True)]
        out += [(k, v, 5) for k, v in zip(PLANAR_COLUMNS[6:9], _floats(self.sigma), strict=True)]
        return out

    def values(self) -> np.ndarray:
        return self.pose

    def sigmas(self) -> np.ndarray:
        return self.sigma


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
    if sol is None or status is not Status.OK:
        return AttitudeRow(
            frame,
            time_s,
            status,
            sol.rms_px if sol is not None else math.nan,
            sol.n_points if sol is not None else n_points,
            latency_ms,
            warnings,
        )
    R = np.asarray(sol.R_nb, float)
    yaw, pitch, roll = matrix_to_euler(R)
    # cov_e = J cov_b J^T with J = euler_rates_from_body (its first column (0, 0, 1)),
    # written out on floats: a fused row of a 1 kHz IMU costs microseconds
    j01, j02, j11, j12, j21, j22 = euler_jacobian_terms(pitch, roll)
    (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = np.asarray(sol.cov_b, float).tolist()
    # rows of J cov_b (J's rows: (0, j01, j02), (0, j11, j12), (1, j21, j22))
    a0 = (j01 * c10 + j02 * c20, j01 * c11 + j02 * c21, j01 * c12 + j02 * c22)
    a1 = (j11 * c10 + j12 * c20, j11 * c11 + j12 * c21, j11 * c12 + j12 * c22)
    a2 = (c00 + j21 * c10 + j22 * c20, c01 + j21 * c11 + j22 * c21, c02 + j21 * c12 + j22 * c22)
    e00 = a0[1] * j01 + a0[2] * j02
    e01 = a0[1] * j11 + a0[2] * j12
    e02 = a0[0] + a0[1] * j21 + a0[2] * j22
    e11 = a1[1] * j11 + a1[2] * j12
    e12 = a1[0] + a1[1] * j21 + a1[2] * j22
    e22 = a2[0] + a2[1] * j21 + a2[2] * j22
    d = _DEG
    return AttitudeRow(
        frame,
        time_s,
        status,
        sol.rms_px,
        sol.n_points,
        latency_ms,
        warnings,
        euler_deg=np.array([yaw * d, pitch * d, roll * d]),
        q_nb=matrix_to_quat(R),
        sigma_deg=np.array(
            [
                math.sqrt(max(e00, 0.0)) * d,
                math.sqrt(max(e11, 0.0)) * d,
                math.sqrt(max(e22, 0.0)) * d,
            ]
        ),  # fmt: skip
        cov=np.array([[e00, e01, e02], [e01, e11, e12], [e02, e12, e22]]) * d * d,
    )


_DEG = 180.0 / math.pi
