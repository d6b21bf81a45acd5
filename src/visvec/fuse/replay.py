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
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from visvec.fuse.align import ALIGN_PRIOR_MIN, SHIFT_MAX, ClockAlignment
from visvec.fuse.history import History
from visvec.fuse.inputs import Fix, ImuData
from visvec.fuse.planar import ALIGN_TAU
from visvec.fuse.rest import RestSegment, find_rest
from visvec.fuse.saturation import NOT_CLIPPED, Saturation

MAX_REJECTED_IN_A_ROW = 3  # then the filter restarts from the latest fix
# a replay's run of this many samples or more with no fix among them goes to the model's
# propagate_run where it has one (one compiled call; the same states as one by one)
RUN_MIN = 4
# a file replay (`fuse`) takes at most this many samples between two fixes' arrivals in
# one `Fusion.run`
RUN_MAX = 512
# a model that estimates its fixes' time offset (PlanarModel.time_offset) has them applied
# at their stated time less the offset as last set: set again, and the history
# replayed, once the estimate is known to SHIFT_SIGMA and has moved SHIFT_STEP from it
SHIFT_STEP = 0.005  # s
SHIFT_SIGMA = 0.005  # s
# while the clocks align, the fixes' time offset may be anywhere in the alignment's range
# (visvec.fuse.planar.ALIGN_TAU): the provisional filter's timing sigma (Fusion._provisional)
PROVISIONAL_TIMING_S = max(abs(x) for x in ALIGN_TAU)


