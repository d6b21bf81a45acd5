"""Compiled kernels of the edge fit (visvec.detect.edges), of the pixel fit
(visvec.detect.photometric: its pixels, Gauss-Newton steps and noise correlation) and of
the triangle's attitude fit (visvec.estimate.rotation: its Gauss-Newton with the
target's height; visvec.estimate.shear: a frame's rolling-shutter evidence), through
Numba.

A frame's edge fit works on a few hundred profiles of a dozen samples each: numpy spends
most of its time there starting its array operations, not doing them. Each kernel here
is one of edges' functions written as loops over the profiles, the same arithmetic in
the same order where the order matters, so that the results agree with the numpy
functions to rounding (tests/detect/test_compiled.py checks them against each other on
frames of every kind the tests render).

Numba is an optional extra (``pip install "visvec[fast]"``): it compiles these loops to
machine code on first use (cached on disk after that) and has wheels for x86-64 and
aarch64, the flight computers' two architectures. It is imported when a kernel is first
called (_load), all kernels then made at once; until then each module name here holds a
_Lazy stand-in. Without it, or with the environment
variable ``VISVEC_PURE=1``, edges and photometric run their numpy functions.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np

from visvec._kernels import AVAILABLE
from visvec._kernels.edge_fit import EdgeLines
from visvec._kernels.pixel_fit import GaussNewtonSteps, PixelSolve
from visvec.camera import _distorted

numba = None  # the module, once loaded
# whether the kernels run: edges and photometric look here on every call; edges.warm_up
# turns it off when they do not load
ON = AVAILABLE

# Abramowitz & Stegun, Handbook of Mathematical Functions (1964), Eq. 7.1.26, as
# edges.erf_with_bell evaluates it (Horner, a5 first): the edge fit's step model
_AS_P = 0.3275911
_AS_A5 = 1.061405429
_AS_A4 = -1.453152027
_AS_A3 = 1.421413741
_AS_A2 = -0.284496736
_AS_A1 = 0.254829592
_SQRT_PI = math.sqrt(math.pi)
_SQRT_2 = math.sqrt(2.0)
_SQRT_2PI = math.sqrt(2.0 * math.pi)


# the kernels by the names this module calls them by, as they were made (_Lazy)
_KERNELS: dict = {}
_LOADING = threading.Lock()
_loaded = False


class _Lazy:
    """A kernel before Numba is loaded: its first call loads every kernel (_load) and
    is passed on to its dispatcher (or, where Numba did not import, to the plain
    function). ``py_func``: the kernel as Python, as a dispatcher's."""

    def __init__(self, name, f):
        self.__name__ = name
        self.py_func = f
        self.dispatcher = None

    def __call__(self, *args):
        if self.dispatcher is None:
            _load()
        # (after a Numba that did not import: the plain function)
        return (self.py_func if self.dispatcher is None else self.dispatcher)(*args)


def _load():
    """Import Numba and put every kernel's dispatcher in its place among this module's
    names at once (where nothing else was put there), so that a kernel calling another
    compiles against the other's dispatcher. A Numba that cannot be imported turns the
    kernels off (ON) and leaves the plain functions in their places."""
    global numba, ON, _loaded
    with _LOADING:
        if _loaded:
            return
        _loaded = True
        names = globals()
        made = {}
        try:
            import numba as nb

            for k in _KERNELS.values():
                if id(k.py_func) not in made:
                    # cache: compiled once per machine, loaded from disk after that;
                    # nogil: the live paths' threads run beside it; no fastmath: sums
                    # taken in the order written
                    made[id(k.py_func)] = nb.njit(cache=True, nogil=True)(k.py_func)
        except Exception as exc:  # a Numba that cannot import here or make them: numpy
            ON = False
            for name, k in _KERNELS.items():
                if names[name] is k:
                    names[name] = k.py_func
            if not isinstance(exc, ImportError):
                raise  # (warm_up says why)
            print(f"visvec: Numba did not import ({exc}); the numpy path runs",
                  file=sys.stderr)  # fmt: skip
            return
        for name, k in _KERNELS.items():
            k.dispatcher = made[id(k.py_func)]
            if names[name] is k:
                names[name] = k.dispatcher
        numba = nb


def _jit(f, name):
    """The kernel ``f`` known as ``name`` in this module: compiled on its first call
    (with the fast extra), else the plain function."""
    if not AVAILABLE:
        return f
    _KERNELS[name] = _Lazy(name, f)
    return _KERNELS[name]


# ---------------------------------------------------------------- profiles (_sample)
def _sample_geometry(corners, off, offs, trims, spacing, max_per_edge):
    """edges._sample but for its cv2.remap: the profiles' bases, normals, edge, index
    along the edge, t in [-1, 1], distance along, the edges' lengths and the sample
    maps (float32, x and y)."""
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
    return bases, normals, gid, k, tt, along, map_x, map_y, length


# ------------------------------------------------------- levels (_level_lines and co)
def _group_linear(t, y, gid, keep, use_keep):
    """edges._group_linear for one y: each edge's least-squares line of y against t
    (over ``keep`` when use_keep), evaluated at every t."""
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


def _levels_suspect(r_lo, r_hi, lo_raw, hi_raw, starts, suspect_rms, suspect_max):
    """edges._levels_suspect (the edges' profiles from ``starts`` (4,) on)."""
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


