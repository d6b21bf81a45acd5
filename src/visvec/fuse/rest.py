"""A rest segment at the start of a recording: the gyro's bias and white noise."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

REST_MIN_S, REST_MAX_S = 0.3, 5.0  # a rest segment at the start: its length
REST_BAND_DPS = 1.5  # a gyro at rest stays within this of its median


class RestSegment(NamedTuple):
    """The gyro over a rest segment: its mean (rad/s, (3,)), its scatter (rad/s, (3,),
    per sample) and how many samples it spans."""

    mean: np.ndarray
    std: np.ndarray
    n: int


def find_rest(ts: list[float], raw: list[np.ndarray], t_end: float) -> RestSegment | None:
    """The rest segment at the start of the samples (times ``ts``, gyro readings
    ``raw`` rad/s) up to ``t_end`` (when the first fix arrives), if any: the gyro within
    REST_BAND_DPS of its median for REST_MIN_S or more (at most REST_MAX_S)."""
    t = np.array(ts)
    n_max = int(np.searchsorted(t, min(t_end, t[0] + REST_MAX_S), side="right"))
    if n_max < 10:
        return None
    g = np.array(raw[:n_max])
    band = math.radians(REST_BAND_DPS)
    med = np.median(g[: max(10, n_max // 4)], axis=0)
    out = np.nonzero(np.any(np.abs(g - med) > band, axis=1))[0]
    n = int(out[0]) if len(out) else n_max
    if n < 10 or t[n - 1] - t[0] < REST_MIN_S:
        return None
    seg = g[:n]
    return RestSegment(seg.mean(axis=0), seg.std(axis=0, ddof=1), n)
