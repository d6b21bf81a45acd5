"""The inertial samples the fusion engine keeps over its history window."""

from __future__ import annotations

import numpy as np

from visvec.fuse.saturation import reading


class History:
    """Parallel lists over the history window, one entry per inertial sample: its time
    (s), the raw gyro reading (rad/s (3,); a clipped one rewritten by its
    reconstruction), which axes were at the gyro's range, the reading the filter
    integrates over the interval ending there (`reading`), the accelerometers' mean
    over that interval (m/s^2 (2,) or None) and the filter's state after it (None before
    the first fix)."""

    def __init__(self) -> None:
        self.ts: list[float] = []
        self.raw: list[np.ndarray] = []
        self.clip: list[np.ndarray] = []
        self.gyro: list[np.ndarray] = []
        self.acc: list[np.ndarray | None] = []
        self.states: list[object | None] = []

    def __len__(self) -> int:
        return len(self.ts)

    def _lists(self) -> tuple[list, ...]:
        return self.ts, self.raw, self.clip, self.gyro, self.acc, self.states

    def clear(self) -> None:
        for buf in self._lists():
            buf.clear()

    def drop(self, cut: int) -> None:
        """Forget the first ``cut`` samples."""
        for buf in self._lists():
            del buf[:cut]

    def reading(self, j: int, sat_sigma: np.ndarray) -> np.ndarray:
        """The reading over the interval ending at sample j: the mean of its two ends
        (trapezoid) and its rate of change."""
        g = self.raw[j]
        if j == 0:
            return reading(g, np.zeros(3), sat_sigma)
        dt = self.ts[j] - self.ts[j - 1]
        g0 = self.raw[j - 1]
        return reading(0.5 * (g + g0), (g - g0) / dt, sat_sigma)