def _level_lines(t, lo_raw, hi_raw, gid, starts, outlier_sigmas, outlier_min,
                 suspect_rms, suspect_max):  # fmt: skip
    """edges._level_lines: lo, hi on the final lines and the profiles whose levels
    passed."""
    m_all = len(t)
    none = np.zeros(0, np.bool_)
    lo = _group_linear(t, lo_raw, gid, none, False)
    hi = _group_linear(t, hi_raw, gid, none, False)
    ok = np.ones(m_all, np.bool_)
    if not _levels_suspect(lo_raw - lo, hi_raw - hi, lo_raw, hi_raw, starts, suspect_rms,
                           suspect_max):  # fmt: skip
        return lo, hi, ok
    res_lo = np.empty(m_all)
    res_hi = np.empty(m_all)
    lim_lo = np.empty(3)
    lim_hi = np.empty(3)
    for g in range(3):
        a, c = starts[g], starts[g + 1] - starts[g]
        n0 = c // 2
        # resistant lines through the medians of each half's levels, at the halves'
        # middle t (t ascends along the edge)
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
    have = False
    new = np.empty(m_all, np.bool_)
    for _ in range(2):
        cnt = np.zeros(3)
        for p in range(m_all):
            g = gid[p]
            new[p] = res_lo[p] <= lim_lo[g] and res_hi[p] <= lim_hi[g]
            if new[p]:
                cnt[g] += 1.0
        for p in range(m_all):
            if cnt[gid[p]] < 5:
                new[p] = True
        if have:
            same = True
            for p in range(m_all):
                if new[p] != ok[p]:
                    same = False
                    break
            if same:
                break
        ok = new.copy()
        have = True
        every = True
        for p in range(m_all):
            if not ok[p]:
                every = False
                break
        lo = _group_linear(t, lo_raw, gid, ok, not every)
        hi = _group_linear(t, hi_raw, gid, ok, not every)
        for p in range(m_all):
            res_lo[p] = abs(lo_raw[p] - lo[p])
            res_hi[p] = abs(hi_raw[p] - hi[p])
    return lo, hi, ok


# ------------------------------------------------------------------ step positions
def _positions(vals, t, gid, half, step, width, n_ext, ends, gn_steps,
               outlier_sigmas, outlier_min, suspect_rms, suspect_max):  # fmt: skip
    """edges._positions: each profile's step position, its step height, per edge the
    mid level and the levels' scatter, and the profiles whose levels agree (the edges'
    profiles one after the other, as _sample gives them)."""
    m_all = vals.shape[0]
    starts = np.zeros(4, np.int64)
    for p in range(m_all):
        starts[gid[p] + 1] += 1
    for g in range(3):
        starts[g + 1] += starts[g]
    n_tot = vals.shape[1]
    # the means of the first and last ``ends`` samples, in float32 as numpy takes the
    # mean of float32 samples
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
    lo, hi, level_ok = _level_lines(t, lo_raw, hi_raw, gid, starts, outlier_sigmas,
                                    outlier_min, suspect_rms, suspect_max)  # fmt: skip
    s_in = n_tot - 2 * n_ext
    e = np.empty(m_all)
    f = np.empty(s_in)
    fit = len(width) == 3
    for p in range(m_all):
        h = hi[p] - lo[p]
        safe = h if abs(h) > 1e-6 else 1e-6
        total = 0.0
        for j in range(s_in):
            f[j] = (vals[p, n_ext + j] - lo[p]) / safe
            total += f[j]
        ep = half - step * (total - 0.5 * (f[0] + f[s_in - 1]))
        if fit:
            s2 = _SQRT_2 * width[gid[p]]
            gden = _SQRT_PI * s2
            for _ in range(gn_steps):
                num = 0.0
                den = 0.0
                for j in range(s_in):
                    u = (-half + j * step - ep) / s2
                    bell = math.exp(-u * u)
                    q = 1.0 / (_AS_P * abs(u) + 1.0)
                    y = ((((_AS_A5 * q + _AS_A4) * q + _AS_A3) * q + _AS_A2) * q + _AS_A1) * q
                    erf = 1.0 - y * bell
                    if u < 0.0:
                        erf = -erf
                    r = f[j] - 0.5 * (1.0 + erf)
                    g = bell / gden
                    num += r * g
                    den += g * g
                ep = ep - min(max(num / max(den, 1e-12), -0.5), 0.5)
        e[p] = ep
    cnt = np.zeros(3)
    s_lo = np.zeros(3)
    s_hi = np.zeros(3)
    s_res = np.zeros(3)
    for p in range(m_all):
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
    return e, hi_raw - lo_raw, mid, level_sd, level_ok


# ---------------------------------------------------------------------- blur widths
def _widths(vals, n_ext, e, clear, gid, half, step, reach_min):
    """edges._widths on the profiles vals[:, n_ext : -n_ext]."""
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
    w = np.empty(3)
    reach = np.full(3, np.inf)
    rounds = 2 if half > reach_min else 1
    for _ in range(rounds):
        for g in range(3):
            tot = 0.0
            gx = 0.0
            for b in range(nb3):
                if abs(x[b]) <= reach[g]:
                    tot += g_all[g, b]
                    gx += g_all[g, b] * x[b]
            safe = tot if tot > 0 else 1.0
            c = gx / safe
            w2 = 0.0
            for b in range(nb3):
                if abs(x[b]) <= reach[g]:
                    w2 += g_all[g, b] * (x[b] - c) ** 2
            w2 = w2 / safe
            if tot > 0 and w2 > 0:
                w[g] = min(math.sqrt(w2), half / 2.0)
            else:
                w[g] = half / 3.0
        for g in range(3):
            reach[g] = max(4.0 * w[g], reach_min)
    return w


def _group_median(a, gid, keep):
    """edges._group_median: (3,) the median of ``a`` over each edge's kept points, 0
    where an edge keeps none."""
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


# ------------------------------------------------------------------- robust lines
def _group_tls(x, y, gid, keep):
    """edges._group_tls."""
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
        a = 0.5 * math.atan2(2.0 * sxy[g], sxx[g] - syy[g])
        d[g, 0] = math.cos(a)
        d[g, 1] = math.sin(a)
        n[g, 0] = -d[g, 1]
        n[g, 1] = d[g, 0]
    return k, c, d, n, dx, dy


