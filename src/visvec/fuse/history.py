"""The inertial samples the fusion engine keeps over its history window."""

from __future__ import annotations

import numpy as np


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

    def reading(self, j: int, sat_sigma: np.ndarray | float) -> np.ndarray:
        """The reading over the interval ending at sample j, as a model's propagate
        takes it: (3, 3) rows: the mean of its two ends (trapezoid, rad/s), its rate of
        change (rad/s^2) and the extra 1-sigma per axis of a saturated (reconstructed)
        reading (rad/s; 0 where the reading is within range)."""
        g = self.raw[j]
        out = np.empty((3, 3))
        if j == 0:
            out[0] = g
            out[1] = 0.0
        else:
            g0 = self.raw[j - 1]
            np.add(g, g0, out=out[0])
            out[0] *= 0.5
            np.subtract(g, g0, out=out[1])
            out[1] /= self.ts[j] - self.ts[j - 1]
        out[2] = sat_sigma
        return out
