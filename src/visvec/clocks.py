"""One clock tied to another by what arrives: a live IMU's (visvec.fuse.live) and a
camera's own frame timestamps (visvec.sources.video) to the host's monotonic clock."""

from __future__ import annotations

import math
from collections import deque

# a clock is tied to the host's by the arrivals of this long (s): two free-running
# crystals differ by tens of ppm, so within it the tie lags the drift by at most the
# drift over the window (0.5 ms at 50 ppm)
CLOCK_WINDOW_S = 10.0


class ClockTie:
    """Another clock against the host's: host time (time.monotonic) minus its time, as
    the least of (arrival - time) over what arrived in the last ``window_s`` (what took
    the least time to arrive sets it; the window's minimum kept by a monotone deque,
    O(1) an arrival).

    Over a whole run, the least of them falls behind a clock slower than the host's:
    two free-running clocks differ by tens of ppm, 50 ppm is 0.18 s an hour. Within the
    window the offset lags at most the drift over the window (1 ms at 100 ppm), and a
    clock that restarts is followed after one window."""

    def __init__(self, window_s: float | None = None):
        self.window_s = CLOCK_WINDOW_S if window_s is None else window_s
        self._env: deque = deque()  # (arrival, arrival - t), the values increasing

    def add(self, arrival: float, t: float) -> None:
        v = arrival - t
        env = self._env
        while env and env[-1][1] >= v:
            env.pop()
        env.append((arrival, v))
        while env[0][0] < arrival - self.window_s:
            env.popleft()

    @property
    def offset(self) -> float:
        """Host time minus the other clock's (s); inf before the first arrival."""
        return self._env[0][1] if self._env else math.inf