def _robust_lines(x, y, gid, use, floor, rounds, inflation):
    """edges._robust_lines: normals, offsets, centres, spreads, sigmas and the inliers."""
    m_all = len(x)
    keep = use.copy()
    k, c, d, n, dx, dy = _group_tls(x, y, gid, keep)
    active = np.ones(3, np.bool_)
    a = np.empty(m_all)
    new = np.empty(m_all, np.bool_)
    for _ in range(rounds):
        sigma = np.empty(3)
        for p in range(m_all):
            g = gid[p]
            a[p] = abs(dx[p] * n[g, 0] + dy[p] * n[g, 1])
        med = _group_median(a, gid, keep)
        for g in range(3):
            sigma[g] = max(1.4826 * med[g], floor)
        changed = np.zeros(3, np.bool_)
        n_new = np.zeros(3)
        for p in range(m_all):
            g = gid[p]
            new[p] = use[p] and a[p] <= max(3.5 * sigma[g], 0.25)
            if new[p] != keep[p]:
                changed[g] = True
            if new[p]:
                n_new[g] += 1.0
        any_active = False
        for g in range(3):
            active[g] = active[g] and changed[g] and n_new[g] >= 5
            any_active = any_active or active[g]
        if not any_active:
            break
        for p in range(m_all):
            if active[gid[p]]:
                keep[p] = new[p]
        k, c, d, n, dx, dy = _group_tls(x, y, gid, keep)
    rss = np.zeros(3)
    spread = np.zeros(3)
    for p in range(m_all):
        if keep[p]:
            g = gid[p]
            r = dx[p] * n[g, 0] + dy[p] * n[g, 1]
            t = dx[p] * d[g, 0] + dy[p] * d[g, 1]
            rss[g] += r * r
            spread[g] += t * t
    sigmas = np.empty(3)
    offset = np.empty(3)
    for g in range(3):
        sigmas[g] = max(math.sqrt(rss[g] / max(k[g] - 2.0, 1.0) * inflation), floor)
        offset[g] = n[g, 0] * c[g, 0] + n[g, 1] * c[g, 1]
    return EdgeLines(n, offset, c, spread, sigmas, keep)


def _inward_lines(x, y, gid, clear, floor, rounds, inflation):
    """edges._lines after its points: each edge's points with a clear step (all of them
    where fewer than 5 are clear) through _robust_lines, the normals turned into the
    triangle (towards the mean of the edges' centres)."""
    m_all = len(x)
    n_clear = np.zeros(3)
    for p in range(m_all):
        if clear[p]:
            n_clear[gid[p]] += 1.0
    use = np.empty(m_all, np.bool_)
    for p in range(m_all):
        use[p] = clear[p] or n_clear[gid[p]] < 5
    n, offset, c, spread, sigmas, keep = robust_lines(x, y, gid, use, floor, rounds, inflation)
    sx = c[0, 0] + c[1, 0] + c[2, 0]
    sy = c[0, 1] + c[1, 1] + c[2, 1]
    for g in range(3):
        if n[g, 0] * sx + n[g, 1] * sy < 3.0 * offset[g]:
            n[g, 0], n[g, 1], offset[g] = -n[g, 0], -n[g, 1], -offset[g]
    return EdgeLines(n, offset, c, spread, sigmas, keep)


# ------------------------------------------------- the pixel fit's noise correlation
def _lag_sums(index, flat, offsets, r, w):
    """photometric._noise_inflation's sums: per lag (offset in the padded raster), the
    band's pixel pairs at that lag and the sums of r r' and w w' over them (``index``:
    each raster cell's pixel, len(r) where none is; ``flat``: each pixel's cell). Lag
    by lag, without a branch: a cell with no pixel gives the zero appended to r and w
    (the sums are those of the pairs, in the same order)."""
    n = len(r)
    lags = len(offsets)
    r0 = np.zeros(n + 1)
    w0 = np.zeros(n + 1)
    r0[:n] = r
    w0[:n] = w
    pairs = np.zeros(lags)
    rr = np.zeros(lags)
    ww = np.zeros(lags)
    for q in range(lags):
        o = offsets[q]
        sp, sr, sw = 0.0, 0.0, 0.0
        for k in range(n):
            j = index[flat[k] + o]
            sp += 1.0 if j < n else 0.0
            sr += r[k] * r0[j]
            sw += w[k] * w0[j]
        pairs[q], rr[q], ww[q] = sp, sr, sw
    return pairs, rr, ww


def _noise_inflation(uv, r, w, lags, L, min_pairs):
    """photometric._noise_inflation compiled: the raster of the band's pixels, the sums
    over their pairs at each lag (_lag_sums), the inflation from them."""
    n = len(r)
    var = 0.0
    den = 0.0
    for k in range(n):
        var += r[k] * r[k]
        den += w[k] * w[k]
    var /= n
    if not (var > 0 and den > 0):
        return 1.0
    u0, v0 = uv[0, 0], uv[0, 1]
    u1, v1 = u0, v0
    for k in range(n):
        u0, u1 = min(u0, uv[k, 0]), max(u1, uv[k, 0])
        v0, v1 = min(v0, uv[k, 1]), max(v1, uv[k, 1])
    width = u1 - u0 + 2 * L + 1
    # unsigned cells, pixels and lags (a half-plane's offsets are all positive): Numba
    # then indexes without checking for a negative index, which took 40 % of the sums
    flat = np.empty(n, np.uint64)
    index = np.full((v1 - v0 + 2 * L + 1) * width, n, np.uint32)
    for k in range(n):
        flat[k] = (uv[k, 1] - v0 + L) * width + (uv[k, 0] - u0 + L)
        index[flat[k]] = k
    offsets = (lags[:, 1] * width + lags[:, 0]).astype(np.uint64)
    pairs, rr, ww = _lag_sums(index, flat, offsets, r, w)
    excess = 0.0
    scatter2 = 0.0
    for q in range(len(offsets)):
        if pairs[q] >= min_pairs:
            share = ww[q] / den
            excess += rr[q] / pairs[q] / var * share
            scatter2 += share * share / pairs[q]
    return 1.0 + max(2.0 * excess - 4.0 * math.sqrt(scatter2), 0.0)


