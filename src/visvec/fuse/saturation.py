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
SAT_BAND = 0.005  # readings within this share of the range are at it
SAT_RUN = 3  # a flat top: this many samples in the band ...
SAT_BEYOND = 0.1  # ... where the samples before point this far past it
SAT_OTHER = 0.03  # an axis or side not yet seen clipped: another's level, less this
SAT_SIGMA = 0.25  # 1-sigma of a saturated reading's reconstruction, in ranges (live)
SAT_SIGMA_BOTH = 0.1  # ... once the samples after the flat top are in


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


class Saturation:
    """The gyro's clip levels (rad/s) per axis and side, and the flat tops found at
    them, on the engine's `History`.

    Parameters
    ----------
    history : History
        The engine's samples, whose readings a reconstruction rewrites.
    gyro_range_dps : float or None
        The gyro's range (deg/s) on every axis, if known; else it is learned.
    """

    def __init__(self, history: History, gyro_range_dps: float | None = None) -> None:
        self.h = history
        # clip levels (rad/s) per axis, positive and negative side; nan: not known
        self.ranges = np.full((3, 2), math.radians(gyro_range_dps) if gyro_range_dps
                              else math.nan)  # fmt: skip
        self._burst_end: int | None = None  # samples since a flat top ended
        self.n_saturated = 0

    def reset(self) -> None:
        """The samples broke off (a gap): no flat top is open."""
        self._burst_end = None

    def level(self, ax: int, sign: float) -> float | None:
        """The clip level of an axis on one side: its own once learned; before that, a
        level learned on another axis or side less SAT_OTHER (a calibrated gyro's
        levels differ by its offsets and scale factors); None while none is known."""
        own = self.ranges[ax, 0 if sign >= 0 else 1]
        if np.isfinite(own):
            return float(own)
        if np.any(np.isfinite(self.ranges)):
            return float(np.nanmin(self.ranges)) * (1 - SAT_OTHER)
        return None

    def clipped(self, g: np.ndarray) -> np.ndarray:
        """Which axes of a raw reading (already in the history) sit at the gyro's range.
        Unless given, each axis's level on each side is learned from its first flat
        top: SAT_RUN samples within SAT_BAND of each other at SAT_MIN_DPS or more,
        where the line through the SAT_RUN samples before them points at least
        SAT_BEYOND past them at the run's middle (a smooth peak levels off before its
        top; a clipped signal hits its flat top at full slope). A calibrated gyro's
        clipped readings scatter a little with the other axes, hence the band."""
        h = self.h
        g = np.asarray(g, float)
        n = len(h.raw)
        need = 2 * SAT_RUN
        if n >= need and not np.all(np.isfinite(self.ranges)):
            for ax in range(3):
                run = np.array([r[ax] for r in h.raw[n - SAT_RUN :]])
                level = float(np.abs(run).max())
                side = 0 if run[-1] >= 0 else 1
                if (
                    np.isfinite(self.ranges[ax, side])
                    or level < math.radians(SAT_MIN_DPS)
                    or not np.all(np.sign(run) == np.sign(run[-1]))
                    or not np.all(np.abs(run) >= level * (1 - SAT_BAND))
                ):
                    continue
                before = np.array([r[ax] for r in h.raw[n - need : n - SAT_RUN]])
                tb = np.array(h.ts[n - need : n - SAT_RUN])
                c = np.polyfit(tb - tb[-1], before, 1)
                pred = abs(float(np.polyval(c, h.ts[n - 2] - tb[-1])))
                if pred >= level * (1 + SAT_BEYOND):
                    self.ranges[ax, side] = level
                    for j in range(n - SAT_RUN, n - 1):
                        h.clip[j] = h.clip[j].copy()
                        h.clip[j][ax] = abs(h.raw[j][ax]) >= level * (1 - SAT_BAND)
        out = np.zeros(3, bool)
        for ax in range(3):
            lvl = self.level(ax, g[ax])
            out[ax] = lvl is not None and abs(g[ax]) >= lvl * (1 - SAT_BAND)
        return out

    def take(self) -> tuple[np.ndarray, int]:
        """After the newest sample was added to the history (its clip flags not yet
        set): its clipped axes, and the first sample whose reading changed (the
        newest, or the start of a flat top reconstructed from before it while it lasts,
        or from both sides three samples after it ends)."""
        h = self.h
        clipped = h.clip[-1] = self.clipped(h.raw[-1])
        j_new = len(h.ts) - 1
        dirty = j_new
        if clipped.any():
            self.n_saturated += 1
            first = self.reconstruct(j_new, both=False)
            if first is not None:
                dirty = min(dirty, first)
            self._burst_end = None
        elif len(h.clip) > 1 and h.clip[-2].any():
            self._burst_end = 0
        if self._burst_end is not None:
            self._burst_end += 1
            if self._burst_end >= 3 or j_new == 0:
                first = self.reconstruct(max(j_new - 3, 0), both=True)
                if first is not None:
                    dirty = min(dirty, first)
                self._burst_end = None
        return clipped, dirty

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