@dataclass(slots=True)
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
    spent_ms: float | None = None  # the time spent on it, where `fuse` measured it


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

    Beyond the replay it learns from the data as they come:
    - a rest segment at the start (visvec.fuse.rest: the gyro within 1.5 deg/s of its
      median for 0.3 s or more before the first fix) gives the gyro's bias and white
      noise (a model with ``with_rest``);
    - a gyro at its range (visvec.fuse.saturation): the clipped samples are
      reconstructed with a sigma, live from the samples before the flat top and again,
      with a replay, from both sides once it ends; such rows carry ``gyro_saturated``;
    - the fixes' clock against the IMU's (visvec.fuse.align), before a planar filter
      starts.

    ``fix.time_s`` must be on the inertial samples' clock.

    Parameters
    ----------
    model : AttitudeModel or PlanarModel
        The filter.
    limits : Limits, optional
        Readings beyond these are faults, not integrated (default: 50 deg/s and
        0.5 m/s^2, the planar mock-up's).
    history_s : float
        The inertial history kept for late fixes (s).
    gyro_range_dps : float, optional
        The gyro's range (deg/s), where known; else learned only from the evidence
        (visvec.fuse.saturation).
    """

    def __init__(self, model, *, limits: Limits | None = None, history_s: float = 10.0,
                 gyro_range_dps: float | None = None):  # fmt: skip
        self.model = model
        self.limits = limits or Limits()
        self.history_s = history_s
        self.history = History()
        self.saturation = Saturation(self.history, gyro_range_dps)
        self.clocks = ClockAlignment()
        self._known: list[tuple[float, int, Fix]] = []  # fixes known, by exposure time
        self._pending: list[Fix] = []  # fixes added since the last sample
        self.n_applied = 0
        self._rejected_streak = 0
        self._refused_since = 0.0  # the exposure of the first fix of the streak
        self._last_good = None  # the last good reading
        self._prev_a = None
        self._index = 0
        self._initialised = False
        self.rest: RestSegment | None = None
        self.shift = 0.0  # s: the fixes are applied this much before their stated time
        self._prov = None  # the provisional model while the clocks align (_provisional)

    @property
    def aligned(self) -> tuple[float, float] | None:
        """The time offset found before the start, (tau, sigma) s; (nan, nan) if none
        was; None before the start."""
        return self.clocks.aligned

    @property
    def n_saturated(self) -> int:
        """How many samples had an axis at the gyro's range."""
        return self.saturation.n_saturated

    @property
    def state(self):
        """The newest state of the samples kept (None before the first fix; a step cut
        short by Ctrl-C may have left its own sample's unfilled)."""
        return next((s for s in reversed(self.history.states) if s is not None), None)

    def add_fix(self, fix: Fix) -> None:
        """A fix that has just become available; it is applied at the next sample."""
        self._pending.append(fix)

    def gap(self) -> None:
        """The samples broke off: forget the history; the filter restarts at the next
        fix taken after the gap."""
        self.history.clear()
        self._known.clear()
        self._last_good = self._prev_a = None
        self.saturation.reset()

    def step(self, t: float, g: np.ndarray, a: np.ndarray | None, *, gap: bool = False,
             index: int | None = None) -> FusedSample:  # fmt: skip
        """Take the inertial sample at ``t`` (gyro rad/s (3,), accel m/s^2 (2,) or
        None) and return the fused state after it. Steps: 1. the sample checked and
        buffered (a fault replaced by the last good one, a saturated reading
        reconstructed); 2. the fixes that came since, in exposure order; 3. a replay
        from the earliest sample they (or a rewritten reading) touch; 4. a restart on
        the fixes after too many refused in a row; 5. the history beyond its window
        forgotten."""
        taken = self._intake(t, g, a, gap, index)
        if isinstance(taken, FusedSample):
            return taken
        return self._finish(t, *taken)

    def _intake(self, t: float, g: np.ndarray, a: np.ndarray | None, gap: bool,
                index: int | None):  # fmt: skip
        """Step 1 of `step`: the sample's index, checked and buffered. Its FusedSample
        when the clock stepped back (the sample refused); else (index, warnings so far,
        clipped axes, first sample whose reading changed)."""
        k = self._index if index is None else index
        self._index = k + 1
        h = self.history
        if h.ts and not gap and t <= h.ts[-1]:
            # a clock that steps back: this sample is refused, the state stands
            return FusedSample(k, t, h.states[-1], self.n_applied, ("imu_time_back",))
        warnings: list[str] = []
        if gap:
            warnings.append("imu_gap")
            self.gap()
        clipped, dirty = self._take_sample(t, *self._checked(g, a, warnings))
        return k, warnings, clipped, dirty

    def _finish(self, t: float, k: int, warnings: list[str], clipped: np.ndarray,
                dirty: int) -> FusedSample:  # fmt: skip
        """Steps 2-5 of `step` for the newest sample, taken by `_intake`."""
        h = self.history
        new = self._take_fixes(t, warnings)
        # replay from the first sample at or after the earliest new fix (else the newest
        # sample, or the first one whose reading was rewritten)
        start = dirty
        if new:
            start = min(start, bisect.bisect_left(h.ts, min(f.time_s for f in new)))
        nis_new: list[float] = []
        if not self._replay(start, new, warnings, nis_new):
            if self._known and self.aligned is None:
                warnings.append("aligning_clocks")
            self._forget(t)  # an IMU with no fix for hours keeps only its history
            return FusedSample(k, t, None, self.n_applied, (*warnings, "no_fix_yet"))
        if self._prov is not None:
            warnings.append("aligning_clocks")
        if (
            new
            and self._rejected_streak >= MAX_REJECTED_IN_A_ROW
            and (
                max(f.time_s for f in new) - self._refused_since
                >= getattr(self.model, "restart_after_s", 0.0)
            )
        ):
            # the filter has disagreed with several fixes in a row: trust the fixes again,
            # keeping what it learned of the sensor where the model can
            self._restart_on(max(new, key=lambda f: f.time_s))
            warnings.append("filter_restarted")
        self._shift_fixes()
        self._forget(t)
        return self._sample(k, t, h.states[-1], clipped, warnings, tuple(nis_new))

    def _sample(self, k: int, t: float, st, clipped: np.ndarray, warnings: list[str],
                nis: tuple[float, ...] = ()) -> FusedSample:  # fmt: skip
        """The FusedSample of sample ``k`` whose state is ``st``, its warnings
        completed from the state."""
        if getattr(st, "saturated", False) or clipped is not NOT_CLIPPED:
            warnings.append("gyro_saturated")
        if getattr(st, "disputed", False):
            warnings.append("fix_disputed")
        if not getattr(st, "confirmed", True):
            warnings.append("fix_unconfirmed")
        return FusedSample(k, t, st, self.n_applied, tuple(warnings), nis)

    def run(self, ts, gyros, accels, first_index: int) -> list[FusedSample]:
        """`step` on consecutive samples (ts (n,) s, gyros (n, 3) rad/s, accels (n, 2)
        m/s^2 or None) with no fix added among them and no gap: a replay's stretch
        between two fixes' arrivals. The samples are taken one by one as `step` takes
        them, and the states of a run of them whose readings nothing rewrote are
        propagated in one call (the model's ``propagate_run``): the same states, to the
        bit, as `step` gives, at a fraction of its time (a 286 Hz IMU with a fix each
        half second: runs of 143 samples). Falls back to `step` where the stretch
        cannot be taken so (before the filter starts, while the clocks align, with fixes
        pending, a model without ``propagate_run`` or one that estimates its fixes' time
        offset)."""
        n = len(ts)
        h = self.history
        if (
            not hasattr(self.model, "propagate_run")
            or hasattr(self.model, "time_offset")
            or not self._initialised
            or self._prov is not None
            or self._pending
            or not h.states
            or h.states[-1] is None
        ):
            return [self.step(float(ts[i]), gyros[i], None if accels is None else accels[i],
                              index=first_index + i) for i in range(n)]  # fmt: skip
        out: list[FusedSample] = []
        # the samples taken whose states are still to come, always the history's newest:
        # (index, time, warnings, clipped axes, the reading and accelerometers as taken)
        held: list[tuple] = []
        base = (h.states[-1], h.ts[-1])  # the state before the first held sample, its time
        for i in range(n):
            t = float(ts[i])
            if t <= h.ts[-1]:
                # a clock that steps back: refused with the newest state, as `step` does
                base = self._release(held, base, out)
            taken = self._intake(t, gyros[i], None if accels is None else accels[i], False,
                                 first_index + i)  # fmt: skip
            if isinstance(taken, FusedSample):
                out.append(taken)
                continue
            k, warnings, clipped, dirty = taken
            if dirty != len(h.ts) - 1:
                # a reading rewritten (a reconstruction): the held samples' states as
                # `step` gave them, from their readings as taken, then this one's replay
                self._release(held, base, out, behind=1)
                out.append(self._finish(t, k, warnings, clipped, dirty))
                base = (h.states[-1], t)
                continue
            held.append((k, t, warnings, clipped, h.gyro[-1], h.acc[-1]))
            self._forget(t)
        self._release(held, base, out)
        return out

    def _release(self, held: list[tuple], base: tuple, out: list[FusedSample],
                 behind: int = 0) -> tuple:  # fmt: skip
        """The states of the ``held`` samples (`run`), the history's newest but
        ``behind``, from ``base`` (state, time): stored, and their FusedSamples put in
        ``out``; ``held`` emptied. Returns the new base (the last held sample's)."""
        if not held:
            return base
        model, states = self.model, self.history.states
        s, t_s = base
        dts = []
        for _, t, *_ in held:
            dts.append(t - t_s)
            t_s = t
        readings = [x[4] for x in held]
        if len(held) >= RUN_MIN:
            new = model.propagate_run(s, readings, dts)
        else:
            new = []
            for (*_, g, a), dt in zip(held, dts, strict=True):
                s = model.propagate(s, g, a, dt)
                new.append(s)
        first = len(states) - behind - len(held)
        states[first : first + len(held)] = new
        for (k, t, warnings, clipped, *_), st in zip(held, new, strict=True):
            out.append(self._sample(k, t, st, clipped, warnings))
        held.clear()
        return new[-1], t_s

    def _checked(self, g: np.ndarray, a: np.ndarray | None, warnings: list[str]):
        """Step 1a: a faulty sample (beyond the limits, or beyond the gyro's declared
        range: the declaration or the sample is wrong) is replaced by the last good one
        (or zeros) and flagged."""
        beyond = self.saturation.beyond(g)
        self.saturation.n_beyond += beyond
        if beyond or is_faulty(g, a, self.limits):
            warnings.append("gyro_beyond_range" if beyond else "imu_fault")
            if self._last_good is not None:
                return self._last_good
            return np.zeros(3), (np.zeros(2) if a is not None else None)
        self._last_good = (g, a)
        return g, a

    def _take_sample(self, t: float, g: np.ndarray, a: np.ndarray | None):
        """Step 1b: buffer the sample and ask the saturation detector about it. The
        reading's clipped axes and the first buffered sample whose reading changed."""
        h = self.history
        h.ts.append(t)
        h.raw.append(np.asarray(g, float))
        h.clip.append(NOT_CLIPPED)
        # the accelerometer over the interval: the mean of its two ends (trapezoid)
        h.acc.append(0.5 * (a + self._prev_a) if a is not None and self._prev_a is not None
                     else a)  # fmt: skip
        self._prev_a = a
        h.states.append(None)
        h.gyro.append(h.reading(len(h.ts) - 1, 0.0))
        return self.saturation.take()

    def _take_fixes(self, t: float, warnings: list[str]) -> list[Fix]:
        """Step 2: the fixes that reached us since the last sample, known from now on
        in exposure order; one older than the history or from the future is flagged
        and dropped."""
        ts, new = self.history.ts, []
        pending, self._pending = self._pending, []
        for f in pending:
            if self.shift:
                f = replace(f, time_s=f.time_s - self.shift, shift=self.shift)
            if f.time_s < ts[0] or f.time_s > t:
                warnings.append("fix_too_old" if f.time_s < ts[0] else "fix_from_future")
                continue
            bisect.insort(self._known, (f.time_s, id(f), f))
            new.append(f)
        return new

    def _replay(self, start: int, new: list[Fix], warnings: list[str],
                nis_new: list[float]) -> bool:  # fmt: skip
        """Step 3: the states from sample ``start`` on, each known fix applied at its
        own exposure time; False while no fix has started the filter."""
        h, known = self.history, self._known
        ts, gyro, acc, states = h.ts, h.gyro, h.acc, h.states
        model = self.model
        if not self._initialised and known:
            if self._align():
                # aligned (or no alignment needed): the filter itself, from the
                # earliest fix known, whatever the provisional one did
                self._initialised = True
                self.rest = find_rest(ts, h.raw, ts[-1])
                if self.rest is not None and hasattr(self.model, "with_rest"):
                    self.model = self.model.with_rest(*self.rest)
                model = self.model
                if self._prov is not None:
                    self._prov = None
                    start = 0
                    self.n_applied = 0
                    new = [f for _, _, f in known]
            else:
                model = self._provisional()
                if model is None:
                    return False
        s = states[start - 1] if start > 0 else None
        if s is not None:
            t_s = ts[start - 1]
        else:
            # not initialised, or restarting: from the earliest known fix in the buffer
            init = known[0][2] if known else None
            if init is None:
                return False
            s, t_s = model.init(init), init.time_s
            if any(init is f for f in new):
                self.n_applied += 1
            start = bisect.bisect_left(ts, t_s)
            for i in range(start):
                states[i] = None
        run = getattr(model, "propagate_run", None)
        n = len(ts)
        j = start
        while j < n:
            # every known fix with its exposure in (t_s, ts[j]], at its own time
            lo = bisect.bisect_right(known, (t_s, math.inf))
            if run is not None and ts[j] > t_s:
                # the samples before the next fix's exposure, in one call
                end = n if lo == len(known) else bisect.bisect_left(ts, known[lo][0], j, n)
                if end - j >= RUN_MIN:
                    dts = [ts[i] - (ts[i - 1] if i > j else t_s) for i in range(j, end)]
                    states[j:end] = run(s, gyro[j:end], dts)
                    s, t_s, j = states[end - 1], ts[end - 1], end
                    continue
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
                        if self._rejected_streak == 0:
                            self._refused_since = f.time_s
                        self._rejected_streak += 1
            if ts[j] > t_s:
                s = model.propagate(s, gyro[j], acc[j], ts[j] - t_s)
                t_s = ts[j]
            states[j] = s
            j += 1
        return True

    def _provisional(self):
        """While the clocks align (planar fixes whose time offset is not known yet):
        the model the rows are fused with meanwhile, so that they need not wait. The
        fixes' timing may be off by anything in the alignment's range
        (PROVISIONAL_TIMING_S): the offset is not estimated, each fix's covariance and
        each row's are widened by that range times the rates the pose may have changed
        at (PlanarModel.timing_spread_s), and the biases are considered, not estimated:
        an honest row, warned aligning_clocks, until the alignment replays the history
        with the filter itself. None for a model that has no provisional form."""
        if self._prov is None and hasattr(self.model, "timing_spread_s"):
            self._prov = replace(self.model, time_offset_sigma=0.0, learn_jitter=False,
                                 timing_spread_s=PROVISIONAL_TIMING_S)  # fmt: skip
        return self._prov

    def _align(self) -> bool:
        """Before the filter starts: the fixes' time offset (visvec.fuse.align). False
        while it waits; once found, the fixes are applied shifted by it, and the
        model's prior on the offset is its sigma (at least ALIGN_PRIOR_MIN)."""
        h = self.history
        if not self.clocks.attempt(self.model, self._known, h.ts, h.gyro, h.acc):
            return False
        tau, sigma = self.clocks.aligned or (math.nan, math.nan)
        if math.isfinite(tau):
            prior = max(sigma, -tau, ALIGN_PRIOR_MIN)
            self.model = replace(self.model, time_offset_sigma=prior)
            self._move_fixes(max(tau, 0.0))
        return True

    def _move_fixes(self, shift: float) -> None:
        """The known fixes applied ``shift`` before their stated time, as the fixes that
        come from now on (before the filter starts: nothing to replay)."""
        self.shift = shift
        ts = self.history.ts
        moved = []
        for _, _, f in self._known:
            g = replace(f, time_s=f.time_s + f.shift - shift, shift=shift)
            if ts[0] < g.time_s <= ts[-1]:
                moved.append((g.time_s, id(g), g))
        moved.sort(key=lambda e: e[:2])
        self._known[:] = moved

    def _shift_fixes(self) -> None:
        """Step 4b: with a model that estimates its fixes' time offset, new fixes are
        applied at their stated time less the offset as now known, so that the model's
        first-order time shift (PlanarModel, the module doc) covers only what is left
        of it: at 40 ms and 35 mm/s^2 the second order is already 0.03 mm, two lamp fix
        sigmas, and a network camera's frames arrive 50-300 ms after their exposure.
        The shift is set again once the estimate is known to SHIFT_SIGMA and has moved
        SHIFT_STEP from it. A fix keeps the shift it came with (the model reads it
        from the fix), so nothing is replayed: a shift costs nothing, whatever the
        estimate does."""
        offset = getattr(self.model, "time_offset", None)
        st = self.history.states[-1] if self.history.states else None
        if offset is None or st is None:
            return
        tau, sigma = offset(st)
        shift = min(max(tau, 0.0), SHIFT_MAX)
        if sigma <= SHIFT_SIGMA and abs(shift - self.shift) >= SHIFT_STEP:
            self.shift = shift

    def _restart_on(self, latest: Fix) -> None:
        """Step 4: start again from ``latest`` (keeping what the model learned of the
        sensor, where it can) and replay the samples after it."""
        h, model = self.history, self.model
        ts, gyro, acc, states = h.ts, h.gyro, h.acc, h.states
        j0 = bisect.bisect_left(ts, latest.time_s)
        prior = states[j0 - 1] if j0 > 0 else None
        if prior is not None and hasattr(model, "reinit"):
            s = model.reinit(prior, latest)
        else:
            s = model.init(latest)
        t_s = latest.time_s
        for i in range(j0):
            states[i] = None
        for j in range(j0, len(ts)):
            if ts[j] > t_s:
                s = model.propagate(s, gyro[j], acc[j], ts[j] - t_s)
                t_s = ts[j]
            states[j] = s
        self._known[:] = [x for x in self._known if x[0] >= latest.time_s]
        self._rejected_streak = 0

    def _forget(self, t: float) -> None:
        """Step 5: what is older than the history window goes."""
        h = self.history
        cut = bisect.bisect_left(h.ts, t - self.history_s)
        if cut > 0:
            h.drop(cut)
            if self._known and self._known[0][0] < h.ts[0]:
                self._known[:] = [x for x in self._known if x[0] >= h.ts[0]]


def fuse(
    imu: ImuData,
    fixes: list[Fix] | tuple[Fix, ...],
    model,
    *,
    limits: Limits | None = None,
    history_s: float = 10.0,
    gyro_range_dps: float | None = None,
    engine: Fusion | None = None,
) -> Iterator[FusedSample]:
    """Fused states at every inertial sample of a recording, causally: each fix is
    given to the engine at the first sample at or after its ``available_s``.

    Parameters
    ----------
    imu : ImuData
        The inertial samples (`read_imu`): times (s), gyro (rad/s), accelerometers
        (m/s^2, planar), gaps.
    fixes : sequence of Fix
        The camera's fixes (`read_fixes`, `fix_from_row`), in any order.
    model : the filter (AttitudeModel, PlanarModel), or None with ``engine``
    limits : Limits, optional
        Readings beyond these are faults (not integrated).
    history_s : float
        The inertial history kept for late fixes (s).
    gyro_range_dps : float, optional
        The gyro's range (deg/s), where known: readings at it are saturated.
    engine : Fusion, optional
        An engine made already (`engine_from_options`); ``model`` is then its own.

    Yields
    ------
    FusedSample
        The state after each sample (``state`` None before the first fix), the fixes
        applied so far and the sample's warnings; `fused_rows` makes them rows.
    """
    if engine is None:
        engine = Fusion(model, limits=limits, history_s=history_s, gyro_range_dps=gyro_range_dps)
    arrivals = sorted(fixes, key=lambda f: (f.available_s, f.time_s))
    nxt = 0
    gaps = sorted(set(imu.gaps))
    n = len(imu)
    k = 0
    while k < n:
        t = float(imu.t[k])
        added = False
        while nxt < len(arrivals) and arrivals[nxt].available_s <= t:
            engine.add_fix(arrivals[nxt])
            nxt += 1
            added = True
        g = bisect.bisect_left(gaps, k)
        gap = g < len(gaps) and gaps[g] == k
        if added or gap:
            a = imu.accel[k] if imu.accel is not None else None
            yield engine.step(t, imu.gyro[k], a, gap=gap, index=k)
            k += 1
            continue
        # the samples before the next fix's arrival and the next gap, in one run
        end = min(n, k + RUN_MAX, gaps[g] if g < len(gaps) else n)
        if nxt < len(arrivals):
            end = min(end, int(np.searchsorted(imu.t, arrivals[nxt].available_s, "left")))
        t0 = time.perf_counter()
        out = engine.run(imu.t[k:end], imu.gyro[k:end],
                         None if imu.accel is None else imu.accel[k:end], k)  # fmt: skip
        # each sample's share of the run's time
        spent = (time.perf_counter() - t0) * 1000.0 / len(out)
        for fs in out:
            fs.spent_ms = spent
            yield fs
        k = end


def is_faulty(g: np.ndarray, a: np.ndarray | None, limits: Limits) -> bool:
    """Whether a sample is a fault: not finite, or beyond the limits."""
    g0, g1, g2 = g.tolist() if isinstance(g, np.ndarray) else (float(x) for x in g)
    if not (math.isfinite(g0) and math.isfinite(g1) and math.isfinite(g2)):
        return True
    if limits.max_rate_dps is not None and (
        max(abs(g0), abs(g1), abs(g2)) > math.radians(limits.max_rate_dps)
    ):
        return True
    if a is None:
        return False
    al = [float(x) for x in a]
    if not all(math.isfinite(x) for x in al):
        return True
    if al and limits.max_accel_mps2 is not None:
        return max(abs(x) for x in al) > limits.max_accel_mps2
    return False