# ------------------------------------------------------------------- the pixel fit
def _band_pixels(pts, given, grid, cx, cy, aspect, lens, image, n, o, reach, clear):
    """photometric._band's pixels: of the pixels its drawn bands cover (``pts``, (P, 2)
    column and row, in raster order) those each edge's exact rule takes, edge after
    edge: their ideal coordinates (M, 2) (``given`` (P, 2), or when that is empty
    photometric._IdealGrid's: the pinhole's, plus with ``lens`` the correction in
    ``grid``), grey levels (M,), places in the frame (M, 2) and each edge's count
    (3,)."""
    total = len(pts)
    # each edge's pixels (their places in pts, in raster order), found in one pass
    picked = np.empty((3, total), np.int64)
    counts = np.zeros(3, np.int64)
    xy = np.empty((total, 2))
    for p in range(total):
        col, row = pts[p, 0], pts[p, 1]
        if len(given):
            x0, x1 = given[p, 0], given[p, 1]
        else:
            x0, x1 = col - cx, (row - cy) * aspect
            if lens:
                x0 += grid[row, col, 0]
                x1 += grid[row, col, 1]
        xy[p, 0], xy[p, 1] = x0, x1
        d0 = x0 * n[0, 0] + x1 * n[0, 1] - o[0]
        d1 = x0 * n[1, 0] + x1 * n[1, 1] - o[1]
        d2 = x0 * n[2, 0] + x1 * n[2, 1] - o[2]
        # a pixel is an edge's when within its reach and clear of the other two
        if abs(d0) < reach[0] and d1 > clear[1] and d2 > clear[2]:
            picked[0, counts[0]] = p
            counts[0] += 1
        if abs(d1) < reach[1] and d2 > clear[2] and d0 > clear[0]:
            picked[1, counts[1]] = p
            counts[1] += 1
        if abs(d2) < reach[2] and d0 > clear[0] and d1 > clear[1]:
            picked[2, counts[2]] = p
            counts[2] += 1
    m = counts[0] + counts[1] + counts[2]
    xs = np.empty((m, 2))
    ys = np.empty(m)
    uv = np.empty((m, 2), np.int64)
    k = 0
    for i in range(3):
        for q in range(counts[i]):
            p = picked[i, q]
            col, row = pts[p, 0], pts[p, 1]
            xs[k, 0] = xy[p, 0]
            xs[k, 1] = xy[p, 1]
            ys[k] = image[row, col]
            uv[k, 0] = col
            uv[k, 1] = row
            k += 1
    return xs, ys, uv, counts


def _cover(q, lo0, lo1, hi0, hi1):
    """photometric._cover compiled: the pixels (column, row) (P, 2) in raster order
    that the three convex quadrilaterals ``q`` (12, 2) (px, four corners each) cover
    with a pixel's margin, within columns lo0..hi0 and rows lo1..hi1: per row the
    columns from each quadrilateral's least x, less one, to its greatest plus one, over
    the strip of rows within one of the row; their union."""
    rows = hi1 - lo1 + 1
    c0 = np.full((rows, 3), 1, np.int64)
    c1 = np.zeros((rows, 3), np.int64)
    total = 0
    for r in range(rows):
        a, b = float(lo1 + r) - 1.0, float(lo1 + r) + 1.0
        for i in range(3):
            xmin, xmax = math.inf, -math.inf
            for k in range(4):
                x0, y0 = q[4 * i + k, 0], q[4 * i + k, 1]
                x1, y1 = q[4 * i + (k + 1) % 4, 0], q[4 * i + (k + 1) % 4, 1]
                if y1 == y0:  # a side along a row: all of it or none
                    t0, t1 = (0.0, 1.0) if a <= y0 <= b else (1.0, 0.0)
                else:
                    ta, tb = (a - y0) / (y1 - y0), (b - y0) / (y1 - y0)
                    t0, t1 = max(min(ta, tb), 0.0), min(max(ta, tb), 1.0)
                if t0 <= t1:
                    xa, xb = x0 + t0 * (x1 - x0), x0 + t1 * (x1 - x0)
                    xmin, xmax = min(xmin, xa, xb), max(xmax, xa, xb)
            if xmin <= xmax:
                c0[r, i] = max(math.ceil(xmin - 1.0), lo0)
                c1[r, i] = min(math.floor(xmax + 1.0), hi0)
        # the three ranges by their first column (an empty one's is past hi0)
        for i in range(3):
            if c1[r, i] < c0[r, i]:
                c0[r, i], c1[r, i] = hi0 + 1, hi0
        for i in (1, 2, 1):
            if c0[r, i] < c0[r, i - 1]:
                c0[r, i], c0[r, i - 1] = c0[r, i - 1], c0[r, i]
                c1[r, i], c1[r, i - 1] = c1[r, i - 1], c1[r, i]
        # their union, counted once
        last = lo0 - 1
        for i in range(3):
            total += max(c1[r, i] - max(c0[r, i], last + 1) + 1, 0)
            last = max(last, c1[r, i])
    pts = np.empty((total, 2), np.int64)
    p = 0
    for r in range(rows):
        last = lo0 - 1
        for i in range(3):
            for u in range(max(c0[r, i], last + 1), c1[r, i] + 1):
                pts[p, 0], pts[p, 1] = u, lo1 + r
                p += 1
            last = max(last, c1[r, i])
    return pts


