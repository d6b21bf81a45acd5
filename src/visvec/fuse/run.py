"""Fused output rows (docs/reference.md, Output rows): one row per inertial sample, in
the fixes' columns."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from visvec.data import Status
from visvec.fuse.inputs import ImuData
from visvec.fuse.replay import FusedSample, Limits, is_faulty
from visvec.output import PoseRow, Row, attitude_row

REST_MAX_RATE_DPS = 2.0  # a rest window turning faster than this was not at rest
REST_MAX_ACCEL_STD = 0.05  # m/s^2


@dataclass(frozen=True)
class RestBiases:
    """Mean gyro (rad/s, 3) and accelerometer (m/s^2, x y) readings over the first
    ``duration_s`` of a recording taken at rest (LuVeX Sec. 3.1.1), and how many
    samples they average."""

    gyro: np.ndarray
    accel: np.ndarray | None
    n: int
    duration_s: float


def rest_biases(imu: ImuData, duration_s: float, limits: Limits | None = None) -> RestBiases:
    """Biases from the first ``duration_s`` seconds, which must be at rest; samples
    beyond ``limits`` (faults) are left out.

    Raises
    ------
    ValueError
        The window holds fewer than 10 samples, or the readings move too much for a
        body at rest (mean rate over 2 deg/s or accelerometer scatter over 0.05 m/s^2).
    """
    sel = imu.t < imu.t[0] + duration_s
    if imu.gaps:
        sel &= np.arange(len(imu)) < imu.gaps[0]
    if limits is not None:
        acc = imu.accel if imu.accel is not None else [None] * len(imu)
        sel &= ~np.array([is_faulty(g, a, limits) for g, a in zip(imu.gyro, acc, strict=True)])
    n = int(sel.sum())
    if n < 10:
        raise ValueError(f"{n} inertial samples in the first {duration_s:g} s; at least 10 needed")
    g = imu.gyro[sel].mean(axis=0)
    a = imu.accel[sel].mean(axis=0) if imu.accel is not None else None
    if np.degrees(np.abs(g)).max() > REST_MAX_RATE_DPS or (
        imu.accel is not None and imu.accel[sel].std(axis=0).max() > REST_MAX_ACCEL_STD
    ):
        raise ValueError(
            f"the first {duration_s:g} s do not look like rest (mean rate "
            f"{np.degrees(g).round(3).tolist()} deg/s); give a shorter rest window or none"
        )
    return RestBiases(g, a, n, duration_s)


class _Solution(NamedTuple):
    """What attitude_row reads of an AttitudeSolution, for a fused state (a row of a
    1 kHz IMU builds no more than it needs)."""

    R_nb: np.ndarray
    cov_b: np.ndarray
    n_points: int
    rms_px: float = math.nan


def fused_rows(samples: Iterator[FusedSample], model) -> Iterator[Row]:
    """Rows of fused samples: planar pose or attitude, like the fixes.

    Parameters
    ----------
    samples : iterator of FusedSample
        The engine's states (`fuse`, or `Fusion.step` live).
    model : AttitudeModel or PlanarModel
        The engine's filter (``engine.model``).

    Yields
    ------
    AttitudeRow or PoseRow
        One per sample: yaw, pitch, roll (deg) and q_NB with their sigmas (deg) and
        covariance (deg^2), or x, y (mm) and heading (deg) with theirs; ``latency_ms``
        the time spent on the sample (its propagation and any replay; in a file
        replay's run of samples, its share of the run's time); ``no_target``
        before the first fix.
    """
    it = iter(samples)
    while True:
        t0 = time.perf_counter()
        fs = next(it, None)
        if fs is None:
            return
        latency_ms = (time.perf_counter() - t0) * 1000.0 if fs.spent_ms is None else fs.spent_ms
        if fs.state is None:
            if model.planar:
                yield PoseRow(fs.index, fs.time_s, Status.NO_TARGET, math.nan, fs.n_fixes,
                              latency_ms, fs.warnings)  # fmt: skip
            else:
                yield attitude_row(fs.index, fs.time_s, None, Status.NO_TARGET, fs.warnings,
                                   latency_ms, fs.n_fixes)  # fmt: skip
            continue
        if model.planar:
            v, s = model.values(fs.state)
            yield PoseRow(
                fs.index, fs.time_s, Status.OK, math.nan, fs.n_fixes, latency_ms, fs.warnings,
                pose=np.array([v[0], v[1], math.degrees(v[2])]),
                sigma=np.array([s[0], s[1], math.degrees(s[2])]),
            )  # fmt: skip
        else:
            R, cov = model.values(fs.state)
            yield attitude_row(fs.index, fs.time_s, _Solution(R, cov, fs.n_fixes), Status.OK,
                               fs.warnings, latency_ms)  # fmt: skip
