"""A gyro at its range: which readings are clipped, and their reconstruction.

A clipped reading says only that the rate was at least the range; integrated as read,
it turns the attitude too little for as long as the clipping lasts. The engine
(visvec.fuse.replay.Fusion) asks `Saturation` after each sample which axes sit at the
range, and the samples of a flat top are rewritten by a smooth reconstruction
(`declip`), with a sigma: live from the samples before it, and again from both sides
once it ends.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from visvec.fuse.history import History

SAT_MIN_DPS = 100.0  # a flat top below this is not a gyro's range
SAT_BAND = 0.01  # readings within this share of the range are at it
SAT_SIGMA = 0.25  # 1-sigma of a saturated reading's reconstruction, in ranges (live)
SAT_SIGMA_BOTH = 0.1  # ... once the samples after the flat top are in
# A range is learned (no range declared) only from evidence a gyro that does not clip
# cannot produce (Saturation.clipped). A flat top starts where one step of SAT_ENTRY
# noise-step sigmas or more (sqrt(2) sigma, sigma the gyro's sample noise) reaches
# SAT_MIN_DPS or more, at the largest reading so far on that axis and side, and the
# next SAT_RUN - 1 readings stay within SAT_BAND of it (a clipped signal meets its flat
# top at full slope; a smooth peak levels off gradually, an air-bearing platform's
# slews ramp); it lasts while they do. A range is the level of SAT_CONFIRM or more flat
# tops that agree within SAT_BAND, still the record's extreme, whose steps (at least
# SAT_STEPS of them) are quieter than the gyro's noise could be by chance: so many of
# them within SAT_QUIET of a noise step's sigma (a white noise step is, with
# probability p0 = erf(SAT_QUIET / sqrt(2)): 0.38) that a binomial(m, p0) count reaches
# it with a probability below SAT_P (a sign test: robust to the few large steps where a
# flat top starts or ends partly clipped). A gyro that turns at a steady rate (a slew at
# a commanded rate, a free spin) carries its noise on every step; one that is clipped
# reads its range, scattered only by its calibration's cross-axis terms (RepoIMU's
# T-stick: steps of 0.0-0.3 deg/s where its noise steps by about 0.5). Checked on every
# shared recording (benchmarks/fusion_recordings.py, tests/fuse/test_saturation.py): no
# range on any BROAD trial nor on RepoIMU's trials that stay within range; RepoIMU
# Test05 and Test10 found on x, on both sides
SAT_RUN = 3
SAT_ENTRY = 8.0
SAT_CONFIRM = 2
SAT_STEPS = 20
SAT_QUIET = 0.5
SAT_P = 1e-6
SAT_TOPS_KEPT = 200  # the flat tops weighed, per axis and side: the latest
# A first clip, before any range is known on its axis and side: a flat top still open
# whose steps are already quieter than the gyro's noise would make them with a
# probability below SAT_MAYBE_P (the sign test above, on this top alone) may be the
# gyro at its range. Nothing is rewritten on this evidence: its readings are kept as
# read and each carries the extra sigma SAT_SIGMA_MAYBE times the top's level, held
# through the top as a reconstruction's is (rows: gyro_saturated). A reading at the
# range says the rate was at least that; a clipped peak reaches at most about twice it
# (declip's cap), and an excess uniform over [0, range] has an RMS of range / sqrt(3).
# SAT_MAYBE_P is looked at after every step of every open top: 1e-4 (ten quiet steps in
# a row) leaves 200 slews at one commanded rate with a real gyro's noise unwidened,
# where 1e-3 widens one in a hundred. Checked on every shared recording
# (tests/fuse/test_saturation.py): RepoIMU Test05's first flat top, widened from its
# tenth step (its range is learned only from a later one); Test06's one flat top (y at
# -408 deg/s for 18 samples, 14 of 17 steps quiet) with the engine's 10 s of history;
# no BROAD trial and no RepoIMU trial within its range
SAT_MAYBE_P = 1e-4
SAT_SIGMA_MAYBE = 1.0 / math.sqrt(3.0)
# the gyro's sample noise (rad/s) per axis: every NOISE_EVERY samples, over the last
# NOISE_SPAN, the median absolute second difference (Gaussian: 0.6745 sqrt(6) sigma) of
# each NOISE_BLOCK samples that stay below SAT_MIN_DPS on that axis (no flat top there),
# the quietest quarter's (the sensor's noise, not the motion's): the lower quartile of
# the blocks (of all blocks when none stays below: a gyro that never rests; the
# motion then widens it); no range is learned before NOISE_BLOCK samples
NOISE_EVERY = 200
NOISE_SPAN = 2000
NOISE_BLOCK = 50
NOISE_MIN_DPS = 0.05  # a quantised gyro's steps at rest may all be zero
# a reading with no axis at the range: one shared flag array, never written (a reading
# flagged later gets its own copy)
NOT_CLIPPED = np.zeros(3, bool)
NOT_CLIPPED.flags.writeable = False


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


def binom_sf(k: int, m: int, p: float) -> float:
    """The probability that a binomial(m, p) count is k or more."""
    if k <= 0:
        return 1.0
    lp, lq = math.log(p), math.log1p(-p)
    total = 0.0
    for i in range(k, m + 1):
        total += math.exp(math.lgamma(m + 1) - math.lgamma(i + 1) - math.lgamma(m - i + 1)
                          + i * lp + (m - i) * lq)  # fmt: skip
    return min(total, 1.0)


def _quiet_chance(steps: list[float], sigma: float) -> float:
    """How likely a gyro whose sample noise is ``sigma`` makes at least as many of a flat
    top's ``steps`` as quiet (within SAT_QUIET of a noise step's sigma; the sign test in
    the comment of SAT_RUN ... SAT_P)."""
    width = SAT_QUIET * math.sqrt(2.0) * sigma
    quiet = sum(abs(d) <= width for d in steps)
    return binom_sf(quiet, len(steps), math.erf(SAT_QUIET / math.sqrt(2.0)))


class Saturation:
    """The gyro's clip levels (rad/s) per axis and side, and the flat tops found at
    them, on the engine's `History`.

    A range is known, not guessed: declared (``gyro_range_dps``: `--gyro-range-dps`,
    the rig's ``[imu] gyro_range_dps``, the IMU file's header), or learned on one axis
    and side only from flat tops a gyro that does not clip cannot produce (`clipped`);
    no axis takes another's level. A reading beyond a declared range (by more than
    SAT_BAND) is beyond what the gyro can read: `beyond` says so, and the engine refuses
    it.

    Parameters
    ----------
    history : History
        The engine's samples, whose readings a reconstruction rewrites.
    gyro_range_dps : float or None
        The gyro's range (deg/s) on every axis, if known; else it is learned.
    """

    def __init__(self, history: History, gyro_range_dps: float | None = None) -> None:
        self.h = history
        self.declared = math.radians(gyro_range_dps) if gyro_range_dps else None
        # clip levels (rad/s) per axis, positive and negative side; nan: not known
        self.ranges = np.full((3, 2), self.declared or math.nan)
        self._burst_end: int | None = None  # samples since a flat top ended
        self.n_saturated = 0
        self.n_beyond = 0  # readings beyond the declared range
        # per axis and side: the largest reading seen, and the flat tops' levels
        self._extreme = np.zeros((3, 2))
        self._tops: list[list[list]] = [[[], []] for _ in range(3)]  # (level, steps)
        self._open: list[tuple | None] = [None, None, None]  # (side, level, last, steps)
        self.learned: list[tuple[int, int, float]] = []  # (axis, side, level) as found
        self._noise: np.ndarray | None = None  # rad/s per axis
        self._noise_at = 0
        self._found = False  # a range learned at the newest sample
        self.n_maybe = 0  # readings that may have been at a range not yet known
        self._maybe: list[list | None] = [None, None, None]  # the open top's steps, once quiet
        self._all_known = bool(np.all(np.isfinite(self.ranges)))

    def reset(self) -> None:
        """The samples broke off (a gap): no flat top is open."""
        self._burst_end = None
        self._open = [None, None, None]
        self._maybe = [None, None, None]

    def level(self, ax: int, sign: float) -> float | None:
        """The clip level of an axis on one side (rad/s), or None while none is
        known."""
        own = self.ranges[ax, 0 if sign >= 0 else 1]
        return float(own) if np.isfinite(own) else None

    def beyond(self, g: np.ndarray) -> bool:
        """Whether a reading lies beyond the declared range (by more than SAT_BAND)."""
        if self.declared is None:
            return False
        lim = self.declared * (1 + SAT_BAND)
        return abs(float(g[0])) > lim or abs(float(g[1])) > lim or abs(float(g[2])) > lim

    def noise(self) -> np.ndarray | None:
        """The gyro's sample noise per axis (rad/s; the comment of NOISE_EVERY ...
        NOISE_BLOCK); None before it is known."""
        h = self.h
        self._noise_at += 1
        if self._noise_at < NOISE_EVERY and self._noise is not None:
            return self._noise
        n = len(h.raw)
        if n < 2 * NOISE_BLOCK:
            return self._noise
        self._noise_at = 0
        m = min(n, NOISE_SPAN) // NOISE_BLOCK * NOISE_BLOCK
        raw = np.array(h.raw[n - m :]).reshape(-1, NOISE_BLOCK, 3)
        calm = np.abs(raw).max(axis=1) < math.radians(SAT_MIN_DPS)  # (blocks, 3)
        d2 = np.abs(np.diff(raw, 2, axis=1))
        sig = np.median(d2, axis=1) / (0.6745 * math.sqrt(6.0))  # (blocks, 3)
        new = np.array([np.percentile(sig[calm[:, k], k] if calm[:, k].any() else sig[:, k], 25)
                        for k in range(3)])  # fmt: skip
        new = np.maximum(new, math.radians(NOISE_MIN_DPS))
        self._noise = new
        return self._noise

    def clipped(self, g: np.ndarray) -> np.ndarray:
        """Which axes of a raw reading (the newest in the history) sit at the gyro's
        range, learning a range from the evidence where none is known (the rule in
        the comment of SAT_RUN ... SAT_P)."""
        h = self.h
        gl = [float(x) for x in g]  # floats: a sample's checks in Python's arithmetic
        n = len(h.raw)
        ext = self._extreme
        for ax in range(3):
            side = 0 if gl[ax] >= 0 else 1
            if abs(gl[ax]) > ext[ax, side]:
                ext[ax, side] = abs(gl[ax])
        if not self._all_known:
            noise = self.noise()
            if noise is not None and n >= SAT_RUN + 2:
                low = math.radians(SAT_MIN_DPS)
                for ax in range(3):
                    # a flat top starts (or goes on) only at SAT_MIN_DPS or more
                    if self._open[ax] is not None or abs(gl[ax]) >= low:
                        self._follow_top(ax, n, float(noise[ax]))
        if not self._any_known:
            return NOT_CLIPPED
        out = np.zeros(3, bool)
        for ax in range(3):
            lvl = self.level(ax, gl[ax])
            out[ax] = lvl is not None and abs(gl[ax]) >= lvl * (1 - SAT_BAND)
        return out if out.any() else NOT_CLIPPED

    @property
    def _any_known(self) -> bool:
        return self.declared is not None or bool(self.learned)

    def _follow_top(self, ax: int, n: int, sigma: float) -> None:
        """The flat top of axis ``ax`` at the newest sample: one that goes on gains a
        step, one that ends is weighed (`_weigh`), and a new one may start."""
        raw = self.h.raw
        x = raw[n - 1][ax]
        top = self._open[ax]
        if top is not None:
            side, level0, prev, steps = top
            sign = 1.0 if side == 0 else -1.0
            v = sign * x
            if v > 0 and abs(v - level0) <= SAT_BAND * level0:
                steps.append(v - prev)
                self._open[ax] = (side, max(level0, v), v, steps)
                return
            self._open[ax] = None
            self._weigh(ax, side, level0, steps, sigma, n)
        x0 = float(raw[n - SAT_RUN][ax])
        sign = 1.0 if x0 >= 0 else -1.0
        side = 0 if sign > 0 else 1
        level = sign * x0
        # the cheap tests first: most readings are no flat top's start
        if level < math.radians(SAT_MIN_DPS) or level < self._extreme[ax, side] * (1 - SAT_BAND):
            return
        if math.isfinite(self.ranges[ax, side]):
            return
        a = [sign * raw[j][ax] for j in range(n - SAT_RUN - 1, n)]
        if level - a[0] < SAT_ENTRY * math.sqrt(2.0) * sigma or any(
            abs(v - level) > SAT_BAND * level for v in a[2:]
        ):
            return
        self._open[ax] = (side, max(a[1:]), a[-1], [a[k + 1] - a[k] for k in range(1, len(a) - 1)])

    def _weigh(self, ax: int, side: int, level: float, steps: list[float], sigma: float,
               n: int) -> None:  # fmt: skip
        """A flat top that ended: kept; the tops that agree with it on their level
        become the range when their steps are too quiet for the gyro's noise (the rule
        in the comment of SAT_RUN ... SAT_P). The history's readings at it are then
        flagged (take() rebuilds them)."""
        tops = self._tops[ax][side]
        tops.append((level, steps))
        del tops[:-SAT_TOPS_KEPT]  # a run of hours keeps the evidence of its latest
        agree = [(lv, st) for lv, st in tops if abs(lv - level) <= SAT_BAND * max(lv, level)]
        m = sum(len(st) for _, st in agree)
        if len(agree) < SAT_CONFIRM or m < SAT_STEPS:
            return
        top_level = max(lv for lv, _ in agree)
        chance = _quiet_chance([d for _, st in agree for d in st], sigma)
        if chance >= SAT_P or self._extreme[ax, side] > top_level * (1 + SAT_BAND):
            return
        self.ranges[ax, side] = top_level
        self.learned.append((ax, side, top_level))
        self._all_known = bool(np.all(np.isfinite(self.ranges)))
        sign = 1.0 if side == 0 else -1.0
        h = self.h
        for j in range(n):
            if sign * h.raw[j][ax] >= top_level * (1 - SAT_BAND):
                self.n_saturated += not h.clip[j].any()
                h.clip[j] = h.clip[j].copy()
                h.clip[j][ax] = True
        self._found = True

    def take(self) -> tuple[np.ndarray, int]:
        """After the newest sample was added to the history (its clip flags not yet
        set): its clipped axes, and the first sample whose reading changed (the
        newest, or the start of a flat top reconstructed from before it while it lasts,
        or from both sides three samples after it ends; all the flat tops kept, when a
        range has just been learned)."""
        h = self.h
        self._found = False
        clipped = h.clip[-1] = self.clipped(h.raw[-1])
        j_new = len(h.ts) - 1
        dirty = j_new
        if self._found:
            # a range just learned: the flat tops the history holds before this one
            for last in self._top_ends(j_new):
                first = self.reconstruct(last, both=True)
                if first is not None:
                    dirty = min(dirty, first)
        if clipped is NOT_CLIPPED and not self._all_known:
            first = self._maybe_clipped(j_new)
            if first is not None:
                dirty = min(dirty, first)
        if clipped is not NOT_CLIPPED:
            self.n_saturated += 1
            first = self.reconstruct(j_new, both=False)
            if first is not None:
                dirty = min(dirty, first)
            self._burst_end = None
        elif len(h.clip) > 1 and h.clip[-2] is not NOT_CLIPPED and h.clip[-2].any():
            self._burst_end = 0
        if self._burst_end is not None:
            self._burst_end += 1
            if self._burst_end >= 3 or j_new == 0:
                first = self.reconstruct(max(j_new - 3, 0), both=True)
                if first is not None:
                    dirty = min(dirty, first)
                self._burst_end = None
        return clipped, dirty

    def _maybe_clipped(self, j_new: int) -> int | None:
        """The open flat tops that may be a first clip (the rule in the comment of
        SAT_MAYBE_P): their readings' extra sigma set, from the top's first sample on
        when it has just become quiet enough; the first sample whose reading changed."""
        first = None
        for ax in range(3):
            top = self._open[ax]
            if top is None:
                self._maybe[ax] = None
                continue
            side, level, _, steps = top
            if self._maybe[ax] is not steps:
                self._maybe[ax] = None  # a top that ended, or this one not yet quiet
                if _quiet_chance(steps, float(self._noise[ax])) >= SAT_MAYBE_P:
                    continue
                self._maybe[ax] = steps  # this top, from its first sample
                start = max(0, j_new - len(steps))
            else:
                start = j_new
            first = start if first is None else min(first, start)
        if first is None:
            return None
        h = self.h
        for j in range(first, j_new + 1):
            sig = np.zeros(3)
            for ax in range(3):
                steps = self._maybe[ax]
                if steps is None:
                    continue
                m = j - (j_new - len(steps)) + 1  # the m-th interval of this top
                if m >= 1:
                    sig[ax] = SAT_SIGMA_MAYBE * self._open[ax][1] * math.sqrt(2 * m - 1)
            if sig.any():
                self.n_maybe += not h.gyro[j][2].any()  # each reading counted once
                h.gyro[j] = h.reading(j, sig)
        return first

    def _top_ends(self, j_new: int) -> list[int]:
        """The last samples of the flat tops flagged in the history that ended before
        the newest sample's own (which take() reconstructs as it goes)."""
        h = self.h
        ends = []
        j = j_new
        while j > 0 and h.clip[j].any():
            j -= 1  # the open flat top, if any
        for i in range(j):
            if h.clip[i].any() and not h.clip[i + 1].any():
                ends.append(i)
        return ends

    def reconstruct(self, last: int, both: bool) -> int | None:
        """Reconstruct the clipped samples of the flat top that ends at or before
        sample ``last`` (rewriting their readings); the first index rewritten."""
        h = self.h
        # only the flat top and the few samples on either side of it are looked at
        beg_all = last
        while beg_all > 0 and h.clip[beg_all - 1].any():
            beg_all -= 1
        lo, hi = max(0, beg_all - 4), min(len(h.ts), last + 4)
        clip = np.array(h.clip[lo:hi])
        ts = np.array(h.ts[lo:hi])
        raw = np.array(h.raw[lo:hi])
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
            lvl[ax] = self.level(ax, sign)
            vals = declip(ts, raw[:, ax], known, ts[at], lvl[ax], sign)
            # the farther the rebuilt peak reaches past the range, the less it is known
            excess[ax] = float(np.abs(vals).max()) - lvl[ax]
            for i, v in zip(at + lo, vals, strict=True):
                h.raw[i] = h.raw[i].copy()
                h.raw[i][ax] = v
            first = beg + lo if first is None else min(first, beg + lo)
        if first is None:
            return None
        # a reconstruction's error is much the same all through its flat top: the m-th
        # interval of a flat top adds (2m - 1) sigma^2 dt^2, so that m of them add
        # (m sigma dt)^2, as one error held for the whole flat top would
        sig = np.maximum((SAT_SIGMA_BOTH if both else SAT_SIGMA) * lvl,
                         (0.5 if both else 1.0) * excess)  # fmt: skip
        run = np.zeros(3)
        for j in range(first, min(len(h.ts), last + 2)):
            hit = h.clip[j] | (h.clip[j - 1] if j > 0 else False)
            run = np.where(hit, run + 1, 0)
            s_ax = np.where(hit, sig * np.sqrt(np.maximum(2 * run - 1, 0)), 0.0)
            h.gyro[j] = h.reading(j, s_ax)
        return first