def _band_lines(image, n, c, reach, clear, fx, fy, cx, cy, dist, last_col, last_row, grid,
                gcx, gcy, aspect, lens):  # fmt: skip
    """photometric._band compiled, without a rolling shutter: the three bands'
    quadrilaterals from the lines n_i . (x - c_i) = 0 (photometric._meet), their corners
    through the lens (camera.distort's polynomial), the box they span in the frame, the
    pixels they cover (_cover) and those each edge's rule takes (_band_pixels). Returns
    whether there were any, then _band_pixels' arrays."""
    o = np.empty(3)
    for i in range(3):
        o[i] = n[i, 0] * c[i, 0] + n[i, 1] * c[i, 1]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    q = np.empty((12, 2))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        for s, (sgn, other) in enumerate(((-1.0, j), (-1.0, k), (1.0, k), (1.0, j))):
            oi = o[i] + sgn * (reach[i] + 1.5)
            o2 = o[other] + clear[other]
            det = n[i, 0] * n[other, 1] - n[i, 1] * n[other, 0]
            x = (oi * n[other, 1] - o2 * n[i, 1]) / det / fx
            y = (n[i, 0] * o2 - n[other, 0] * oi) / det / fx
            xd, yd = distorted(x, y, k1, k2, p1, p2, k3)
            q[4 * i + s, 0] = fx * xd + cx
            q[4 * i + s, 1] = fy * yd + cy
    empty = (np.empty((0, 2)), np.empty(0), np.empty((0, 2), np.int64), np.zeros(3, np.int64))
    if not np.all(np.isfinite(q)):
        return False, *empty
    lo0 = max(math.floor(q[:, 0].min()) - 1, 0)
    lo1 = max(math.floor(q[:, 1].min()) - 1, 0)
    hi0 = min(math.ceil(q[:, 0].max()) + 1, last_col)
    hi1 = min(math.ceil(q[:, 1].max()) + 1, last_row)
    if hi0 <= lo0 or hi1 <= lo1:
        return False, *empty
    pts = _cover(q, lo0, lo1, hi0, hi1)
    if len(pts) == 0:
        return False, *empty
    xs, ys, uv, counts = _band_pixels(pts, np.empty((0, 2)), grid, gcx, gcy, aspect, lens, image,
                                      n, o, reach, clear)  # fmt: skip
    return True, xs, ys, uv, counts


def _phi_of(u, table, rng, inv_step):
    """photometric._phi_of at one u: Phi(u) and phi(u) from ``table`` (photometric._PHI,
    its nodes 1 / ``inv_step`` apart from -``rng``), the same expressions in the same
    order."""
    t = (min(max(u, -rng), rng) + rng) * inv_step
    # (unsigned: Numba indexes the table without checking for a negative index)
    i = min(np.uint64(t), np.uint64(table.shape[0] - 2))
    f = t - i
    f2 = f * f
    f3 = f2 * f
    h00 = 2.0 * f3 - 3.0 * f2 + 1.0
    h10 = f3 - 2.0 * f2 + f
    h01 = 3.0 * f2 - 2.0 * f3
    h11 = f3 - f2
    step = h00 * table[i, 0] + h10 * table[i, 1] + h01 * table[i + 1, 0] + h11 * table[i + 1, 1]
    slope = h00 * table[i, 2] + h10 * table[i, 3] + h01 * table[i + 1, 2] + h11 * table[i + 1, 3]
    return step, slope


def _pixel_gn(x, y, counts, n, c, w, centroid, scale, steps, table, rng, inv_step):
    """photometric._gauss_newton compiled: the same model, parameters and steps; each
    edge's Jacobian (9, m_e) filled pixel by pixel, its normal equations by BLAS. The
    three edges' Jacobians lie one after another in one buffer, each C-contiguous, so
    that BLAS takes them in place (a copy of each edge's columns of one (9, m) array
    cost a tenth of a step)."""
    m = len(y)
    n = n.copy()
    c = c.copy()
    w = w.copy()
    H = np.zeros((15, 15))
    b = np.zeros(15)
    level = np.zeros(6)
    r_all = np.empty(m)
    g_all = np.empty(m)
    u_all = np.empty(m)
    perp_all = np.empty(m)
    slope_all = np.empty(m)
    bounds = np.zeros(4, np.int64)
    for e in range(3):
        bounds[e + 1] = bounds[e] + counts[e]
    buf = np.empty(9 * m)
    # the board's plane's columns (1, x, y about the centroid, scaled), then T times them
    for e in range(3):
        Je = buf[9 * bounds[e] : 9 * bounds[e + 1]].reshape((9, counts[e]))
        for k in range(counts[e]):
            p = bounds[e] + k
            Je[3, k] = 1.0
            Je[4, k] = (x[p, 0] - centroid[0]) / scale
            Je[5, k] = (x[p, 1] - centroid[1]) / scale
    # each edge's parameters: its line's rotation and offset, its width, the six levels
    idx = np.empty(9, np.int64)
    for q in range(6):
        idx[3 + q] = 9 + q
    rss = 0.0
    for it in range(steps):
        for e in range(3):
            Je = buf[9 * bounds[e] : 9 * bounds[e + 1]].reshape((9, counts[e]))
            nx, ny, cx, cy, we = n[e, 0], n[e, 1], c[e, 0], c[e, 1], w[e]
            for k in range(counts[e]):
                p = bounds[e] + k
                rx, ry = x[p, 0] - cx, x[p, 1] - cy
                u = (rx * nx + ry * ny) / we
                T, slope = _phi_of(u, table, rng, inv_step)
                u_all[p] = u
                perp_all[p] = rx * -ny + ry * nx
                slope_all[p] = slope
                Je[6, k] = T
                Je[7, k] = T * Je[4, k]
                Je[8, k] = T * Je[5, k]
        if it == 0:
            # the levels from the starting lines, by linear least squares
            AtA = np.zeros((6, 6))
            Aty = np.zeros(6)
            for e in range(3):
                A = buf[9 * bounds[e] : 9 * bounds[e + 1]].reshape((9, counts[e]))[3:9]
                AtA += A @ A.T
                Aty += A @ y[bounds[e] : bounds[e + 1]]
            try:
                level = np.linalg.solve(AtA, Aty)
            except Exception:  # noqa: BLE001 - Numba catches no narrower class
                return GaussNewtonSteps(n, c, w, level, H, b, rss, r_all, g_all, False)
        H[:, :] = 0.0
        b[:] = 0.0
        rss = 0.0
        for e in range(3):
            Je = buf[9 * bounds[e] : 9 * bounds[e + 1]].reshape((9, counts[e]))
            we = w[e]
            for k in range(counts[e]):
                p = bounds[e] + k
                X, Y, T = Je[4, k], Je[5, k], Je[6, k]
                C = level[3] + level[4] * X + level[5] * Y
                r = y[p] - (level[0] + level[1] * X + level[2] * Y + T * C)
                g = C * slope_all[p] / we
                rss += r * r
                r_all[p] = r
                g_all[p] = g
                Je[0, k] = g * perp_all[p]
                Je[1, k] = -g
                Je[2, k] = -g * u_all[p]
            He = Je @ Je.T
            be = Je @ r_all[bounds[e] : bounds[e + 1]]
            idx[0], idx[1], idx[2] = 2 * e, 2 * e + 1, 6 + e
            for q in range(9):
                b[idx[q]] += be[q]
                for s in range(9):
                    H[idx[q], idx[s]] += He[q, s]
        try:
            step = np.linalg.solve(H, b)
        except Exception:  # noqa: BLE001
            return GaussNewtonSteps(n, c, w, level, H, b, rss, r_all, g_all, False)
        for e in range(3):
            th, oo = step[2 * e], step[2 * e + 1]
            cs, sn = math.cos(th), math.sin(th)
            n0 = cs * n[e, 0] - sn * n[e, 1]
            n1 = sn * n[e, 0] + cs * n[e, 1]
            n[e, 0], n[e, 1] = n0, n1
            c[e, 0] += oo * n0
            c[e, 1] += oo * n1
            w[e] = max(w[e] + step[6 + e], 0.2)
        for q in range(6):
            level[q] += step[9 + q]
        rss -= step @ b
    return GaussNewtonSteps(n, c, w, level, H, b, rss, r_all, g_all, True)


