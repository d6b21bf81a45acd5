"""Causal fusion of inertial samples and late fixes by replay.

The LuVeX paper (Keldysh preprint 2011-24, Sec. 4.1) stores the IMU history and, when
a camera fix of a moment 0.6 s ago arrives, integrates again from that fix to now. Here
the same replay serves a Kalman filter and any order of arrival: the state after every
inertial sample is kept for ``history_s``; when fixes become available
(``time_s + latency``) the filter goes back to the stored state just before the
earliest of their exposure times and runs forward through the stored samples, applying
every known fix at its own exposure time (between two samples, the propagation is
split there). A late or out-of-order fix therefore lands where it belongs, and the row
at time t uses only the samples up to t and the fixes available by t.

Faulty samples (rate or acceleration beyond the limits, the paper's 0.5 m/s^2 and
50 deg/s for the planar mock-up) are not integrated: the last good reading stands in.
A gap in the samples is never integrated over: the filter restarts at the first fix
taken after it.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from visvec.fuse.inputs import Fix, ImuData

MAX_REJECTED_IN_A_ROW = 3  # then the filter restarts from the latest fix


@dataclass(frozen=True)
class FusedSample:
    """The fused state after inertial sample ``index`` (None before the first fix),
    the number of fixes applied so far, the sample's warnings and the normalised
    innovation squared of each fix that arrived with it."""

    index: int
    time_s: float
    state: object | None
    n_fixes: int
    warnings: tuple[str, ...]
    nis: tuple[float, ...] = ()


@dataclass(frozen=True)
class Limits:
    """Readings beyond these are faults (None: no limit)."""

    max_rate_dps: float | None = 50.0
    max_accel_mps2: float | None = 0.5


class Fusion:
    """The fusion engine, fed one event at a time: inertial samples in time order
    (`step`) and fixes when they become available (`add_fix`). Each `step` returns the
    fused state after that sample, using the samples so far and the fixes added before
    it (see the module docstring); a file replay and a live stream drive it alike.

    ``fix.time_s`` must be on the inertial samples' clock.
    """

    def __init__(self, model, *, limits: Limits | None = None, history_s: float = 10.0):
        self.model = model
        self.limits = limits or Limits()
        self.history_s = history_s
        # buffers over the history window, parallel: sample time, reading, state after it
        self._ts: list[float] = []
        self._gyro: list[np.ndarray] = []
        self._acc: list[np.ndarray | None] = []
        self._states: list[object | None] = []
        self._known: list[tuple[float, int, Fix]] = []  # fixes known, by exposure time
        self._pending: list[Fix] = []  # fixes added since the last sample
        self.n_applied = 0
        self._rejected_streak = 0
        self._last_good = self._prev = None  # the last good reading; the last one as used
        self._index = 0

    def add_fix(self, fix: Fix) -> None:
        """A fix that has just become available; it is applied at the next sample."""
        self._pending.append(fix)

    def gap(self) -> None:
        """The samples broke off: forget the history; the filter restarts at the next
        fix taken after the gap."""
        for buf in (self._ts, self._gyro, self._acc, self._states, self._known):
            buf.clear()
        self._last_good = self._prev = None

    def step(self, t: float, g: np.ndarray, a: np.ndarray | None, *, gap: bool = False,
             index: int | None = None) -> FusedSample:  # fmt: skip
        """Take the inertial sample at ``t`` (gyro rad/s (3,), accel m/s^2 (2,) or
        None) and return the fused state after it."""
        k = self._index if index is None else index
        self._index = k + 1
        model = self.model
        ts, gyro, acc, states, known = self._ts, self._gyro, self._acc, self._states, self._known
        warnings: list[str] = []
        if gap:
            warnings.append("imu_gap")
            self.gap()
        if is_faulty(g, a, self.limits):
            warnings.append("imu_fault")
            if self._last_good is not None:
                g, a = self._last_good
            else:
                g, a = np.zeros(3), (np.zeros(2) if a is not None else None)
        else:
            self._last_good = (g, a)
        # the reading over the interval ending at t: the mean of its two ends (trapezoid)
        g_end, a_end = g, a
        if self._prev is not None:
            g = 0.5 * (g + self._prev[0])
            a = 0.5 * (a + self._prev[1]) if a is not None else None
        self._prev = (g_end, a_end)
        ts.append(t)
        gyro.append(g)
        acc.append(a)
        states.append(None)
        # fixes that reached us by now
        new: list[Fix] = []
        nis_new: list[float] = []
        pending, self._pending = self._pending, []
        for f in pending:
            if f.time_s < ts[0] or f.time_s > t:
                warnings.append("fix_too_old" if f.time_s < ts[0] else "fix_from_future")
                continue
            bisect.insort(known, (f.time_s, id(f), f))
            new.append(f)
        # replay from the first sample at or after the earliest new fix (else the newest)
        start = len(ts) - 1
        if new:
            start = min(start, bisect.bisect_left(ts, min(f.time_s for f in new)))
        s = states[start - 1] if start > 0 else None
        if s is not None:
            t_s = ts[start - 1]
        else:
            # not initialised, or restarting: from the earliest known fix in the buffer
            init = known[0][2] if known else None
            if init is None:
                return FusedSample(k, t, None, self.n_applied, (*warnings, "no_fix_yet"))
            s, t_s = model.init(init), init.time_s
            if any(init is f for f in new):
                self.n_applied += 1
            start = bisect.bisect_left(ts, t_s)
            for i in range(start):
                states[i] = None
        for j in range(start, len(ts)):
            # every known fix with its exposure in (t_s, ts[j]], at its own time
            lo = bisect.bisect_right(known, (t_s, math.inf))
            hi = bisect.bisect_right(known, (ts[j], math.inf))
            for f_t, _, f in known[lo:hi]:
                s = model.propagate(s, gyro[j], acc[j], f_t - t_s)
                t_s = f_t
                s, ok, nis = model.update(s, f)
                if any(f is n for n in new):
                    nis_new.append(nis)
                    if ok:
                        self.n_applied += 1
                        self._rejected_streak = 0
                    else:
                        warnings.append("fix_rejected")
                        self._rejected_streak += 1
            if ts[j] > t_s:
                s = model.propagate(s, gyro[j], acc[j], ts[j] - t_s)
                t_s = ts[j]
            states[j] = s
        if self._rejected_streak >= MAX_REJECTED_IN_A_ROW:
            # the filter has disagreed with several fixes in a row: trust the fixes again
            latest = max(new, key=lambda f: f.time_s)
            s, t_s = model.init(latest), latest.time_s
            j0 = bisect.bisect_left(ts, t_s)
            for i in range(j0):
                states[i] = None
            for j in range(j0, len(ts)):
                if ts[j] > t_s:
                    s = model.propagate(s, gyro[j], acc[j], ts[j] - t_s)
                    t_s = ts[j]
                states[j] = s
            known[:] = [x for x in known if x[0] >= latest.time_s]
            self._rejected_streak = 0
            warnings.append("filter_restarted")
        # forget what is older than the history window
        cut = bisect.bisect_left(ts, t - self.history_s)
        if cut > 0:
            del ts[:cut], gyro[:cut], acc[:cut], states[:cut]
            known[:] = [x for x in known if x[0] >= ts[0]]
        return FusedSample(k, t, states[-1], self.n_applied, tuple(warnings), tuple(nis_new))


def fuse(
    imu: ImuData,
    fixes: list[Fix] | tuple[Fix, ...],
    model,
    *,
    limits: Limits | None = None,
    history_s: float = 10.0,
) -> Iterator[FusedSample]:
    """Fused states at every inertial sample of a recording, causally: each fix is
    given to the engine at the first sample at or after its ``available_s``."""
    engine = Fusion(model, limits=limits, history_s=history_s)
    arrivals = sorted(fixes, key=lambda f: (f.available_s, f.time_s))
    nxt = 0
    gaps = set(imu.gaps)
    for k in range(len(imu)):
        t = float(imu.t[k])
        while nxt < len(arrivals) and arrivals[nxt].available_s <= t:
            engine.add_fix(arrivals[nxt])
            nxt += 1
        a = imu.accel[k] if imu.accel is not None else None
        yield engine.step(t, imu.gyro[k], a, gap=k in gaps, index=k)


def is_faulty(g: np.ndarray, a: np.ndarray | None, limits: Limits) -> bool:
    if not np.all(np.isfinite(g)) or (a is not None and not np.all(np.isfinite(a))):
        return True
    if limits.max_rate_dps is not None and np.degrees(np.abs(g)).max() > limits.max_rate_dps:
        return True
    if a is not None and limits.max_accel_mps2 is not None:
        return bool(np.abs(a).max() > limits.max_accel_mps2)
    return False
