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
from dataclasses import dataclass, replace

import numpy as np

from visvec.fuse.inputs import Fix, ImuData
from visvec.fuse.models import ALIGN_TAU

MAX_REJECTED_IN_A_ROW = 3  # then the filter restarts from the latest fix
# a model that estimates its fixes' time offset (PlanarModel.time_offset) has them applied
# at their stated time less the offset as last set: set again, and the history
# replayed, once the estimate is known to SHIFT_SIGMA and has moved SHIFT_STEP from it
SHIFT_STEP = 0.005  # s
SHIFT_SIGMA = 0.005  # s
SHIFT_MAX = ALIGN_TAU[1]  # s: the largest offset the alignment tries
# the filter waits for the time offset's alignment (PlanarModel.align; Fusion._align):
# at rest at most while its fixes span ALIGN_WAIT_S, not at all when they come fewer
# than ALIGN_FEW_FIXES in that time (they could not align it); the prior on the offset
# is then the alignment's sigma, at least ALIGN_PRIOR_MIN (that sigma is too small:
# PlanarModel.align), within which the filter's first-order time shift holds
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


SAT_MIN_DPS = 100.0  # a flat top below this is not a gyro's range
SAT_BAND = 0.005  # readings within this share of the range are at it
SAT_RUN = 3  # a flat top: this many samples in the band ...
SAT_BEYOND = 0.1  # ... where the samples before point this far past it
SAT_OTHER = 0.03  # an axis or side not yet seen clipped: another's level, less this
SAT_SIGMA = 0.25  # 1-sigma of a saturated reading's reconstruction, in ranges (live)
SAT_SIGMA_BOTH = 0.1  # ... once the samples after the flat top are in
REST_MIN_S, REST_MAX_S = 0.3, 5.0  # a rest segment at the start: its length
REST_BAND_DPS = 1.5  # a gyro at rest stays within this of its median


def reading(mean: np.ndarray, rate: np.ndarray, sat: np.ndarray) -> np.ndarray:
    """What a model's propagate takes as ``gyro``: (3, 3) rows: the interval's mean rate
    (rad/s), its rate of change (rad/s^2) and the extra 1-sigma per axis of a
    saturated reading (rad/s; 0 where the reading is within range)."""
    return np.stack([mean, rate, sat])


def declip(
    t: np.ndarray, v: np.ndarray, known: np.ndarray, at: np.ndarray, rng: float, sign: float
) -> np.ndarray:
    """Values at times ``at`` of a signal clipped at +-``rng``, from a quadratic through
    the unclipped samples (t[known], v[known]) on either side of the flat top (the
    clipped-signal reconstruction of, e.g., Abel & Smith, "Restoring a clipped signal",
    ICASSP 1991, with the simplest smooth model); never inside the range, never beyond
    twice it."""
    tk, vk = t[known], v[known]
    deg = min(2, len(tk) - 1)
    if deg < 1:
        return np.full(len(at), sign * rng)
    c = np.polyfit(tk - at[0], vk, deg)
    est = np.polyval(c, at - at[0])
    return sign * np.clip(sign * est, rng, 2.0 * rng)