def _strided(x, y, counts, stride):
    """photometric._strided: every ``stride``-th pixel of each band."""
    cs = (counts + stride - 1) // stride
    m = cs[0] + cs[1] + cs[2]
    xs = np.empty((m, 2))
    ys = np.empty(m)
    k = 0
    start = 0
    for e in range(3):
        for p in range(start, start + counts[e], stride):
            xs[k, 0], xs[k, 1] = x[p, 0], x[p, 1]
            ys[k] = y[p]
            k += 1
        start += counts[e]
    return xs, ys, cs


def _pixel_solve(x, y, uv, counts, n, c, w, V, centroid, scale, warm, st):
    """photometric._solve compiled: the same steps, checks, inflation and covariance;
    ``st`` the fit's constants (PixelFitSettings). A PixelSolve."""
    table, rng, inv_step = st.table, st.rng, st.inv_step
    steps, stride = st.steps, st.stride
    fail = np.full((6, 6), np.nan)
    if warm:
        # from the run's blur: one step on every pixel, another while the last moved a
        # width by more than ``settled``, ``warm_steps`` at most
        out = _pixel_gn(x, y, counts, n, c, w, centroid, scale, 1, table, rng, inv_step)
        steps = 1
        while steps < st.warm_steps and out.ok:
            moved = 0.0
            for e in range(3):
                moved = max(moved, abs(out.w[e] / w[e] - 1.0))
            if moved <= st.settled:
                break
            w = out.w
            out = _pixel_gn(x, y, counts, out.n, out.c, w, centroid, scale, 1, table, rng,
                            inv_step)  # fmt: skip
            steps += 1
    else:
        if steps > 1 and stride > 1:
            xs, ys, cs = _strided(x, y, counts, stride)
            first = _pixel_gn(xs, ys, cs, n, c, w, centroid, scale, steps - 1, table, rng,
                              inv_step)  # fmt: skip
            n, c, w = first.n, first.c, first.w
            if not first.ok:
                return PixelSolve(False, V, fail, w, math.nan, 1.0, 0)
            steps = 1
        out = _pixel_gn(x, y, counts, n, c, w, centroid, scale, steps, table, rng, inv_step)
    n, c, w, _, H, _, rss, r, g, ok = out
    if not ok:
        return PixelSolve(False, V, fail, w, math.nan, 1.0, steps)
    m = len(y)
    s2 = max(rss, 0.0) / max(m - 15, 1)
    rms = np.empty(3)
    start = 0
    for e in range(3):
        ss = 0.0
        for p in range(start, start + counts[e]):
            ss += r[p] * r[p]
        rms[e] = math.sqrt(ss / counts[e])
        start += counts[e]
    rms.sort()
    if rms[2] > st.rms_ratio * rms[1]:
        return PixelSolve(False, V, fail, w, s2, 1.0, steps)
    inflation = noise_inflation(uv, r, g, st.lags, st.lag_px, st.min_pairs)
    try:
        Hi = np.linalg.inv(H)
    except Exception:  # noqa: BLE001 - Numba catches no narrower class
        return PixelSolve(False, V, fail, w, s2, inflation, steps)
    cov_p = inflation * s2 * np.ascontiguousarray(Hi[:6, :6])
    # the vertices (edges._vertices: vertex i on lines i + 1, i + 2, Cramer's rule) and
    # how the lines move them (photometric._vertex_gain)
    V2 = np.empty((3, 2))
    invs = np.empty((3, 2, 2))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        a, b, cc, d = n[j, 0], n[j, 1], n[k, 0], n[k, 1]
        det = a * d - b * cc
        if det == 0.0:
            return PixelSolve(False, V, fail, w, s2, inflation, steps)
        invs[i, 0, 0], invs[i, 0, 1] = d / det, -b / det
        invs[i, 1, 0], invs[i, 1, 1] = -cc / det, a / det
        oj = n[j, 0] * c[j, 0] + n[j, 1] * c[j, 1]
        ok_ = n[k, 0] * c[k, 0] + n[k, 1] * c[k, 1]
        V2[i, 0] = invs[i, 0, 0] * oj + invs[i, 0, 1] * ok_
        V2[i, 1] = invs[i, 1, 0] * oj + invs[i, 1, 1] * ok_
    G = np.zeros((6, 6))
    for v in range(3):
        for row in range(2):
            ln = (v + 1 + row) % 3
            nx, ny = n[ln, 0], n[ln, 1]
            sv = (V2[v, 0] - c[ln, 0]) * -ny + (V2[v, 1] - c[ln, 1]) * nx
            for q in range(2):
                G[2 * v + q, 2 * ln] -= invs[v, q, row] * sv
                G[2 * v + q, 2 * ln + 1] += invs[v, q, row]
    return PixelSolve(True, V2, G @ cov_p @ G.T, w, s2, inflation, steps)


