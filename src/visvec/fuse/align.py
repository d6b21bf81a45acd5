"""The fixes' clock against the IMU's, aligned before the filter starts.

With a model that can (PlanarModel.align), the engine finds the fixes' time offset
from their poses against the IMU's before it starts the filter, and applies the fixes
shifted by it (visvec.fuse.replay.Fusion).
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from visvec.fuse.inputs import Fix
from visvec.fuse.planar import ALIGN_TAU

SHIFT_MAX = ALIGN_TAU[1]  # s: the largest offset the alignment tries
# the filter waits for the time offset's alignment: at rest at most while its fixes span
# ALIGN_WAIT_S, not at all when they come fewer than ALIGN_FEW_FIXES in that time (they
# could not align it); the prior on the offset is then the alignment's sigma, at least
# ALIGN_PRIOR_MIN (that sigma is too small: PlanarModel.align), within which the
# filter's first-order time shift holds
ALIGN_WAIT_S = 4.0
# a platform that moves this much over ALIGN_WAIT_S of fixes waits on for its alignment
ALIGN_MOVING_MM = 10.0
ALIGN_MOVING_DEG = 1.0
ALIGN_EVERY_S = 0.25  # while it waits, it tries again this often
ALIGN_FEW_FIXES = 10
ALIGN_PRIOR_MIN = 0.02
# an alignment is taken only when the ALIGN_CONFIRM tries before it (each ALIGN_EVERY_S
# earlier, on nearly the same fixes) found it too, within ALIGN_AGREE of the larger of
# their sigmas. Over a second or two of fixes a steady change of the turn rate confounds
# the offset with the gyro's bias, and the fit's sigma does not hold what is left: a live
# soak's start (benchmarks/live_soak.py) aligned 26.7 +- 4.0 ms on its first 1 s of fixes,
# 11.8 +- 5.6 on 1.5 s, 7.3 +- 4.4 on 2 s, the offset 3.8 ms; started on the first, the
# filter took the same fixes to 19.9 +- 3.5 ms and its first rows were 5 sigma off.
# Confirmed, that run starts at 4.2 s, 4.0 +- 1.5 ms, no row beyond 4 sigma.
# benchmarks/fusion_timing.py (offsets 7-300 ms, jitter 0 and 1 ms, five stretches of the
# lap, 10 s each): unconfirmed, one run aligned 76 ms off and put 43 rows beyond 5 sigma
# (7.9); confirmed, none beyond 5 (at most 3.8), 0.5 % of rows beyond 3 (0.9 %), the
# start's median 2.6 s (2.3 s); but three runs with 1 ms of jitter on one stretch did
# not start within their 10 s (rows aligning_clocks, not wrong ones)
ALIGN_AGREE = 1.0
ALIGN_CONFIRM = 1

UNALIGNED = (math.nan, math.nan)


class ClockAlignment:
    """The alignment's progress: ``aligned`` is None while it waits, then the offset
    found (tau, sigma) in seconds, or (nan, nan) when the filter started without one."""

    def __init__(self) -> None:
        self.aligned: tuple[float, float] | None = None
        self._next = -math.inf
        self._tries: list[tuple[float, float] | None] = []  # the last tries' finds

    def attempt(self, model, known: list[tuple[float, int, Fix]], ts: list[float],
                gyro: list[np.ndarray], acc: list) -> bool:  # fmt: skip
        """Whether the filter may start (``aligned`` then says with what offset), given
        the fixes known (by exposure time) and the samples' times, readings and
        accelerations.

        It tries on the first ALIGN_WAIT_S of fixes, whenever they arrive (so that the
        start does not depend on the order in which they came), and then, while the
        platform moves, on the latest ALIGN_WAIT_S: a moving platform's rows with the
        offset unknown would be wrong with a small sigma (a stream 300 ms late with
        1 ms of jitter: rows 45 sigma off). It starts without when the platform is at
        rest after ALIGN_WAIT_S (the offset does not matter then; the filter learns it
        once it moves), or at once when the fixes come too sparse to align (fewer than
        ALIGN_FEW_FIXES in ALIGN_WAIT_S: LuVeX's 1.7 Hz). An alignment is taken once the
        try before it found the same (ALIGN_CONFIRM, ALIGN_AGREE)."""
        align = getattr(model, "align", None)
        if align is None or self.aligned is not None or not known:
            return True
        if model.time_offset_sigma <= 0.0:  # the offset is held (known)
            self.aligned = UNALIGNED
            return True
        if ts[-1] < self._next:
            return False
        self._next = ts[-1] + ALIGN_EVERY_S
        waited = ts[-1] - known[0][0]
        if waited / len(known) >= ALIGN_WAIT_S / ALIGN_FEW_FIXES:
            self.aligned = UNALIGNED
            return True
        if waited < ALIGN_WAIT_S:
            t0 = known[0][0]
            fixes = [f for t, _, f in known if t <= t0 + ALIGN_WAIT_S]
        else:
            t1 = known[-1][0]
            fixes = [f for t, _, f in known if t >= t1 - ALIGN_WAIT_S]
        # with the samples they can reach
        lo = bisect.bisect_left(ts, fixes[0].time_s - SHIFT_MAX - 0.05)
        hi = bisect.bisect_right(ts, fixes[-1].time_s + 0.05)
        tt = np.array(ts[lo:hi])
        rate = np.array([g[0][2] for g in gyro[lo:hi]])
        a = acc[lo:hi]
        accel = None if any(x is None for x in a) else np.array(a)
        found = align(tt, rate, accel, fixes)
        earlier = self._tries[-ALIGN_CONFIRM:] if ALIGN_CONFIRM else []
        self._tries = [*earlier, found]
        if found is not None and not _agree(found, earlier):
            found = None  # not yet confirmed: as if none were found
        if found is None:
            if waited < ALIGN_WAIT_S or _moving(fixes):
                return False
            self.aligned = UNALIGNED
            return True
        self.aligned = found
        return True


def _agree(found: tuple[float, float], earlier: list) -> bool:
    """Whether an alignment (tau, sigma) is confirmed by the ALIGN_CONFIRM tries before
    it (ALIGN_AGREE)."""
    return len(earlier) >= ALIGN_CONFIRM and all(
        e is not None and abs(found[0] - e[0]) <= ALIGN_AGREE * max(found[1], e[1]) for e in earlier
    )


def _moving(fixes: list[Fix]) -> bool:
    """Whether planar fixes show the platform moving: their positions spread over
    ALIGN_MOVING_MM or their headings over ALIGN_MOVING_DEG."""
    v = np.array([f.value for f in fixes])
    heading = np.unwrap(v[:, 2])
    return bool(np.ptp(v[:, 0]) > ALIGN_MOVING_MM or np.ptp(v[:, 1]) > ALIGN_MOVING_MM
                or np.ptp(heading) > math.radians(ALIGN_MOVING_DEG))  # fmt: skip