class Fusion:
    """The fusion engine, fed one event at a time: inertial samples in time order
    (`step`) and fixes when they become available (`add_fix`). Each `step` returns the
    fused state after that sample, using the samples so far and the fixes added before
    it (see the module docstring); a file replay and a live stream drive it alike.

    Beyond the replay it learns from the data as they come:
    - a rest segment at the start (the gyro within 1.5 deg/s of its median for 0.3 s
      or more before the first fix) gives the gyro's bias and white noise (a model
      with ``with_rest``);
    - a gyro at its range (a flat top: the largest reading seen, repeated) is
      detected; the clipped samples are reconstructed (`declip`) with a sigma, live
      from the samples before the flat top and again, with a replay, from both sides
      once it ends; such rows carry ``gyro_saturated``.

    ``fix.time_s`` must be on the inertial samples' clock.
    """

    def __init__(self, model, *, limits: Limits | None = None, history_s: float = 10.0,
                 gyro_range_dps: float | None = None):  # fmt: skip
        self.model = model
        self.limits = limits or Limits()
        self.history_s = history_s
        # buffers over the history window, parallel: sample time, raw gyro, whether it
        # was at the range per axis, reading as used, state after it
        self._ts: list[float] = []
        self._raw: list[np.ndarray] = []
        self._clip: list[np.ndarray] = []
        self._gyro: list[np.ndarray] = []
        self._acc: list[np.ndarray | None] = []
        self._states: list[object | None] = []
        self._known: list[tuple[float, int, Fix]] = []  # fixes known, by exposure time
        self._pending: list[Fix] = []  # fixes added since the last sample
        self.n_applied = 0
        self._rejected_streak = 0
        self._refused_since = 0.0  # the exposure of the first fix of the streak
        self._last_good = None  # the last good reading
        self._prev_a = None
        self._index = 0
        # clip levels (rad/s) per axis, positive and negative side; nan: not known
        self._ranges = np.full((3, 2), math.radians(gyro_range_dps) if gyro_range_dps
                               else math.nan)  # fmt: skip
        self._burst_end: int | None = None  # samples since a flat top ended
        self._initialised = False
        self.rest = None  # (mean rad/s (3,), std rad/s (3,), n) once found
        self.n_saturated = 0
        self.shift = 0.0  # s: the fixes are applied this much before their stated time
        # the time offset found before the start, (tau, sigma) s; (nan, nan) if none was
        self.aligned: tuple[float, float] | None = None
        self._align_next = -math.inf
        self._align_tries: list[tuple[float, float] | None] = []  # the last tries' finds

    @property
    def state(self):
        """The newest state of the samples kept (None before the first fix; a step cut
        short by Ctrl-C may have left its own sample's unfilled)."""
        return next((s for s in reversed(self._states) if s is not None), None)

    def add_fix(self, fix: Fix) -> None:
        """A fix that has just become available; it is applied at the next sample."""
        self._pending.append(fix)

    def gap(self) -> None:
        """The samples broke off: forget the history; the filter restarts at the next
        fix taken after the gap."""
        for buf in (self._ts, self._raw, self._clip, self._gyro, self._acc, self._states,
                    self._known):  # fmt: skip
            buf.clear()
        self._last_good = self._prev_a = None
        self._burst_end = None

    def _level(self, ax: int, sign: float) -> float | None:
        """The clip level of an axis on one side: its own once learned; before that, a
        level learned on another axis or side less SAT_OTHER (a calibrated gyro's
        levels differ by its offsets and scale factors); None while none is known."""
        own = self._ranges[ax, 0 if sign >= 0 else 1]
        if np.isfinite(own):
            return float(own)
        if np.any(np.isfinite(self._ranges)):
            return float(np.nanmin(self._ranges)) * (1 - SAT_OTHER)
        return None

    def _clipped(self, g: np.ndarray) -> np.ndarray:
        """Which axes of a raw reading (already in the buffer) sit at the gyro's range.
        Unless given, each axis's level on each side is learned from its first flat
        top: SAT_RUN samples within SAT_BAND of each other at SAT_MIN_DPS or more,
        where the line through the SAT_RUN samples before them points at least
        SAT_BEYOND past them at the run's middle (a smooth peak levels off before its
        top; a clipped signal hits its flat top at full slope). A calibrated gyro's
        clipped readings scatter a little with the other axes, hence the band."""
        g = np.asarray(g, float)
        n = len(self._raw)
        need = 2 * SAT_RUN
        if n >= need and not np.all(np.isfinite(self._ranges)):
            for ax in range(3):
                run = np.array([r[ax] for r in self._raw[n - SAT_RUN :]])
                level = float(np.abs(run).max())
                side = 0 if run[-1] >= 0 else 1
                if (
                    np.isfinite(self._ranges[ax, side])
                    or level < math.radians(SAT_MIN_DPS)
                    or not np.all(np.sign(run) == np.sign(run[-1]))
                    or not np.all(np.abs(run) >= level * (1 - SAT_BAND))
                ):
                    continue
                before = np.array([r[ax] for r in self._raw[n - need : n - SAT_RUN]])
                tb = np.array(self._ts[n - need : n - SAT_RUN])
                c = np.polyfit(tb - tb[-1], before, 1)
                pred = abs(float(np.polyval(c, self._ts[n - 2] - tb[-1])))
                if pred >= level * (1 + SAT_BEYOND):
                    self._ranges[ax, side] = level
                    for j in range(n - SAT_RUN, n - 1):
                        self._clip[j] = self._clip[j].copy()
                        self._clip[j][ax] = abs(self._raw[j][ax]) >= level * (1 - SAT_BAND)
        out = np.zeros(3, bool)
        for ax in range(3):
            lvl = self._level(ax, g[ax])
            out[ax] = lvl is not None and abs(g[ax]) >= lvl * (1 - SAT_BAND)
        return out

    def _make_reading(self, j: int, sat_sigma: np.ndarray) -> np.ndarray:
        """The reading over the interval ending at sample j: the mean of its two ends
        (trapezoid) and its rate of change."""
        g = self._raw[j]
        if j == 0:
            return reading(g, np.zeros(3), sat_sigma)
        dt = self._ts[j] - self._ts[j - 1]
        g0 = self._raw[j - 1]
        return reading(0.5 * (g + g0), (g - g0) / dt, sat_sigma)

    def _reconstruct(self, last: int, both: bool) -> int | None:
        """Reconstruct the clipped samples of the flat top that ends at or before
        sample ``last`` (rewriting their readings); the first index rewritten."""
        # only the flat top and the few samples on either side of it are looked at
        beg_all = last
        while beg_all > 0 and self._clip[beg_all - 1].any():
            beg_all -= 1
        lo, hi = max(0, beg_all - 4), min(len(self._ts), last + 4)
        clip = np.array(self._clip[lo:hi])
        ts = np.array(self._ts[lo:hi])
        raw = np.array(self._raw[lo:hi])
        loc = last - lo
        first = None
        excess = np.zeros(3)
        lvl = np.zeros(3)
        for ax in range(3):
            c = clip[:, ax]
            if not c[loc]:
                continue
            end = beg = loc
            while beg > 0 and c[beg - 1]:
                beg -= 1
            before = np.arange(max(0, beg - 4), beg)
            before = before[~c[before]]
            after = np.arange(end + 1, min(len(c), end + 4)) if both else np.array([], int)
            after = after[~c[after]] if len(after) else after
            known = np.concatenate([before, after]).astype(int)
            if len(known) == 0:
                continue
            at = np.arange(beg, end + 1)
            sign = float(np.sign(raw[end, ax]))
            lvl[ax] = self._level(ax, sign)
            vals = declip(ts, raw[:, ax], known, ts[at], lvl[ax], sign)
            # the farther the rebuilt peak reaches past the range, the less it is known
            excess[ax] = float(np.abs(vals).max()) - lvl[ax]
            for i, v in zip(at + lo, vals, strict=True):
                self._raw[i] = self._raw[i].copy()
                self._raw[i][ax] = v
            first = beg + lo if first is None else min(first, beg + lo)
        if first is None:
            return None
        # a reconstruction's error is much the same all through its flat top: the m-th
        # interval of a flat top adds (2m - 1) sigma^2 dt^2, so that m of them add
        # (m sigma dt)^2, as one error held for the whole flat top would
        sig = np.maximum((SAT_SIGMA_BOTH if both else SAT_SIGMA) * lvl,
                         (0.5 if both else 1.0) * excess)  # fmt: skip
        run = np.zeros(3)
        for j in range(first, min(len(self._ts), last + 2)):
            hit = self._clip[j] | (self._clip[j - 1] if j > 0 else False)
            run = np.where(hit, run + 1, 0)
            s_ax = np.where(hit, sig * np.sqrt(np.maximum(2 * run - 1, 0)), 0.0)
            self._gyro[j] = self._make_reading(j, s_ax)
        return first

    def _find_rest(self, t_end: float) -> None:
        """The rest segment at the start of the buffer (the samples up to ``t_end``,
        when the first fix arrives), if any."""
        ts = np.array(self._ts)
        n_max = int(np.searchsorted(ts, min(t_end, ts[0] + REST_MAX_S), side="right"))
        if n_max < 10:
            return
        raw = np.array(self._raw[:n_max])
        band = math.radians(REST_BAND_DPS)
        med = np.median(raw[: max(10, n_max // 4)], axis=0)
        out = np.nonzero(np.any(np.abs(raw - med) > band, axis=1))[0]
        n = int(out[0]) if len(out) else n_max
        if n < 10 or ts[n - 1] - ts[0] < REST_MIN_S:
            return
        seg = raw[:n]
        self.rest = (seg.mean(axis=0), seg.std(axis=0, ddof=1), n)
        if hasattr(self.model, "with_rest"):
            self.model = self.model.with_rest(*self.rest)

    def step(self, t: float, g: np.ndarray, a: np.ndarray | None, *, gap: bool = False,
             index: int | None = None) -> FusedSample:  # fmt: skip
        """Take the inertial sample at ``t`` (gyro rad/s (3,), accel m/s^2 (2,) or
        None) and return the fused state after it. Steps: 1. the sample checked and
        buffered (a fault replaced by the last good one, a saturated reading
        reconstructed); 2. the fixes that came since, in exposure order; 3. a replay
        from the earliest sample they (or a rewritten reading) touch; 4. a restart on
        the fixes after too many refused in a row; 5. the history beyond its window
        forgotten."""
        k = self._index if index is None else index
        self._index = k + 1
        if self._ts and not gap and t <= self._ts[-1]:
            # a clock that steps back: this sample is refused, the state stands
            return FusedSample(k, t, self._states[-1], self.n_applied, ("imu_time_back",))
        warnings: list[str] = []
        if gap:
            warnings.append("imu_gap")
            self.gap()
        clipped, dirty = self._take_sample(t, *self._checked(g, a, warnings))
        new = self._take_fixes(t, warnings)
        # replay from the first sample at or after the earliest new fix (else the newest
        # sample, or the first one whose reading was rewritten)
        start = dirty
        if new:
            start = min(start, bisect.bisect_left(self._ts, min(f.time_s for f in new)))
        nis_new: list[float] = []
        if not self._replay(start, new, warnings, nis_new):
            if self._known and self.aligned is None:
                warnings.append("aligning_clocks")
            self._forget(t)  # an IMU with no fix for hours keeps only its history
            return FusedSample(k, t, None, self.n_applied, (*warnings, "no_fix_yet"))
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
        st = self._states[-1]
        if getattr(st, "saturated", False) or clipped.any():
            warnings.append("gyro_saturated")
        if getattr(st, "disputed", False):
            warnings.append("fix_disputed")
        if not getattr(st, "confirmed", True):
            warnings.append("fix_unconfirmed")
        return FusedSample(k, t, st, self.n_applied, tuple(warnings), tuple(nis_new))

    def _checked(self, g: np.ndarray, a: np.ndarray | None, warnings: list[str]):
        """Step 1a: a faulty sample (beyond the limits) is replaced by the last good
        one (or zeros) and flagged."""
        if is_faulty(g, a, self.limits):
            warnings.append("imu_fault")
            if self._last_good is not None:
                return self._last_good
            return np.zeros(3), (np.zeros(2) if a is not None else None)
        self._last_good = (g, a)
        return g, a

    def _take_sample(self, t: float, g: np.ndarray, a: np.ndarray | None):
        """Step 1b: buffer the sample; reconstruct the readings of a flat top (from
        before it while it lasts, from both sides three samples after it ends). The
        reading's clipped axes and the first buffered sample whose reading changed."""
        ts, acc = self._ts, self._acc
        ts.append(t)
        self._raw.append(np.asarray(g, float))
        self._clip.append(np.zeros(3, bool))
        clipped = self._clip[-1] = self._clipped(g)
        # the accelerometer over the interval: the mean of its two ends (trapezoid)
        acc.append(0.5 * (a + self._prev_a) if a is not None and self._prev_a is not None
                   else a)  # fmt: skip
        self._prev_a = a
        self._states.append(None)
        j_new = len(ts) - 1
        self._gyro.append(self._make_reading(j_new, np.zeros(3)))
        dirty = j_new
        if clipped.any():
            self.n_saturated += 1
            first = self._reconstruct(j_new, both=False)
            if first is not None:
                dirty = min(dirty, first)
            self._burst_end = None
        elif len(self._clip) > 1 and self._clip[-2].any():
            self._burst_end = 0
        if self._burst_end is not None:
            self._burst_end += 1
            if self._burst_end >= 3 or j_new == 0:
                first = self._reconstruct(max(j_new - 3, 0), both=True)
                if first is not None:
                    dirty = min(dirty, first)
                self._burst_end = None
        return clipped, dirty

    def _take_fixes(self, t: float, warnings: list[str]) -> list[Fix]:
        """Step 2: the fixes that reached us since the last sample, known from now on
        in exposure order; one older than the history or from the future is flagged
        and dropped."""
        ts, new = self._ts, []
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
        ts, gyro, acc, states, known = self._ts, self._gyro, self._acc, self._states, self._known
        s = states[start - 1] if start > 0 else None
        if s is not None:
            t_s = ts[start - 1]
        else:
            # not initialised, or restarting: from the earliest known fix in the buffer
            init = known[0][2] if known else None
            if init is None:
                return False
            if not self._initialised:
                if not self._align():
                    return False
                self._initialised = True
                self._find_rest(ts[-1])
                init = known[0][2]
            s, t_s = self.model.init(init), init.time_s
            if any(init is f for f in new):
                self.n_applied += 1
            start = bisect.bisect_left(ts, t_s)
            for i in range(start):
                states[i] = None
        model = self.model
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
                        if self._rejected_streak == 0:
                            self._refused_since = f.time_s
                        self._rejected_streak += 1
            if ts[j] > t_s:
                s = model.propagate(s, gyro[j], acc[j], ts[j] - t_s)
                t_s = ts[j]
            states[j] = s
        return True

    def _align(self) -> bool:
        """Before the filter starts, with a model that can (PlanarModel.align): the
        fixes' time offset from their poses against the IMU's. False while it waits;
        once found, the fixes are applied shifted by it, and the model's prior on the
        offset is its sigma (at least ALIGN_PRIOR_MIN).

        It tries on the first ALIGN_WAIT_S of fixes, whenever they arrive (so that the
        start does not depend on the order in which they came), and then, while the
        platform moves, on the latest ALIGN_WAIT_S: a moving platform's rows with the
        offset unknown would be wrong with a small sigma (a stream 300 ms late with
        1 ms of jitter: rows 45 sigma off). It starts without when the platform is at
        rest after ALIGN_WAIT_S (the offset does not matter then; the filter learns it
        once it moves), or at once when the fixes come too sparse to align (fewer than
        ALIGN_FEW_FIXES in ALIGN_WAIT_S: LuVeX's 1.7 Hz). An alignment is taken once the
        try before it found the same (ALIGN_CONFIRM, ALIGN_AGREE)."""
        align = getattr(self.model, "align", None)
        known = self._known
        if align is None or self.aligned is not None or not known:
            return True
        if self.model.time_offset_sigma <= 0.0:  # the offset is held (known)
            self.aligned = (math.nan, math.nan)
            return True
        if self._ts[-1] < self._align_next:
            return False
        self._align_next = self._ts[-1] + ALIGN_EVERY_S
        waited = self._ts[-1] - known[0][0]
        if waited / len(known) >= ALIGN_WAIT_S / ALIGN_FEW_FIXES:
            self.aligned = (math.nan, math.nan)
            return True
        if waited < ALIGN_WAIT_S:
            t0 = known[0][0]
            fixes = [f for t, _, f in known if t <= t0 + ALIGN_WAIT_S]
        else:
            t1 = known[-1][0]
            fixes = [f for t, _, f in known if t >= t1 - ALIGN_WAIT_S]
        # with the samples they can reach
        lo = bisect.bisect_left(self._ts, fixes[0].time_s - SHIFT_MAX - 0.05)
        hi = bisect.bisect_right(self._ts, fixes[-1].time_s + 0.05)
        ts = np.array(self._ts[lo:hi])
        rate = np.array([g[0][2] for g in self._gyro[lo:hi]])
        acc = self._acc[lo:hi]
        accel = None if any(a is None for a in acc) else np.array(acc)
        found = align(ts, rate, accel, fixes)
        earlier = self._align_tries[-ALIGN_CONFIRM:] if ALIGN_CONFIRM else []
        self._align_tries = [*earlier, found]
        if found is not None and not _agree(found, earlier):
            found = None  # not yet confirmed: as if none were found
        if found is None:
            if waited < ALIGN_WAIT_S or _moving(fixes):
                return False
            self.aligned = (math.nan, math.nan)
            return True
        tau, sigma = found
        self.aligned = found
        prior = max(sigma, -tau, ALIGN_PRIOR_MIN)
        self.model = replace(self.model, time_offset_sigma=prior)
        self._move_fixes(max(tau, 0.0))
        return True

    def _move_fixes(self, shift: float) -> None:
        """The known fixes applied ``shift`` before their stated time, as the fixes that
        come from now on (before the filter starts: nothing to replay)."""
        self.shift = shift
        ts = self._ts
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
        st = self._states[-1] if self._states else None
        if offset is None or st is None:
            return
        tau, sigma = offset(st)
        shift = min(max(tau, 0.0), SHIFT_MAX)
        if sigma <= SHIFT_SIGMA and abs(shift - self.shift) >= SHIFT_STEP:
            self.shift = shift

    def _restart_on(self, latest: Fix) -> None:
        """Step 4: start again from ``latest`` (keeping what the model learned of the
        sensor, where it can) and replay the samples after it."""
        ts, gyro, acc, states, model = self._ts, self._gyro, self._acc, self._states, self.model
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
        ts = self._ts
        cut = bisect.bisect_left(ts, t - self.history_s)
        if cut > 0:
            for buf in (ts, self._raw, self._clip, self._gyro, self._acc, self._states):
                del buf[:cut]
            self._known[:] = [x for x in self._known if x[0] >= ts[0]]


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
    given to the engine at the first sample at or after its ``available_s``."""
    if engine is None:
        engine = Fusion(model, limits=limits, history_s=history_s, gyro_range_dps=gyro_range_dps)
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
