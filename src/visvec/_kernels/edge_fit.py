"""The edge fit's kernels (visvec.detect.edges: its profiles, levels, step positions,
blur widths, robust lines and their statistics) and its named results.

A frame's edge fit works on a few hundred profiles of a dozen samples each: numpy spends
most of its time there starting its array operations, not doing them. Each kernel here
is one of edges' functions written as loops over the profiles, the same arithmetic in
the same order where the order matters, so that the results agree with the numpy
functions to rounding (tests/detect/test_compiled.py checks them against each other on
frames of every kind the tests render). The robust lines' rounds (robust_lines,
inward_lines) are one function for both paths, their per-point parts loops with numpy
twins. Compiled by Numba with the ``fast`` extra (visvec._kernels.jit); the results
are NamedTuples, which Numba builds and reads as it does plain tuples, so that the
numpy and the compiled fit return the same names."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from visvec._kernels.jit import kernel

# Abramowitz & Stegun, Handbook of Mathematical Functions (1964), Eq. 7.1.26:
# erf(x) = 1 - (a1 t + a2 t^2 + ... + a5 t^5) exp(-x^2), t = 1 / (1 + p x), x >= 0,
# absolute error under 1.5e-7 (erf_with_bell: the edge fit's step model)
_AS_P = 0.3275911
_AS_A5 = 1.061405429
_AS_A4 = -1.453152027
_AS_A3 = 1.421413741
_AS_A2 = -0.284496736
_AS_A1 = 0.254829592
_SQRT_PI = math.sqrt(math.pi)
_SQRT_2 = math.sqrt(2.0)
_SQRT_2PI = math.sqrt(2.0 * math.pi)
# the narrowest blur width an edge can show (px): a pixel's box alone (its RMS width,
# sqrt(1 / 12)), whatever the lens. A width measured below it is noise: the second
# moment of a mean profile derivative is weighted by the squared distance from the edge,
# and noise in the window's far bins can take most of it away (a 320x240 frame's
# 0.80 / 0.68 px edges beside one of 0.15 px, in 1 of 300 cold frames); the step
# positions then fitted with so sharp a step cannot move between the profiles' samples,
# stay on the sparse pass's line, and scatter a third as much as they err (a tilt at 5.3
# sigma)
MIN_WIDTH_PX = math.sqrt(1.0 / 12.0)


class EdgeLines(NamedTuple):
    """The three edges' total-least-squares lines (robust_lines, inward_lines).

    Attributes
    ----------
    normals : ndarray, shape (3, 2)
        Unit normals (into the triangle, after edges._lines).
    offsets : ndarray, shape (3,)
        n . x on each line (ideal px).
    centres : ndarray, shape (3, 2)
        The mean of each edge's inliers (ideal px).
    spreads : ndarray, shape (3,)
        The sum of the inliers' squared distances along the line from its centre
        (px^2): a line's turn about its centre has the variance sigma^2 / spread.
    sigmas : ndarray, shape (3,)
        A point's 1-sigma across its line (px): the residuals', inflated for the
        profiles' shared pixels, at least the floor.
    keep : ndarray of bool, shape (M,)
        The inliers.
    """

    normals: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray
    spreads: np.ndarray
    sigmas: np.ndarray
    keep: np.ndarray


def erf_with_bell(u, bell):
    """erf(u) to 1.5e-7 (Abramowitz & Stegun 7.1.26, Horner from a5) given ``bell`` =
    exp(-u^2), which the edge step's Gauss-Newton needs anyway: half the time of scipy's
    erf (an edge point moves by about 1e-7 px against it). Written once for both paths:
    arrays (edges' numpy fit) or floats (the compiled one, profile by profile)."""
    t = 1.0 / (_AS_P * np.abs(u) + 1.0)
    y = ((((_AS_A5 * t + _AS_A4) * t + _AS_A3) * t + _AS_A2) * t + _AS_A1) * t
    return np.copysign(1.0 - y * bell, u)


class StepPositions(NamedTuple):
    """Each profile's step and its edge's levels (edges._positions and its kernel).

    Attributes
    ----------
    e : ndarray, shape (P,)
        Each profile's sub-pixel step position along its inward normal (px, from the
        profile's centre).
    heights : ndarray, shape (P,)
        Each profile's step height, its inner end's level less its outer end's (grey
        levels).
    mid : ndarray, shape (3,)
        Each edge's mid level over the profiles whose levels agree (grey levels).
    level_sd : ndarray, shape (3,)
        The scatter of those profiles' mid levels about their edge's level lines (grey
        levels).
    level_ok : ndarray of bool, shape (P,)
        The profiles whose levels agree with their edge's (the others have something
        else in their window).
    """

    e: np.ndarray
    heights: np.ndarray
    mid: np.ndarray
    level_sd: np.ndarray
    level_ok: np.ndarray


class SampleGeometry(NamedTuple):
    """Where a pass's profiles lie (sample_geometry; edges._sample reads them through
    cv2.remap), the edges' profiles one after the other.

    Attributes
    ----------
    bases : ndarray, shape (M, 2)
        Each profile's point on its edge's chord (full-image px).
    normals : ndarray, shape (M, 2)
        Its unit normal into the triangle.
    gid : ndarray of int, shape (M,)
        Its edge.
    index : ndarray of int, shape (M,)
        Its place along the edge (0, 1, ...).
    t : ndarray, shape (M,)
        Its place along the edge in [-1, 1].
    along : ndarray, shape (M,)
        Its distance from the edge's first end (px).
    map_x, map_y : ndarray of float32, shape (M, S)
        Its samples' places in the region of interest (px), x and y.
    lengths : ndarray, shape (3,)
        Each edge's chord's length (px).
    """

    bases: np.ndarray
    normals: np.ndarray
    gid: np.ndarray
    index: np.ndarray
    t: np.ndarray
    along: np.ndarray
    map_x: np.ndarray
    map_y: np.ndarray
    lengths: np.ndarray


class EdgeStats(NamedTuple):
    """A fine pass's statistics of each edge (edge_stats).

    Attributes
    ----------
    sigmas : ndarray, shape (3,)
        A point's 1-sigma across its line with the levels' error added (px).
    counts : ndarray, shape (3,)
        The inliers (float).
    outliers : ndarray, shape (3,)
        The share of profiles that are not inliers.
    gaps : ndarray, shape (3, 2)
        How far the inliers stop short of the edge's two ends beyond the trims (px;
        the whole length without inliers).
    """

    sigmas: np.ndarray
    counts: np.ndarray
    outliers: np.ndarray
    gaps: np.ndarray


class LineScatter(NamedTuple):
    """The total-least-squares line through each edge's kept points (_group_tls and
    its numpy twin).

    Attributes
    ----------
    count : ndarray, shape (3,)
        Each edge's kept points (float).
    centre : ndarray, shape (3, 2)
        Their mean (px).
    direction : ndarray, shape (3, 2)
        The line's unit direction (the scatter's principal axis).
    normal : ndarray, shape (3, 2)
        Its unit normal (the direction turned by +90 deg).
    dx, dy : ndarray, shape (M,)
        Every point's coordinates about its edge's centre (px).
    """

    count: np.ndarray
    centre: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    dx: np.ndarray
    dy: np.ndarray


def step_residual(f, x, e, s2):
    """The edge fit's blurred step at a profile's sample: with the sample at ``x`` (px
    along the inward normal), the step at ``e`` and s2 = sqrt(2) w (w its blur width),
    u = (x - e) / s2; returns the residual f - (1 + erf(u)) / 2 of the normalised level
    ``f`` and the model's slope g = exp(-u^2) / (sqrt(pi) s2) (-d residual / d e, per
    px), which the position's Gauss-Newton step sum(r g) / sum(g^2) takes. Written once
    for both paths: arrays (edges' numpy fit, broadcast) or floats (the compiled one)."""
    u = (x - e) / s2
    bell = np.exp(-u * u)
    # (the kernel's name: compiled within a compiled caller, the plain function on the
    # numpy path, where it is one without Numba or after jit.off)
    return f - 0.5 * (1.0 + _erf_with_bell(u, bell)), bell / (_SQRT_PI * s2)


def position_step(num, den):
    """The Gauss-Newton step of a profile's step position (px, subtracted from it):
    sum(r g) / sum(g^2) over its samples (``num``, ``den``; step_residual's r and g),
    at most half a pixel each way. Written once for both paths: arrays (every profile
    at once) or floats (the compiled one, profile by profile)."""
    return np.minimum(np.maximum(num / np.maximum(den, 1e-12), -0.5), 0.5)


def vertices(normals: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, list | None]:
    """The triangle's vertices (3, 2) in ideal pixels from its three lines n . x = offset
    (line i opposite vertex i; the edge fit's and the pixel fit's) and, per vertex i,
    the inverse of the 2x2 matrix [n_j; n_k] of its two lines (Cramer's rule: x = A^-1
    [o_j, o_k]); all NaN and None when two lines are parallel."""
    nrm, off = normals.tolist(), offsets.tolist()
    V = np.empty((3, 2))
    invs = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        (a, b), (c, d) = nrm[j], nrm[k]
        det = a * d - b * c
        if det == 0.0:
            return np.full((3, 2), np.nan), None
        inv = ((d / det, -b / det), (-c / det, a / det))
        V[i] = (inv[0][0] * off[j] + inv[0][1] * off[k], inv[1][0] * off[j] + inv[1][1] * off[k])
        invs.append(inv)
    return V, invs


# ---------------------------------------------------------------- profiles (_sample)
def _sample_geometry(corners, off, offs, trims, spacing, max_per_edge):
    """edges._sample but for its cv2.remap: a SampleGeometry. Edge i runs from vertex
    i + 1 to vertex i + 2, its profiles (at least 4, at most ``max_per_edge``) about
    ``spacing`` apart between its trims (``trims`` (3,) px from each vertex, at most
    0.4 of the edge), each at ``offs``
    along the inward normal, in the frame less ``off``."""
    A = np.empty((3, 2))
    D = np.empty((3, 2))
    length = np.empty(3)
    for i in range(3):
        a = (i + 1) % 3
        b = (i + 2) % 3
        A[i, 0] = corners[a, 0]
        A[i, 1] = corners[a, 1]
        D[i, 0] = corners[b, 0] - corners[a, 0]
        D[i, 1] = corners[b, 1] - corners[a, 1]
        length[i] = math.sqrt(D[i, 0] * D[i, 0] + D[i, 1] * D[i, 1])
        d = max(length[i], 1e-9)
        D[i, 0] = D[i, 0] / d
        D[i, 1] = D[i, 1] / d
    ax = corners[1, 0] - corners[0, 0]
    ay = corners[1, 1] - corners[0, 1]
    bx = corners[2, 0] - corners[0, 0]
    by = corners[2, 1] - corners[0, 1]
    inward = 1.0 if ax * by - ay * bx > 0 else -1.0
    N = np.empty((3, 2))
    m = np.empty(3, np.int64)
    s0 = np.empty(3)
    s1 = np.empty(3)
    for i in range(3):
        N[i, 0] = -inward * D[i, 1]
        N[i, 1] = inward * D[i, 0]
        s0[i] = min(trims[(i + 1) % 3], 0.4 * length[i])
        s1[i] = length[i] - min(trims[(i + 2) % 3], 0.4 * length[i])
        m[i] = int(min(max((s1[i] - s0[i]) / spacing, 4.0), max_per_edge))
    total = m[0] + m[1] + m[2]
    n_s = len(offs)
    bases = np.empty((total, 2))
    normals = np.empty((total, 2))
    gid = np.empty(total, np.int64)
    k = np.empty(total, np.int64)
    tt = np.empty(total)
    along = np.empty(total)
    map_x = np.empty((total, n_s), np.float32)
    map_y = np.empty((total, n_s), np.float32)
    p = 0
    for i in range(3):
        for j in range(m[i]):
            frac = j / (m[i] - 1)
            al = s0[i] + frac * (s1[i] - s0[i])
            gid[p] = i
            k[p] = j
            tt[p] = 2.0 * frac - 1.0
            along[p] = al
            bases[p, 0] = A[i, 0] + al * D[i, 0]
            bases[p, 1] = A[i, 1] + al * D[i, 1]
            normals[p, 0] = N[i, 0]
            normals[p, 1] = N[i, 1]
            bx0 = bases[p, 0] - off[0]
            by0 = bases[p, 1] - off[1]
            for q in range(n_s):
                map_x[p, q] = bx0 + offs[q] * N[i, 0]
                map_y[p, q] = by0 + offs[q] * N[i, 1]
            p += 1
    return SampleGeometry(bases, normals, gid, k, tt, along, map_x, map_y, length)


def _sample_geometry_numpy(corners, off, offs, trims, spacing, max_per_edge):
    """_sample_geometry with numpy (also for corners that are not finite)."""
    A = corners[[1, 2, 0]]  # edge i runs from vertex i+1 to vertex i+2
    D = corners[[2, 0, 1]] - A
    length = np.sqrt(np.einsum("ij,ij->i", D, D))
    D = D / np.maximum(length, 1e-9)[:, None]
    # normals point into the triangle: the left normal (-Dy, Dx) of edges run v1 -> v2
    # -> v0 -> v1 does when (v1 - v0) x (v2 - v0) > 0
    (ax, ay), (bx, by) = (corners[1] - corners[0]).tolist(), (corners[2] - corners[0]).tolist()
    inward = 1.0 if ax * by - ay * bx > 0 else -1.0
    N = np.empty((3, 2))
    N[:, 0] = -inward * D[:, 1]
    N[:, 1] = inward * D[:, 0]
    s0 = np.minimum(trims[[1, 2, 0]], 0.4 * length)
    s1 = length - np.minimum(trims[[2, 0, 1]], 0.4 * length)
    m = np.clip((s1 - s0) / spacing, 4, max_per_edge).astype(int)
    gid = np.repeat(np.arange(3), m)
    k = np.arange(len(gid)) - np.repeat(np.cumsum(m) - m, m)  # index along the edge
    frac = k / np.repeat(m - 1, m)
    along = s0[gid] + frac * (s1 - s0)[gid]
    tt = 2.0 * frac - 1.0
    bases = A[gid] + along[:, None] * D[gid]
    normals = N[gid]
    # the sample points as two (M, S) float32 maps, x and y: built as 2-D broadcasts
    # (an interleaved (M, S, 2) map took 3x longer to build than cv2.remap takes to run)
    b = bases - off
    map_x = (b[:, 0:1] + offs * normals[:, 0:1]).astype(np.float32)
    map_y = (b[:, 1:2] + offs * normals[:, 1:2]).astype(np.float32)
    return SampleGeometry(bases, normals, gid, k, tt, along, map_x, map_y, length)


# ------------------------------------------------------- levels (_level_lines and co)
def _group_linear(t, y, gid, keep, use_keep):
    """Each edge's least-squares line of y against t (over ``keep`` when use_keep),
    evaluated at every t."""
    w = np.zeros(3)
    st = np.zeros(3)
    stt = np.zeros(3)
    sy = np.zeros(3)
    sty = np.zeros(3)
    for p in range(len(t)):
        if use_keep and not keep[p]:
            continue
        g = gid[p]
        w[g] += 1.0
        st[g] += t[p]
        stt[g] += t[p] * t[p]
        sy[g] += y[p]
        sty[g] += t[p] * y[p]
    slope = np.zeros(3)
    icpt = np.zeros(3)
    for g in range(3):
        den = w[g] * stt[g] - st[g] * st[g]
        if abs(den) > 1e-12:
            slope[g] = (w[g] * sty[g] - st[g] * sy[g]) / den
        icpt[g] = (sy[g] - slope[g] * st[g]) / max(w[g], 1.0)
    out = np.empty(len(t))
    for p in range(len(t)):
        out[p] = icpt[gid[p]] + slope[gid[p]] * t[p]
    return out


def _group_linear_numpy(t, y, gid, keep, use_keep):
    """_group_linear with numpy."""
    if use_keep:
        wt, sel, yk = t[keep], gid[keep], y[keep]
    else:
        wt, sel, yk = t, gid, y
    w = np.bincount(sel, minlength=3)
    st = np.bincount(sel, wt, 3)
    stt = np.bincount(sel, wt * wt, 3)
    den = w * stt - st * st
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    sy = np.bincount(sel, yk, 3)
    slope = np.where(ok, (w * np.bincount(sel, wt * yk, 3) - st * sy) / den, 0.0)
    icpt = (sy - slope * st) / np.maximum(w, 1)
    return icpt[gid] + slope[gid] * t


def _levels_suspect(r_lo, r_hi, lo_raw, hi_raw, starts, suspect_rms, suspect_max):
    """Whether any edge's level residuals (r_lo, r_hi about least-squares lines; the
    edges' profiles one after the other, edge g's from starts[g] to starts[g + 1]) are
    more than the profiles' noise explains (an RMS above ``suspect_rms`` times, or one
    residual above ``suspect_max`` times, the noise; edges.LEVEL_SUSPECT_RMS, _MAX); the
    noise variance of each level from the differences of neighbouring profiles, half
    their mean square."""
    for row in range(2):
        raw = lo_raw if row == 0 else hi_raw
        r = r_lo if row == 0 else r_hi
        for g in range(3):
            a, b = starts[g], starts[g + 1]
            c = b - a
            # the raw levels are float32 (numpy's mean of the float32 samples): their
            # differences and sum of squares too, as numpy takes them
            s = np.float32(0.0)
            for p in range(a, b - 1):
                d = raw[p + 1] - raw[p]
                s += d * d
            noise2 = max(np.float64(s) / (2.0 * max(c - 1, 1)), 1e-6)
            rs = 0.0
            rmax = 0.0
            for p in range(a, b):
                r2 = r[p] * r[p]
                rs += r2
                rmax = max(rmax, r2)
            if rs > suspect_rms**2 * max(c - 2, 1) * noise2:
                return True
            if rmax > suspect_max**2 * noise2:
                return True
    return False


def _levels_suspect_numpy(r_lo, r_hi, lo_raw, hi_raw, starts, suspect_rms, suspect_max):
    """_levels_suspect with numpy (each edge's sums in one reduceat)."""
    counts = np.diff(starts)
    first = starts[:3]
    d = np.diff(np.stack((lo_raw, hi_raw)), axis=1)
    d[:, starts[1] - 1] = 0.0  # the steps from one edge to the next
    d[:, starts[2] - 1] = 0.0
    d *= d
    noise2 = np.add.reduceat(d, first, axis=1) / (2.0 * np.maximum(counts - 1, 1))
    noise2 = np.maximum(noise2, 1e-6)
    r = np.stack((r_lo, r_hi))
    r *= r
    if np.any(
        np.add.reduceat(r, first, axis=1) > suspect_rms**2 * np.maximum(counts - 2, 1) * noise2
    ):
        return True
    return bool(np.any(np.maximum.reduceat(r, first, axis=1) > suspect_max**2 * noise2))


def _resistant_residuals(t, lo_raw, hi_raw, gid, starts, outlier_sigmas, outlier_min):
    """Each profile's levels' distances (res_lo, res_hi (M,)) from resistant lines: per
    edge through the medians (of t and of the level) of each half of the edge (t
    ascends along it), and each edge's limits on them (lim_lo, lim_hi (3,)):
    ``outlier_sigmas`` robust sigmas (1.4826 x the median distance), at least
    ``outlier_min``."""
    m_all = len(t)
    res_lo = np.empty(m_all)
    res_hi = np.empty(m_all)
    lim_lo = np.empty(3)
    lim_hi = np.empty(3)
    for g in range(3):
        a, c = starts[g], starts[g + 1] - starts[g]
        n0 = c // 2
        m_lo0 = np.median(lo_raw[a : a + n0].astype(np.float64))
        m_lo1 = np.median(lo_raw[a + n0 : a + c].astype(np.float64))
        m_hi0 = np.median(hi_raw[a : a + n0].astype(np.float64))
        m_hi1 = np.median(hi_raw[a + n0 : a + c].astype(np.float64))
        t0 = 0.5 * (t[a + (n0 - 1) // 2] + t[a + n0 // 2])
        t1 = 0.5 * (t[a + n0 + (c - n0 - 1) // 2] + t[a + n0 + (c - n0) // 2])
        dt = t1 - t0 if abs(t1 - t0) > 1e-9 else 1.0
        s_lo = (m_lo1 - m_lo0) / dt
        s_hi = (m_hi1 - m_hi0) / dt
        for p in range(a, a + c):
            u = t[p] - t0
            res_lo[p] = abs(lo_raw[p] - m_lo0 - s_lo * u)
            res_hi[p] = abs(hi_raw[p] - m_hi0 - s_hi * u)
        lim_lo[g] = max(outlier_sigmas * 1.4826 * np.median(res_lo[a : a + c]), outlier_min)
        lim_hi[g] = max(outlier_sigmas * 1.4826 * np.median(res_hi[a : a + c]), outlier_min)
    return res_lo, res_hi, lim_lo, lim_hi


def _resistant_residuals_numpy(t, lo_raw, hi_raw, gid, starts, outlier_sigmas, outlier_min):
    """_resistant_residuals with numpy: the halves' medians from one sort of a table of
    them, the distances' medians from another."""
    m = len(gid)
    nc = np.diff(starts)
    index = np.arange(m) - starts[gid]
    n0 = nc // 2  # profiles in each edge's first half
    h0 = n0[gid]
    second = index >= h0
    col = index - h0 * second
    # the medians of the halves: rows 4 g + 2 (hi) + (second half)
    row = 4 * gid + second
    table = np.full((12, int(nc.max() - n0.min()) + 1), np.inf)
    table[row, col] = lo_raw
    table[row + 2, col] = hi_raw
    table.sort(axis=1)
    k = np.column_stack([n0, nc - n0, n0, nc - n0]).ravel()
    med = sorted_medians(table, k).reshape(3, 2, 2)  # edge, lo/hi, half
    # t ascends along the edge: the median of a half is its middle profile's t
    s0 = starts[:3]
    t0 = 0.5 * (t[s0 + (n0 - 1) // 2] + t[s0 + n0 // 2])
    t1 = 0.5 * (t[s0 + n0 + (nc - n0 - 1) // 2] + t[s0 + n0 + (nc - n0) // 2])
    dt = np.where(np.abs(t1 - t0) > 1e-9, t1 - t0, 1.0)
    slope = (med[:, :, 1] - med[:, :, 0]) / dt[:, None]  # (3, 2)
    u = t - t0[gid]
    res_lo = np.abs(lo_raw - med[gid, 0, 0] - slope[gid, 0] * u)
    res_hi = np.abs(hi_raw - med[gid, 1, 0] - slope[gid, 1] * u)
    table = np.full((6, int(nc.max())), np.inf)
    table[gid, index] = res_lo
    table[gid + 3, index] = res_hi
    table.sort(axis=1)
    scale = sorted_medians(table, np.concatenate([nc, nc]))
    lim = np.maximum(outlier_sigmas * 1.4826 * scale, outlier_min)
    return res_lo, res_hi, lim[:3], lim[3:]


def _level_inliers(res_lo, res_hi, lim_lo, lim_hi, gid):
    """The profiles whose two levels lie within their edge's limits; an edge that would
    keep fewer than 5 (too few for a line) keeps them all."""
    m_all = len(res_lo)
    new = np.empty(m_all, np.bool_)
    cnt = np.zeros(3)
    for p in range(m_all):
        g = gid[p]
        new[p] = res_lo[p] <= lim_lo[g] and res_hi[p] <= lim_hi[g]
        if new[p]:
            cnt[g] += 1.0
    for p in range(m_all):
        if cnt[gid[p]] < 5:
            new[p] = True
    return new


def _level_inliers_numpy(res_lo, res_hi, lim_lo, lim_hi, gid):
    """_level_inliers with numpy."""
    new = (res_lo <= lim_lo[gid]) & (res_hi <= lim_hi[gid])
    return new | (np.bincount(gid, new, 3) < 5)[gid]


def _level_lines(t, lo_raw, hi_raw, gid, starts, outlier_sigmas, outlier_min,
                 suspect_rms, suspect_max):  # fmt: skip
    """Board (lo) and triangle (hi) level lines along each edge, robust to profiles
    whose window holds something else (edges.LEVEL_OUTLIER_SIGMAS). The profiles are in
    order along each edge (t ascending), the edges one after the other (edge g's from
    starts[g]).

    Least-squares lines through every profile are kept when their residuals are what
    the profiles' noise explains (_levels_suspect). Otherwise the first lines are
    resistant ones (_resistant_residuals), which follow a lighting gradient and are not
    moved by outliers in under half of either half of an edge; the profiles whose two
    levels lie within ``outlier_sigmas`` robust sigmas of them are kept
    (_level_inliers) and least-squares lines fitted to them; once more if the kept set
    changes against those lines. Returns lo, hi (M,) on the final lines and the mask of
    profiles whose levels passed (M,).

    One function for both paths: compiled, or run as Python with the per-profile
    parts' numpy twins (visvec._kernels.jit.kernel)."""
    none = np.zeros(0, np.bool_)
    lo = _group_linear(t, lo_raw, gid, none, False)
    hi = _group_linear(t, hi_raw, gid, none, False)
    ok = np.ones(len(t), np.bool_)
    if not _levels_suspect(lo_raw - lo, hi_raw - hi, lo_raw, hi_raw, starts, suspect_rms,
                           suspect_max):  # fmt: skip
        return lo, hi, ok
    res_lo, res_hi, lim_lo, lim_hi = _resistant_residuals(t, lo_raw, hi_raw, gid, starts,
                                                          outlier_sigmas, outlier_min)  # fmt: skip
    for it in range(2):
        new = _level_inliers(res_lo, res_hi, lim_lo, lim_hi, gid)
        if it > 0 and np.array_equal(new, ok):
            break
        ok = new
        every = ok.all()
        lo = _group_linear(t, lo_raw, gid, ok, not every)
        hi = _group_linear(t, hi_raw, gid, ok, not every)
        res_lo = np.abs(lo_raw - lo)
        res_hi = np.abs(hi_raw - hi)
    return lo, hi, ok


# ------------------------------------------------------------------ step positions
def _edge_starts(gid):
    """(4,) where each edge's profiles start (the edges one after the other), and the
    end."""
    starts = np.zeros(4, np.int64)
    for p in range(len(gid)):
        starts[gid[p] + 1] += 1
    for g in range(3):
        starts[g + 1] += starts[g]
    return starts


def _edge_starts_numpy(gid):
    """_edge_starts with numpy."""
    return np.concatenate((np.zeros(1, np.int64), np.cumsum(np.bincount(gid, minlength=3))))


def _end_levels(vals, ends):
    """Each profile's levels at its ends (M,) each: the means of its first and last
    ``ends`` samples, in float32 as numpy takes the mean of float32 samples."""
    m_all, n_tot = vals.shape
    lo_raw = np.empty(m_all, np.float32)
    hi_raw = np.empty(m_all, np.float32)
    n_ends = np.float32(ends)
    for p in range(m_all):
        a = np.float32(0.0)
        b = np.float32(0.0)
        for j in range(ends):
            a += vals[p, j]
            b += vals[p, n_tot - ends + j]
        lo_raw[p] = a / n_ends
        hi_raw[p] = b / n_ends
    return lo_raw, hi_raw


def _end_levels_numpy(vals, ends):
    """_end_levels with numpy (np.add.reduce: a mean without its wrapper's overhead)."""
    return np.add.reduce(vals[:, :ends], axis=1) / ends, np.add.reduce(
        vals[:, -ends:], axis=1
    ) / ends


def _area_positions(vals, lo, hi, n_ext, half, step):
    """Each profile's samples inside the window (vals[:, n_ext : -n_ext]) normalised
    between its levels, f (M, S), and its step position by the area estimator: for a
    step from lo to hi blurred by any symmetric kernel narrower than the window, the
    integral of f from -half to +half (trapezoids, ``step`` apart) is half - e."""
    m_all = vals.shape[0]
    s_in = vals.shape[1] - 2 * n_ext
    f = np.empty((m_all, s_in))
    e = np.empty(m_all)
    for p in range(m_all):
        h = hi[p] - lo[p]
        safe = h if abs(h) > 1e-6 else 1e-6
        total = 0.0
        for j in range(s_in):
            f[p, j] = (vals[p, n_ext + j] - lo[p]) / safe
            total += f[p, j]
        e[p] = half - step * (total - 0.5 * (f[p, 0] + f[p, s_in - 1]))
    return f, e


def _area_positions_numpy(vals, lo, hi, n_ext, half, step):
    """_area_positions with numpy."""
    if n_ext:
        vals = vals[:, n_ext:-n_ext]
    step_h = hi - lo
    safe = np.where(np.abs(step_h) > 1e-6, step_h, 1e-6)
    f = (vals - lo[:, None]) / safe[:, None]
    return f, half - step * (f.sum(axis=1) - 0.5 * (f[:, 0] + f[:, -1]))


def _position_sums(f, e, s2, half, step):
    """Each profile's Gauss-Newton sums for its step position: sum(r g) and sum(g^2)
    over its samples (step_residual at the samples -half + j step, the step at e, s2
    = sqrt(2) w)."""
    m_all, s_in = f.shape
    num = np.empty(m_all)
    den = np.empty(m_all)
    for p in range(m_all):
        a = 0.0
        b = 0.0
        for j in range(s_in):
            r, g = _step_residual(f[p, j], -half + j * step, e[p], s2[p])
            a += r * g
            b += g * g
        num[p], den[p] = a, b
    return num, den


def _position_sums_numpy(f, e, s2, half, step):
    """_position_sums with numpy (every profile at once)."""
    x = np.arange(-half, half + 1e-9, step)[None, :]
    r, g = step_residual(f, x, e[:, None], s2[:, None])
    return (r * g).sum(axis=1), (g * g).sum(axis=1)


def _level_stats(lo, hi, lo_raw, hi_raw, gid, level_ok):
    """Per edge (3,), over the profiles whose levels passed: the mid level (lo + hi) /
    2, and the scatter of the profiles' mid levels about the edge's mid-level line."""
    cnt = np.zeros(3)
    s_lo = np.zeros(3)
    s_hi = np.zeros(3)
    s_res = np.zeros(3)
    for p in range(len(lo)):
        if level_ok[p]:
            g = gid[p]
            cnt[g] += 1.0
            s_lo[g] += lo[p]
            s_hi[g] += hi[p]
            res = 0.5 * (lo_raw[p] + hi_raw[p] - lo[p] - hi[p])
            s_res[g] += res * res
    mid = np.empty(3)
    level_sd = np.empty(3)
    for g in range(3):
        c = max(cnt[g], 1.0)
        mid[g] = (s_lo[g] + s_hi[g]) / (2.0 * c)
        level_sd[g] = math.sqrt(s_res[g] / max(c - 2.0, 1.0))
    return mid, level_sd


def _level_stats_numpy(lo, hi, lo_raw, hi_raw, gid, level_ok):
    """_level_stats with numpy."""
    w = level_ok.astype(float)
    cnt = np.maximum(np.bincount(gid, w, 3), 1)
    mid = (np.bincount(gid, w * lo, 3) + np.bincount(gid, w * hi, 3)) / (2 * cnt)
    res = 0.5 * (lo_raw + hi_raw - lo - hi)
    return mid, np.sqrt(np.bincount(gid, w * res * res, 3) / np.maximum(cnt - 2, 1))


def _positions(vals, t, gid, half, step, width, n_ext, ends, gn_steps,
               outlier_sigmas, outlier_min, suspect_rms, suspect_max):  # fmt: skip
    """Each profile's step position (px along its inward normal), its step height, per
    edge the mid level and the levels' scatter, and the profiles whose levels agree
    (edges._positions says how; the edges' profiles one after the other, as _sample
    gives them): the end levels (_end_levels, over ``ends`` samples), their lines
    (_level_lines), the area estimate (_area_positions) and, with the edges' blur
    ``width`` (3,), ``gn_steps`` Gauss-Newton steps of the erf step model
    (_position_sums, position_step). A StepPositions.

    One function for both paths: compiled, or run as Python with the per-profile
    parts' numpy twins (visvec._kernels.jit.kernel)."""
    starts = _edge_starts(gid)
    lo_raw, hi_raw = _end_levels(vals, ends)
    lo, hi, level_ok = _level_lines(t, lo_raw, hi_raw, gid, starts, outlier_sigmas,
                                    outlier_min, suspect_rms, suspect_max)  # fmt: skip
    f, e = _area_positions(vals, lo, hi, n_ext, half, step)
    if len(width) == 3:
        s2 = _SQRT_2 * width[gid]
        for _ in range(gn_steps):
            num, den = _position_sums(f, e, s2, half, step)
            e = e - _position_step(num, den)
    mid, level_sd = _level_stats(lo, hi, lo_raw, hi_raw, gid, level_ok)
    return StepPositions(e, hi_raw - lo_raw, mid, level_sd, level_ok)


# ---------------------------------------------------------------------- blur widths
def _aligned_slopes(vals, n_ext, e, clear, gid, half, step):
    """Each edge's mean profile derivative (3, 3 S') over bins aligned on each profile's
    step (its derivative shifted by its step position e to the nearest sample), over
    the profiles with a clear step, in the bins that at least half the edge's profiles
    cover within one window of the edge (0 elsewhere); and the bins' centres x (3 S',)
    (px, the edge at 0). The profiles are vals[:, n_ext : -n_ext] (S' + 1 samples
    ``step`` apart from -half)."""
    m_all = vals.shape[0]
    n_bins = vals.shape[1] - 2 * n_ext - 1
    nb3 = 3 * n_bins
    sums = np.zeros((3, nb3))
    cnt = np.zeros((3, nb3))
    for p in range(m_all):
        if not clear[p]:
            continue
        k = int(np.rint(e[p] / step))
        g = gid[p]
        for j in range(n_bins):
            b = j - k + n_bins
            sums[g, b] += np.float64(vals[p, n_ext + j + 1] - vals[p, n_ext + j])
            cnt[g, b] += 1.0
    x = np.empty(nb3)
    for b in range(nb3):
        x[b] = -half + (b - n_bins + 0.5) * step
    g_all = np.zeros((3, nb3))
    for g in range(3):
        top = 0.0
        for b in range(nb3):
            top = max(top, cnt[g, b])
        for b in range(nb3):
            if cnt[g, b] > 0 and cnt[g, b] >= 0.5 * top and abs(x[b]) <= half:
                g_all[g, b] = sums[g, b] / max(cnt[g, b], 1.0)
    return g_all, x


def _aligned_slopes_numpy(vals, n_ext, e, clear, gid, half, step):
    """_aligned_slopes with numpy."""
    d = np.diff(vals[:, n_ext : vals.shape[1] - n_ext], axis=1)
    n_bins = d.shape[1]
    k = np.rint(e[clear] / step).astype(np.int64)
    j = np.arange(n_bins)[None, :] - k[:, None] + n_bins  # aligned bin, in [0, 3 n_bins)
    flat = (gid[clear][:, None] * (3 * n_bins) + j).ravel()
    sums = np.bincount(flat, d[clear].ravel(), 9 * n_bins).reshape(3, 3 * n_bins)
    cnt = np.bincount(flat, minlength=9 * n_bins).reshape(3, 3 * n_bins)
    x = -half + (np.arange(3 * n_bins) - n_bins + 0.5) * step  # bin centres, edge at 0
    use = (cnt > 0) & (cnt >= 0.5 * cnt.max(axis=1, keepdims=True)) & (np.abs(x) <= half)
    return np.where(use, sums / np.maximum(cnt, 1), 0.0), x


def _moment_widths(g_all, x, reach, half):
    """Each edge's RMS width (3,) (px): the second moment of its mean derivative g_all
    about its centroid over the bins within ``reach`` (3,) of the edge, at most half /
    2; half / 3 where it has no positive mass."""
    w = np.empty(3)
    for g in range(3):
        tot = 0.0
        gx = 0.0
        for b in range(len(x)):
            if abs(x[b]) <= reach[g]:
                tot += g_all[g, b]
                gx += g_all[g, b] * x[b]
        safe = tot if tot > 0 else 1.0
        c = gx / safe
        w2 = 0.0
        for b in range(len(x)):
            if abs(x[b]) <= reach[g]:
                w2 += g_all[g, b] * (x[b] - c) ** 2
        w2 = w2 / safe
        if tot > 0 and w2 > 0:
            w[g] = min(math.sqrt(w2), half / 2.0)
        else:
            w[g] = half / 3.0
    return w


def _moment_widths_numpy(g_all, x, reach, half):
    """_moment_widths with numpy."""
    g = np.where(np.abs(x)[None, :] <= reach[:, None], g_all, 0.0)
    tot = g.sum(axis=1)
    safe = np.where(tot > 0, tot, 1.0)
    c = (g @ x) / safe
    w2 = (g * (x[None, :] - c[:, None]) ** 2).sum(axis=1) / safe
    ok = (tot > 0) & (w2 > 0)
    return np.where(ok, np.sqrt(np.where(ok, w2, 1.0)).clip(max=half / 2.0), half / 3.0)


def _widths(vals, n_ext, e, clear, gid, half, step, reach_min):
    """(3,) each edge's RMS blur width (px; edges._widths says how): the second moment
    of its mean profile derivative, aligned on each profile's step (_aligned_slopes,
    _moment_widths); a window wider than ``reach_min`` measured again within 4 widths of
    the edge (its far bins add only noise to the second moment); never below a pixel's
    box (MIN_WIDTH_PX). One function for both paths: compiled, or run as Python with the
    numpy twins."""
    g_all, x = _aligned_slopes(vals, n_ext, e, clear, gid, half, step)
    reach = np.full(3, np.inf)
    w = _moment_widths(g_all, x, reach, half)
    if half > reach_min:
        reach = np.maximum(4.0 * w, reach_min)
        w = _moment_widths(g_all, x, reach, half)
    return np.maximum(w, MIN_WIDTH_PX)


def _group_median(a, gid, index, keep):
    """(3,) the median of ``a`` over each edge's kept points, 0 where an edge keeps
    none (``index``: each point's place along its edge, which the numpy twin's table
    takes; the loops need none)."""
    out = np.zeros(3)
    for g in range(3):
        cnt = 0
        for p in range(len(a)):
            if gid[p] == g and keep[p]:
                cnt += 1
        if cnt:
            v = np.empty(cnt)
            q = 0
            for p in range(len(a)):
                if gid[p] == g and keep[p]:
                    v[q] = a[p]
                    q += 1
            out[g] = np.median(v)
    return out


def sorted_medians(table: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Median of each row's first k values of a row-sorted table (padded with inf)."""
    rows = np.arange(len(k))
    return 0.5 * (table[rows, (k - 1) // 2] + table[rows, k // 2])


def _group_median_numpy(a, gid, index, keep):
    """_group_median with numpy, the same value as np.median: one sort of a (3,
    longest edge) table padded with inf."""
    table = np.full((3, int(index.max()) + 1), np.inf)
    table[gid[keep], index[keep]] = a[keep]
    table.sort(axis=1)
    k = np.bincount(gid[keep], minlength=3)
    return np.where(k > 0, sorted_medians(table, np.maximum(k, 1)), 0.0)


# ------------------------------------------------------------------- robust lines
def _group_tls(x, y, gid, keep):
    """The total-least-squares line through each edge's kept points (x, y), all three
    at once: a LineScatter (each edge's count, centre, unit direction and normal, and
    every point's coordinates about its edge's centre)."""
    k = np.zeros(3)
    sx = np.zeros(3)
    sy = np.zeros(3)
    for p in range(len(x)):
        if keep[p]:
            g = gid[p]
            k[g] += 1.0
            sx[g] += x[p]
            sy[g] += y[p]
    c = np.empty((3, 2))
    for g in range(3):
        kk = max(k[g], 1.0)
        c[g, 0] = sx[g] / kk
        c[g, 1] = sy[g] / kk
    dx = np.empty(len(x))
    dy = np.empty(len(x))
    sxx = np.zeros(3)
    syy = np.zeros(3)
    sxy = np.zeros(3)
    for p in range(len(x)):
        g = gid[p]
        dx[p] = x[p] - c[g, 0]
        dy[p] = y[p] - c[g, 1]
        if keep[p]:
            sxx[g] += dx[p] * dx[p]
            syy[g] += dy[p] * dy[p]
            sxy[g] += dx[p] * dy[p]
    d = np.empty((3, 2))
    n = np.empty((3, 2))
    for g in range(3):
        # the principal axis of each 2x2 scatter matrix: 0.5 atan2(2 sxy, sxx - syy)
        a = 0.5 * math.atan2(2.0 * sxy[g], sxx[g] - syy[g])
        d[g, 0] = math.cos(a)
        d[g, 1] = math.sin(a)
        n[g, 0] = -d[g, 1]
        n[g, 1] = d[g, 0]
    return LineScatter(k, c, d, n, dx, dy)


def _group_tls_numpy(x, y, gid, keep):
    """_group_tls with numpy."""
    w = keep.astype(float)
    k = np.bincount(gid, w, 3)
    kk = np.maximum(k, 1.0)
    c = np.empty((3, 2))
    c[:, 0] = np.bincount(gid, w * x, 3) / kk
    c[:, 1] = np.bincount(gid, w * y, 3) / kk
    dx, dy = x - c[gid, 0], y - c[gid, 1]
    wdx = w * dx
    sxx = np.bincount(gid, wdx * dx, 3)
    syy = np.bincount(gid, w * dy * dy, 3)
    sxy = np.bincount(gid, wdx * dy, 3)
    a = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    d = np.empty((3, 2))
    d[:, 0], d[:, 1] = np.cos(a), np.sin(a)
    n = np.empty((3, 2))
    n[:, 0], n[:, 1] = -d[:, 1], d[:, 0]
    return LineScatter(k, c, d, n, dx, dy)


def _distances(dx, dy, n, gid):
    """(M,) each point's distance from its edge's line (dx, dy about the edge's centre)."""
    a = np.empty(len(dx))
    for p in range(len(dx)):
        g = gid[p]
        a[p] = abs(dx[p] * n[g, 0] + dy[p] * n[g, 1])
    return a


def _distances_numpy(dx, dy, n, gid):
    """_distances with numpy."""
    return np.abs(dx * n[gid, 0] + dy * n[gid, 1])


def _inliers(a, use, keep, limit, gid):
    """The points (of those ``use`` takes) within ``limit`` (3,) of their edge's line
    (distances ``a``), whether each edge's differ from ``keep``, and each edge's count."""
    new = np.empty(len(a), np.bool_)
    changed = np.zeros(3, np.bool_)
    count = np.zeros(3)
    for p in range(len(a)):
        g = gid[p]
        new[p] = use[p] and a[p] <= limit[g]
        if new[p] != keep[p]:
            changed[g] = True
        if new[p]:
            count[g] += 1.0
    return new, changed, count


def _inliers_numpy(a, use, keep, limit, gid):
    """_inliers with numpy."""
    new = use & (a <= limit[gid])
    return new, np.bincount(gid, new != keep, 3) > 0, np.bincount(gid, new, 3)


def _kept_where(active, new, keep, gid):
    """``new`` on the edges still ``active``, ``keep`` on the others."""
    out = keep.copy()
    for p in range(len(keep)):
        if active[gid[p]]:
            out[p] = new[p]
    return out


def _kept_where_numpy(active, new, keep, gid):
    """_kept_where with numpy."""
    return np.where(active[gid], new, keep)


def _line_sums(dx, dy, n, d, gid, keep):
    """Per edge, the kept points' sums of squares across the line and along it."""
    rss = np.zeros(3)
    spread = np.zeros(3)
    for p in range(len(dx)):
        if keep[p]:
            g = gid[p]
            r = dx[p] * n[g, 0] + dy[p] * n[g, 1]
            t = dx[p] * d[g, 0] + dy[p] * d[g, 1]
            rss[g] += r * r
            spread[g] += t * t
    return rss, spread


def _line_sums_numpy(dx, dy, n, d, gid, keep):
    """_line_sums with numpy."""
    w = keep.astype(float)
    r = dx * n[gid, 0] + dy * n[gid, 1]
    t = dx * d[gid, 0] + dy * d[gid, 1]
    return np.bincount(gid, w * r * r, 3), np.bincount(gid, w * t * t, 3)


def _robust_lines(x, y, gid, index, use, floor, rounds, inflation):
    """Total-least-squares lines through each edge's points (those with ``use``), with
    iterative outlier rejection (3.5 robust sigmas, sigma from the median absolute
    residual, at least ``floor``), all three edges at once. An edge stops iterating when
    its inliers no longer change or would fall under 5. The sigmas are the residuals'
    times ``inflation`` (edges.EDGE_VARIANCE_INFLATION: neighbouring profiles share
    pixels through the bilinear sampling, so the points are not independent). Normals
    not yet turned into the triangle: an EdgeLines.

    One function for both paths: compiled, or run as Python with the per-point parts'
    numpy twins (visvec._kernels.jit.kernel)."""
    keep = use.copy()
    k, c, d, n, dx, dy = _group_tls(x, y, gid, keep)
    active = np.ones(3, np.bool_)
    for _ in range(rounds):
        a = _distances(dx, dy, n, gid)
        sigma = np.maximum(1.4826 * group_median(a, gid, index, keep), floor)
        new, changed, count = _inliers(a, use, keep, np.maximum(3.5 * sigma, 0.25), gid)
        active &= changed & (count >= 5)
        if not active.any():
            break
        keep = _kept_where(active, new, keep, gid)
        k, c, d, n, dx, dy = _group_tls(x, y, gid, keep)
    rss, spread = _line_sums(dx, dy, n, d, gid, keep)
    sigmas = np.maximum(np.sqrt(rss / np.maximum(k - 2.0, 1.0) * inflation), floor)
    offset = n[:, 0] * c[:, 0] + n[:, 1] * c[:, 1]
    return EdgeLines(n, offset, c, spread, sigmas, keep)


def _usable(clear, gid):
    """The points a line is fitted through: an edge's with a clear step, all of them
    where fewer than 5 are clear."""
    n_clear = np.zeros(3)
    for p in range(len(clear)):
        if clear[p]:
            n_clear[gid[p]] += 1.0
    use = np.empty(len(clear), np.bool_)
    for p in range(len(clear)):
        use[p] = clear[p] or n_clear[gid[p]] < 5
    return use


def _usable_numpy(clear, gid):
    """_usable with numpy."""
    return clear | (np.bincount(gid, clear, 3) < 5)[gid]


def _inward_lines(x, y, gid, index, clear, floor, rounds, inflation):
    """The three edge lines through the points (x, y) (edges._lines): _robust_lines
    through the usable ones (_usable), the normals turned into the triangle (towards
    the mean of the edges' centres: a point on each side is inside; compared as sums,
    n . sum < 3 offset). One function for both paths."""
    n, offset, c, spread, sigmas, keep = robust_lines(x, y, gid, index, _usable(clear, gid),
                                                      floor, rounds, inflation)  # fmt: skip
    sx = c[0, 0] + c[1, 0] + c[2, 0]
    sy = c[0, 1] + c[1, 1] + c[2, 1]
    for g in range(3):
        if n[g, 0] * sx + n[g, 1] * sy < 3.0 * offset[g]:
            n[g, 0], n[g, 1], offset[g] = -n[g, 0], -n[g, 1], -offset[g]
    return EdgeLines(n, offset, c, spread, sigmas, keep)


# ------------------------------------------------- a fine pass's lines (_edge_fit)
def _level_gain(width, half, step):
    """edges._level_gain: (3,) px per unit of relative mid-level error, the erf model's
    sum(g) / sum(g^2) over the window's samples, g = exp(-x^2 / 2 w^2) / (sqrt(2 pi) w).
    One implementation: the numpy path runs it as Python, the fast extra compiles it."""
    x = np.arange(-half, half + 1e-9, step)
    out = np.empty(3)
    for e in range(3):
        g = np.exp(-0.5 * (x / width[e]) ** 2) / (_SQRT_2PI * width[e])
        out[e] = np.sum(g) / np.sum(g * g)
    return out


def _edge_stats(sigmas, level_px, h_mid, gid, keep, along, trims, lengths):
    """edges._edge_fit's statistics (an EdgeStats): each edge's per-point sigma with the
    levels' error added (level_px / |h_mid|, common to the edge's profiles
    (edges._level_gain): added per point, so that over the count it is the variance of
    the line's shift from the fitted level line), inlier count (float), outlier share,
    and how far its inliers
    stop short of its two ends beyond the trims ((3, 2); the whole length without
    inliers)."""
    counts = np.zeros(3)
    n_profiles = np.zeros(3)
    s_min = np.full(3, np.inf)
    s_max = np.full(3, -np.inf)
    for j in range(gid.shape[0]):
        e = gid[j]
        n_profiles[e] += 1.0
        if keep[j]:
            counts[e] += 1.0
            s_min[e] = min(s_min[e], along[j])
            s_max[e] = max(s_max[e], along[j])
    sig = np.empty(3)
    outl = np.empty(3)
    gaps = np.empty((3, 2))
    for e in range(3):
        sig[e] = math.hypot(sigmas[e], level_px[e] / max(abs(h_mid[e]), 1e-6))
        outl[e] = 1.0 - counts[e] / n_profiles[e]
        if counts[e] > 0:
            gaps[e, 0] = s_min[e] - trims[(e + 1) % 3]
            gaps[e, 1] = lengths[e] - trims[(e + 2) % 3] - s_max[e]
        else:
            gaps[e, 0] = gaps[e, 1] = lengths[e]
    return EdgeStats(sig, counts, outl, gaps)


def _edge_stats_numpy(sigmas, level_px, h_mid, gid, keep, along, trims, lengths):
    """_edge_stats with numpy."""
    sig = np.hypot(sigmas, level_px / np.maximum(np.abs(h_mid), 1e-6))
    counts = np.bincount(gid, keep, 3)
    n_profiles = np.bincount(gid, minlength=3)
    outl = 1.0 - counts / n_profiles
    starts = np.cumsum(n_profiles) - n_profiles
    s_min = np.minimum.reduceat(np.where(keep, along, np.inf), starts)
    s_max = np.maximum.reduceat(np.where(keep, along, -np.inf), starts)
    gaps = np.where(
        (counts > 0)[:, None],
        np.column_stack([s_min - trims[[1, 2, 0]], lengths - trims[[2, 0, 1]] - s_max]),
        lengths[:, None],
    )
    return EdgeStats(sig, counts, outl, gaps)


def _edge_lag_sums(ideal, gid, keep, normals, offsets, sigmas, lags):
    """edges.lag_sums: per lag j = 0..lags, the sum of z_k z_(k + j) over the inlier
    pairs j profiles apart on one edge (z the residual from the edge's line over its
    sigma) and their count."""
    m = gid.shape[0]
    z = np.zeros(m)
    for k in range(m):
        if keep[k]:
            e = gid[k]
            r = ideal[k, 0] * normals[e, 0] + ideal[k, 1] * normals[e, 1] - offsets[e]
            z[k] = r / sigmas[e]
    out = np.zeros((2, lags + 1))
    for j in range(lags + 1):
        s = 0.0
        p = 0
        for k in range(m - j):
            if keep[k] and keep[k + j] and gid[k] == gid[k + j]:
                s += z[k] * z[k + j]
                p += 1
        out[0, j] = s
        out[1, j] = p
    return out


def _edge_lag_sums_numpy(ideal, gid, keep, normals, offsets, sigmas, lags):
    """_edge_lag_sums with numpy."""
    r = ideal[:, 0] * normals[gid, 0] + ideal[:, 1] * normals[gid, 1] - offsets[gid]
    z = np.where(keep, r / sigmas[gid], 0.0)
    out = np.zeros((2, lags + 1))
    out[0, 0], out[1, 0] = z @ z, np.count_nonzero(keep)
    for j in range(1, lags + 1):
        same = (gid[:-j] == gid[j:]) & keep[:-j] & keep[j:]
        out[0, j] = float(np.sum(z[:-j] * z[j:] * same))
        out[1, j] = np.count_nonzero(same)
    return out


_erf_with_bell = kernel(globals(), "_erf_with_bell", erf_with_bell)
_step_residual = kernel(globals(), "_step_residual", step_residual)
_position_step = kernel(globals(), "_position_step", position_step)
sample_geometry = kernel(globals(), "sample_geometry", _sample_geometry,
                         numpy=_sample_geometry_numpy)  # fmt: skip
_group_linear = kernel(globals(), "_group_linear", _group_linear, numpy=_group_linear_numpy)
_levels_suspect = kernel(globals(), "_levels_suspect", _levels_suspect,
                         numpy=_levels_suspect_numpy)  # fmt: skip
_resistant_residuals = kernel(globals(), "_resistant_residuals", _resistant_residuals,
                              numpy=_resistant_residuals_numpy)  # fmt: skip
_level_inliers = kernel(globals(), "_level_inliers", _level_inliers, numpy=_level_inliers_numpy)
_level_lines = kernel(globals(), "_level_lines", _level_lines)
_edge_starts = kernel(globals(), "_edge_starts", _edge_starts, numpy=_edge_starts_numpy)
_end_levels = kernel(globals(), "_end_levels", _end_levels, numpy=_end_levels_numpy)
_area_positions = kernel(globals(), "_area_positions", _area_positions,
                         numpy=_area_positions_numpy)  # fmt: skip
_position_sums = kernel(globals(), "_position_sums", _position_sums, numpy=_position_sums_numpy)
_level_stats = kernel(globals(), "_level_stats", _level_stats, numpy=_level_stats_numpy)
positions = kernel(globals(), "positions", _positions)
_aligned_slopes = kernel(globals(), "_aligned_slopes", _aligned_slopes,
                         numpy=_aligned_slopes_numpy)  # fmt: skip
_moment_widths = kernel(globals(), "_moment_widths", _moment_widths, numpy=_moment_widths_numpy)
widths = kernel(globals(), "widths", _widths)
_group_tls = kernel(globals(), "_group_tls", _group_tls, numpy=_group_tls_numpy)
group_median = kernel(globals(), "group_median", _group_median, numpy=_group_median_numpy)
_distances = kernel(globals(), "_distances", _distances, numpy=_distances_numpy)
_inliers = kernel(globals(), "_inliers", _inliers, numpy=_inliers_numpy)
_kept_where = kernel(globals(), "_kept_where", _kept_where, numpy=_kept_where_numpy)
_line_sums = kernel(globals(), "_line_sums", _line_sums, numpy=_line_sums_numpy)
_usable = kernel(globals(), "_usable", _usable, numpy=_usable_numpy)
robust_lines = kernel(globals(), "robust_lines", _robust_lines)
inward_lines = kernel(globals(), "inward_lines", _inward_lines)
level_gain = kernel(globals(), "level_gain", _level_gain)
edge_stats = kernel(globals(), "edge_stats", _edge_stats, numpy=_edge_stats_numpy)
edge_lag_sums = kernel(globals(), "edge_lag_sums", _edge_lag_sums, numpy=_edge_lag_sums_numpy)
