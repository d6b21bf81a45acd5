"""Synthetic planar streams for the fusion's timing (tests/fuse/test_planar_timing.py,
benchmarks/fusion_timing.py): the lamps path, a 100 Hz IMU along it with the
simulator's biases and noise, and 30 Hz lamp fixes whose stated times are late by a
given offset; the fused rows' errors over their sigma."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np

from visvec.fuse.inputs import Fix, ImuData
from visvec.fuse.planar import PlanarModel
from visvec.sim.lamps import ImuModel, PerimeterPath

LAP = PerimeterPath(lap_s=66.0)
# a lamp fix's covariance (x, y mm; heading rad)
FIX_COV = np.diag([0.014**2, 0.014**2, math.radians(0.003) ** 2])
# the share of a 3-axis Gaussian beyond 3 sigma on some axis
GAUSS3 = 1.0 - (1.0 - 0.0027) ** 3


class Along:
    """The lap from ``t0`` s on (another stretch of it: other turns and pushes)."""

    def __init__(self, t0: float = 0.0):
        self.t0 = t0

    def at(self, t):
        return LAP.at(np.asarray(t) + self.t0)

    def derivatives(self, t, h=1e-3):
        return LAP.derivatives(np.asarray(t) + self.t0, h)


def imu_along(seconds: float, seed: int, path=None) -> ImuData:
    """100 Hz planar samples along ``path`` (the lap), with the simulator's biases and
    noise."""
    path = path or Along()
    m = ImuModel(fault_fraction=0.0)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.01)
    vel, acc = path.derivatives(t)
    psi = path.at(t)[:, 2]
    c, s = np.cos(psi), np.sin(psi)
    ax = (c * acc[:, 0] + s * acc[:, 1]) / 1000.0 + m.accel_bias_mps2[0]
    ay = (-s * acc[:, 0] + c * acc[:, 1]) / 1000.0 + m.accel_bias_mps2[1]
    gz = np.radians(np.degrees(vel[:, 2]) + m.gyro_bias_dps)
    n = len(t)
    gyro = np.zeros((n, 3))
    gyro[:, 2] = gz + np.radians(m.gyro_noise_dps) * rng.standard_normal(n)
    accel = np.column_stack([ax, ay]) + m.accel_noise_mps2 * rng.standard_normal((n, 2))
    return ImuData(t, gyro, accel, np.arange(n), (), 0.01)


def held_up(extra: float, at: float, hold: float, offset: float = 0.008,
            jitter: float = 0.0003) -> Callable:  # fmt: skip
    """The lateness of a stream ``offset`` s late with ``jitter`` s of white jitter whose
    frames come ``extra`` s later still from ``at`` for ``hold`` s (a camera or its
    network held up), for late_fixes."""

    def late(t: float, rng: np.random.Generator) -> float:
        on = at <= t < at + hold
        return offset + jitter * rng.standard_normal() + (extra if on else 0.0)

    return late


def late_fixes(seconds: float, late: Callable, seed: int, latency: float = 0.003,
               path=None) -> list[Fix]:  # fmt: skip
    """30 Hz fixes along ``path``, each the pose ``late(t, rng)`` s before its stated
    time t, available ``latency`` s after it."""
    path = path or Along()
    rng = np.random.default_rng(seed + 100)
    out = []
    for i, t in enumerate(np.arange(0.05, seconds - 0.1, 1.0 / 30.0)):
        p = path.at(np.array([t - late(t, rng)]))[0]
        p = p + rng.multivariate_normal(np.zeros(3), FIX_COV)
        out.append(Fix(float(t), float(t) + latency, p, FIX_COV, i))
    return out


def errors_over_sigma(samples: Iterable, path=None) -> tuple[np.ndarray, np.ndarray]:
    """Per ok row (a fused sample with a state): its time and its largest error over
    sigma (x, y, heading) against ``path``."""
    path = path or Along()
    t, z = [], []
    for fs in samples:
        if fs.state is None:
            continue
        v, sig = PlanarModel.values(fs.state)
        tr = path.at(np.array([fs.time_s]))[0]
        e = np.abs([v[0] - tr[0], v[1] - tr[1], (v[2] - tr[2] + math.pi) % (2 * math.pi) - math.pi])
        t.append(fs.time_s)
        z.append(float(np.max(e / sig)))
    return np.array(t), np.array(z)