# ------------------------------------------------- a fine pass's lines (_edge_fit)
def _level_gain(width, half, step):
    """edges._level_gain: (3,) px per unit of relative mid-level error, the erf model's
    sum(g) / sum(g^2) over the window's samples."""
    x = np.arange(-half, half + 1e-9, step)
    out = np.empty(3)
    for e in range(3):
        w = width[e]
        s1 = 0.0
        s2 = 0.0
        for k in range(x.shape[0]):
            g = math.exp(-0.5 * (x[k] / w) ** 2) / (_SQRT_2PI * w)
            s1 += g
            s2 += g * g
        out[e] = s1 / s2
    return out


def _edge_stats(sigmas, level_px, h_mid, gid, keep, along, trims, lengths):
    """edges._edge_fit's statistics: each edge's per-point sigma with the levels' error
    added, inlier count (float), outlier share, and how far its inliers stop short of
    its two ends beyond the trims ((3, 2); the whole length without inliers)."""
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
    return sig, counts, outl, gaps


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


# ------------------------------------- the triangle's attitude (estimate.rotation)
def _expmap(w0, w1, w2):
    """visvec.rotations.expmap_xyz: Rodrigues' formula, its series below 1e-8 rad."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        t = math.sqrt(t2)
        a, b = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    E = np.empty((3, 3))
    E[0, 0] = 1.0 - b * (w1 * w1 + w2 * w2)
    E[0, 1] = b * w0 * w1 - a * w2
    E[0, 2] = b * w0 * w2 + a * w1
    E[1, 0] = b * w0 * w1 + a * w2
    E[1, 1] = 1.0 - b * (w0 * w0 + w2 * w2)
    E[1, 2] = b * w1 * w2 - a * w0
    E[2, 0] = b * w0 * w2 - a * w1
    E[2, 1] = b * w1 * w2 + a * w0
    E[2, 2] = 1.0 - b * (w0 * w0 + w1 * w1)
    return E


def _closed_form_3(t_c, X, xy):
    """visvec.estimate.rotation.initial_rotation for three points: the closed-form
    rotation from three bearings (each branch of the depths in front, Procrustes by SVD;
    the better reprojecting of two). Returns (found, R)."""
    tt = t_c[0] * t_c[0] + t_c[1] * t_c[1] + t_c[2] * t_c[2]
    b = np.empty((3, 3))
    bt = np.empty(3)
    root = np.empty(3)
    for i in range(3):
        n = math.sqrt(xy[i, 0] * xy[i, 0] + xy[i, 1] * xy[i, 1] + 1.0)
        b[i, 0], b[i, 1], b[i, 2] = xy[i, 0] / n, xy[i, 1] / n, 1.0 / n
        bt[i] = b[i, 0] * t_c[0] + b[i, 1] * t_c[1] + b[i, 2] * t_c[2]
        disc = bt[i] * bt[i] - tt + (X[i, 0] * X[i, 0] + X[i, 1] * X[i, 1] + X[i, 2] * X[i, 2])
        root[i] = math.sqrt(disc) if disc > 0.0 else 0.0
    best = np.eye(3)
    n_found = 0
    best_cost = np.inf
    for sign in (1.0, -1.0):
        lam = bt + sign * root
        if lam.min() <= 0:
            continue
        V = np.empty((3, 3))
        for k in range(3):
            for j in range(3):
                V[k, j] = lam[k] * b[k, j] - t_c[j]
        H = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                H[i, j] = X[0, i] * V[0, j] + X[1, i] * V[1, j] + X[2, i] * V[2, j]
        U, _, Vt = np.linalg.svd(H)
        d = np.linalg.det(U) * np.linalg.det(Vt)
        s = 1.0 if d == 0.0 else math.copysign(1.0, d)
        R = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                R[i, j] = Vt[0, i] * U[j, 0] + Vt[1, i] * U[j, 1] + s * Vt[2, i] * U[j, 2]
        cost = 0.0
        behind = False
        for k in range(3):
            p0 = R[0, 0] * X[k, 0] + R[0, 1] * X[k, 1] + R[0, 2] * X[k, 2] + t_c[0]
            p1 = R[1, 0] * X[k, 0] + R[1, 1] * X[k, 1] + R[1, 2] * X[k, 2] + t_c[1]
            p2 = R[2, 0] * X[k, 0] + R[2, 1] * X[k, 1] + R[2, 2] * X[k, 2] + t_c[2]
            if p2 <= 0:
                behind = True
            cost += (p0 / p2 - xy[k, 0]) ** 2 + (p1 / p2 - xy[k, 1]) ** 2
        if behind:
            continue
        n_found += 1
        if n_found == 1 or cost < best_cost:
            best, best_cost = R, cost
    return n_found > 0, best


def _gn_shift(R, t_c, X, xy, W, axis, mean, w_s, max_iterations, tol_rad2, tol_shift):
    """visvec.estimate.rotation._gauss_newton_shift, in (d, s): each iteration its
    residuals and Jacobian (residuals_and_jacobian_shift), the normal equations with the
    shift's prior, the step, R <- exp([d]x) R. Returns (R, s, r, J, N, iterations,
    converged), r after the last small step to second order in it."""
    n = X.shape[0]
    s = mean
    r = np.empty(2 * n)
    J = np.empty((2 * n, 4))
    converged = False
    it = 0
    while True:
        e0 = R[0, 0] * axis[0] + R[0, 1] * axis[1] + R[0, 2] * axis[2]
        e1 = R[1, 0] * axis[0] + R[1, 1] * axis[1] + R[1, 2] * axis[2]
        e2 = R[2, 0] * axis[0] + R[2, 1] * axis[1] + R[2, 2] * axis[2]
        for i in range(n):
            x0, x1, x2 = X[i, 0] + s * axis[0], X[i, 1] + s * axis[1], X[i, 2] + s * axis[2]
            qx = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2
            qy = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2
            qz = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2
            iz = 1.0 / (qz + t_c[2])
            u, v = (qx + t_c[0]) * iz, (qy + t_c[1]) * iz
            r[2 * i] = u - xy[i, 0]
            r[2 * i + 1] = v - xy[i, 1]
            J[2 * i, 0] = -qy * u * iz
            J[2 * i, 1] = (qz + qx * u) * iz
            J[2 * i, 2] = -qy * iz
            J[2 * i, 3] = (e0 - u * e2) * iz
            J[2 * i + 1, 0] = -(qy * v + qz) * iz
            J[2 * i + 1, 1] = qx * v * iz
            J[2 * i + 1, 2] = qx * iz
            J[2 * i + 1, 3] = (e1 - v * e2) * iz
        JtW = J.T @ W
        N = JtW @ J
        N[3, 3] += w_s
        if it == max_iterations:
            break
        it += 1
        g = JtW @ r
        g[3] += (s - mean) * w_s
        step = -np.linalg.solve(N, g)
        R = _expmap(step[0], step[1], step[2]) @ R
        s += step[3]
        if step[0] ** 2 + step[1] ** 2 + step[2] ** 2 < tol_rad2 and abs(step[3]) < tol_shift:
            converged = True
            r = r + J @ step
            break
    return R, s, r, J, N, it, converged


# ------------------------- an undeclared rolling shutter's evidence (estimate.shear)
def _readout_frame(J, W, r, xy, rows, omega, lever, cy, height, ifx, ify, ka, info, rhs):
    """One frame of visvec.estimate.shear.ReadoutEvidence.add: its design (-shutter_shift
    of a 1 s readout beside shear.model_error_design) and what the free fit's weight
    P = W - W J C0 J^T W leaves of it, added to ``info`` and ``rhs`` in place. Returns
    (False, 0) when J^T W J is singular (nothing added), else (True, the frame's
    chi-square term)."""
    JW = J.T @ W
    try:
        C0 = np.linalg.inv(JW @ J)
    except Exception:  # noqa: BLE001 - numpy's LinAlgError, as add catches it
        return False, 0.0
    P = W - JW.T @ C0 @ JW
    n_par = info.shape[0]
    D = np.zeros((6, n_par))
    vx = xy[0, 0] - (xy[0, 0] + xy[1, 0] + xy[2, 0]) / 3.0
    vy = xy[0, 1] - (xy[0, 1] + xy[1, 1] + xy[2, 1]) / 3.0
    norm = math.hypot(vx, vy)
    c, s = vx / norm, vy / norm
    wx, wy, wz = omega[0], omega[1], omega[2]
    for i in range(3):
        x, y = xy[i, 0], xy[i, 1]
        t = (rows[i] - cy) / height
        ex, ey, ez = x + lever[0], y + lever[1], 1.0 + lever[2]
        ox, oy, oz = wy * ez - wz * ey, wz * ex - wx * ez, wx * ey - wy * ex
        D[2 * i, 0] = -(ox - x * oz) * t
        D[2 * i + 1, 0] = -(oy - y * oz) * t
        D[2 * i, 1 + 2 * i], D[2 * i, 2 + 2 * i] = c, -s
        D[2 * i + 1, 1 + 2 * i], D[2 * i + 1, 2 + 2 * i] = s, c
        D[2 * i, 7] = ifx
        D[2 * i + 1, 8], D[2 * i + 1, 9] = ify, y
    PD = P @ D
    a, b = -(PD.T @ r), D.T @ PD
    info += b
    rhs += a + b[:, 0] * ka
    return True, (r @ P) @ r + 2.0 * ka * a[0] + ka * ka * b[0, 0]


def _readout_solve(info, prior_info, rhs, chi2, dof):
    """visvec.estimate.shear.ReadoutEvidence._posterior: (covariance, estimate, the
    chi-square per degree of freedom they leave)."""
    A = info + prior_info
    if A[0, 0] <= 0:
        A[0, 0] = 1.0
    cov = np.linalg.inv(A)
    theta = cov @ rhs
    left = dof - np.sum(cov * info)
    return cov, theta, (chi2 - theta @ rhs) / max(left, 1.0)


sample_geometry = _jit(_sample_geometry, "sample_geometry")
_lag_sums = _jit(_lag_sums, "_lag_sums")
noise_inflation = _jit(_noise_inflation, "noise_inflation")
band_pixels = _jit(_band_pixels, "band_pixels")
cover = _jit(_cover, "cover")
_cover = _jit(_cover, "_cover")
_band_pixels = _jit(_band_pixels, "_band_pixels")
distorted = _jit(_distorted, "distorted")
band_lines = _jit(_band_lines, "band_lines")
_phi_of = _jit(_phi_of, "_phi_of")
_pixel_gn = _jit(_pixel_gn, "_pixel_gn")
_strided = _jit(_strided, "_strided")
pixel_solve = _jit(_pixel_solve, "pixel_solve")
_group_linear = _jit(_group_linear, "_group_linear")
_levels_suspect = _jit(_levels_suspect, "_levels_suspect")
_level_lines = _jit(_level_lines, "_level_lines")
positions = _jit(_positions, "positions")
widths = _jit(_widths, "widths")
_group_tls = _jit(_group_tls, "_group_tls")
group_median = _jit(_group_median, "group_median")
_group_median = _jit(_group_median, "_group_median")
robust_lines = _jit(_robust_lines, "robust_lines")
inward_lines = _jit(_inward_lines, "inward_lines")
_expmap = _jit(_expmap, "_expmap")
gn_shift = _jit(_gn_shift, "gn_shift")
closed_form_3 = _jit(_closed_form_3, "closed_form_3")
level_gain = _jit(_level_gain, "level_gain")
edge_stats = _jit(_edge_stats, "edge_stats")
edge_lag_sums = _jit(_edge_lag_sums, "edge_lag_sums")
readout_frame = _jit(_readout_frame, "readout_frame")
readout_solve = _jit(_readout_solve, "readout_solve")
