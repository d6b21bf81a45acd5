"""The pixel fit's kernels (visvec.detect.photometric: its bands' pixels, Gauss-Newton
steps and noise correlation) and its named results and settings.

Each kernel is one of photometric's functions written as loops over the pixels, the
same arithmetic in the same order where the order matters (tests/detect/test_compiled.py
checks them against each other); compiled by Numba with the ``fast`` extra
(visvec._kernels.jit). The results are NamedTuples, which Numba builds and reads as it
does plain tuples, so that the numpy and the compiled fit return the same names."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from visvec._kernels.jit import kernel
from visvec.camera import _distorted

# the level model: the board's level and the triangle's contrast each N_LEVELS terms in
# the pixel's place about the centroid, scaled: (1, X, Y, X^2 + Y^2), a lighting
# gradient and a lens's radial falloff (vignetting: I0 (1 - k |x - x0|^2) about any
# centre x0 is in their span)
N_LEVELS = 4
# the fit's parameters: 3 lines x (rotation, offset), 3 widths, 2 N_LEVELS levels
N_PARAMS = 9 + 2 * N_LEVELS
# an edge's Jacobian columns: its line's rotation and offset, its width, the levels
N_EDGE = 3 + 2 * N_LEVELS


class BandPixels(NamedTuple):
    """The pixels the fit takes (photometric._band and its kernels): each edge's band's,
    edge after edge, in raster order.

    Attributes
    ----------
    x : ndarray, shape (M, 2)
        Their ideal (undistorted) coordinates (px).
    y : ndarray, shape (M,)
        Their grey levels.
    uv : ndarray of int, shape (M, 2)
        Their places in the frame (column, row).
    counts : ndarray of int, shape (3,)
        Each edge's number of pixels.
    """

    x: np.ndarray
    y: np.ndarray
    uv: np.ndarray
    counts: np.ndarray


class GaussNewtonSteps(NamedTuple):
    """After the pixel fit's Gauss-Newton steps (photometric._gauss_newton).

    Attributes
    ----------
    n : ndarray, shape (3, 2)
        The lines' unit normals (into the triangle).
    c : ndarray, shape (3, 2)
        The lines' centres (ideal px).
    w : ndarray, shape (3,)
        The edges' blur widths (px, the model's w).
    level : ndarray, shape (2 N_LEVELS,)
        The level model's coefficients: the board's (1, X, Y, X^2 + Y^2), then the
        contrast's (grey levels; X, Y about the centroid, scaled).
    H : ndarray, shape (N_PARAMS, N_PARAMS)
        The last step's normal matrix J^T J.
    b : ndarray, shape (N_PARAMS,)
        The last step's J^T r.
    rss : float
        The residual sum of squares after the last step, as Gauss-Newton predicts it
        (grey levels^2).
    r : ndarray, shape (M,)
        The last pass's residuals (grey levels).
    g : ndarray, shape (M,)
        The last pass's dI / d(distance) (grey levels per px).
    ok : bool
        False where a system was singular.
    """

    n: np.ndarray
    c: np.ndarray
    w: np.ndarray
    level: np.ndarray
    H: np.ndarray
    b: np.ndarray
    rss: float
    r: np.ndarray
    g: np.ndarray
    ok: bool


class PixelSolve(NamedTuple):
    """The pixel fit's answer on a frame's bands (photometric._solve).

    Attributes
    ----------
    ok : bool
        Whether the fit is to be taken.
    V : ndarray, shape (3, 2)
        The vertices (ideal px; the starting ones when it is not taken).
    cov : ndarray, shape (6, 6)
        Their covariance (px^2; NaN, or None from numpy, when not taken).
    w : ndarray, shape (3,)
        The blur widths (px).
    s2 : float
        The residuals' variance (grey levels^2).
    inflation : float
        The covariance's factor for the noise's correlation.
    steps : int
        The Gauss-Newton steps taken on every pixel.
    """

    ok: bool
    V: np.ndarray
    cov: np.ndarray | None
    w: np.ndarray
    s2: float
    inflation: float
    steps: int


class PixelFitSettings(NamedTuple):
    """The pixel fit's constants as its compiled solve takes them (photometric's
    module constants; see there what each does).

    Attributes
    ----------
    steps : int
        GN_STEPS, a run's first fit's Gauss-Newton steps.
    stride : int
        FIRST_STRIDE, the pixels the steps before the last take.
    lags : ndarray, shape (L, 2)
        The half-plane's lags (px) of the noise correlation.
    lag_px : int
        NOISE_LAG_PX.
    min_pairs : int
        NOISE_MIN_PAIRS.
    rms_ratio : float
        EDGE_RMS_RATIO.
    settled : float
        WIDTH_SETTLED.
    warm_steps : int
        WARM_STEPS.
    table : ndarray, shape (N + 1, 4)
        The blurred step's Hermite table (photometric._PHI).
    rng : float
        PHI_RANGE.
    inv_step : float
        1 / PHI_STEP.
    """

    steps: int
    stride: int
    lags: np.ndarray
    lag_px: int
    min_pairs: int
    rms_ratio: float
    settled: float
    warm_steps: int
    table: np.ndarray
    rng: float
    inv_step: float


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
    return BandPixels(xs, ys, uv, counts)


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
        return False, BandPixels(*empty)
    lo0 = max(math.floor(q[:, 0].min()) - 1, 0)
    lo1 = max(math.floor(q[:, 1].min()) - 1, 0)
    hi0 = min(math.ceil(q[:, 0].max()) + 1, last_col)
    hi1 = min(math.ceil(q[:, 1].max()) + 1, last_row)
    if hi0 <= lo0 or hi1 <= lo1:
        return False, BandPixels(*empty)
    pts = _cover(q, lo0, lo1, hi0, hi1)
    if len(pts) == 0:
        return False, BandPixels(*empty)
    return True, _band_pixels(pts, np.empty((0, 2)), grid, gcx, gcy, aspect, lens, image, n, o,
                              reach, clear)  # fmt: skip


def phi_of(u, table, rng, inv_step):
    """Phi(u) and phi(u), the blurred step and its slope, by cubic Hermite interpolation
    in ``table`` (photometric._PHI: values and slopes at nodes 1 / ``inv_step`` apart
    from -``rng``). Written once for both paths: ``u`` an array (photometric's numpy
    fit) or one float (the compiled fit, pixel by pixel, as _phi_of)."""
    t = (np.minimum(np.maximum(u, -rng), rng) + rng) * inv_step
    # (unsigned: Numba indexes the table without checking for a negative index)
    i = np.minimum(np.uint64(t), np.uint64(table.shape[0] - 2))
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


def across_edge(x0, x1, cx, cy, nx, ny, we):
    """A pixel at (x0, x1) (ideal px) against its edge's line through (cx, cy) with
    unit normal (nx, ny) and blur width ``we``: u = n . (x - c) / w, its distance across
    the line in blur widths, and perp = n_perp . (x - c), its place along it (px).
    Written once for both paths: arrays (photometric's numpy fit) or floats (the
    compiled one, pixel by pixel)."""
    rx, ry = x0 - cx, x1 - cy
    return (rx * nx + ry * ny) / we, rx * -ny + ry * nx


def pixel_residual(y, X, Y, R2, T, slope, level, we):
    """The pixel fit's model at a pixel and what it leaves: the board's level
    level[0:4] . (1, X, Y, R2) plus the step T = Phi(u) times the contrast C =
    level[4:8] . (1, X, Y, R2) (X, Y the pixel about the centroid, scaled; R2 = X^2 + Y^2:
    a lens's radial falloff), against the grey level y. Returns the residual r = y -
    model (grey levels) and g = C phi(u) / w, dI / d(distance across the line) (grey
    levels per px), from which the line's Jacobian columns follow: (g perp, -g, -g u)
    for its turn about c, its offset and its blur width. Written once for both paths
    (arrays or floats, as across_edge)."""
    C = level[4] + level[5] * X + level[6] * Y + level[7] * R2
    r = y - (level[0] + level[1] * X + level[2] * Y + level[3] * R2 + T * C)
    return r, C * slope / we


def _pixel_gn(x, y, counts, n, c, w, centroid, scale, steps, table, rng, inv_step):
    """photometric._gauss_newton compiled: the same model, parameters and steps; each
    edge's Jacobian (N_EDGE, m_e) filled pixel by pixel, its normal equations by BLAS.
    The three edges' Jacobians lie one after another in one buffer, each C-contiguous,
    so that BLAS takes them in place (a copy of each edge's columns of one (N_EDGE, m)
    array cost a tenth of a step)."""
    m = len(y)
    n = n.copy()
    c = c.copy()
    w = w.copy()
    H = np.zeros((N_PARAMS, N_PARAMS))
    b = np.zeros(N_PARAMS)
    level = np.zeros(2 * N_LEVELS)
    r_all = np.empty(m)
    g_all = np.empty(m)
    u_all = np.empty(m)
    perp_all = np.empty(m)
    slope_all = np.empty(m)
    bounds = np.zeros(4, np.int64)
    for e in range(3):
        bounds[e + 1] = bounds[e] + counts[e]
    buf = np.empty(N_EDGE * m)
    # the board's level columns (1, X, Y, X^2 + Y^2 about the centroid, scaled), then T
    # times them
    for e in range(3):
        Je = buf[N_EDGE * bounds[e] : N_EDGE * bounds[e + 1]].reshape((N_EDGE, counts[e]))
        for k in range(counts[e]):
            p = bounds[e] + k
            X = (x[p, 0] - centroid[0]) / scale
            Y = (x[p, 1] - centroid[1]) / scale
            Je[3, k] = 1.0
            Je[4, k] = X
            Je[5, k] = Y
            Je[6, k] = X * X + Y * Y
    # each edge's parameters: its line's rotation and offset, its width, the levels
    idx = np.empty(N_EDGE, np.int64)
    for q in range(2 * N_LEVELS):
        idx[3 + q] = 9 + q
    rss = 0.0
    for it in range(steps):
        for e in range(3):
            Je = buf[N_EDGE * bounds[e] : N_EDGE * bounds[e + 1]].reshape((N_EDGE, counts[e]))
            nx, ny, cx, cy, we = n[e, 0], n[e, 1], c[e, 0], c[e, 1], w[e]
            for k in range(counts[e]):
                p = bounds[e] + k
                u, perp = _across_edge(x[p, 0], x[p, 1], cx, cy, nx, ny, we)
                T, slope = _phi_of(u, table, rng, inv_step)
                u_all[p] = u
                perp_all[p] = perp
                slope_all[p] = slope
                for q in range(N_LEVELS):
                    Je[3 + N_LEVELS + q, k] = T * Je[3 + q, k]
        if it == 0:
            # the levels from the starting lines, by linear least squares
            AtA = np.zeros((2 * N_LEVELS, 2 * N_LEVELS))
            Aty = np.zeros(2 * N_LEVELS)
            for e in range(3):
                Je = buf[N_EDGE * bounds[e] : N_EDGE * bounds[e + 1]].reshape((N_EDGE, counts[e]))
                A = Je[3:]
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
            Je = buf[N_EDGE * bounds[e] : N_EDGE * bounds[e + 1]].reshape((N_EDGE, counts[e]))
            we = w[e]
            for k in range(counts[e]):
                p = bounds[e] + k
                r, g = _pixel_residual(y[p], Je[4, k], Je[5, k], Je[6, k], Je[3 + N_LEVELS, k],
                                       slope_all[p], level, we)  # fmt: skip
                rss += r * r
                r_all[p] = r
                g_all[p] = g
                Je[0, k] = g * perp_all[p]
                Je[1, k] = -g
                Je[2, k] = -g * u_all[p]
            He = Je @ Je.T
            be = Je @ r_all[bounds[e] : bounds[e + 1]]
            idx[0], idx[1], idx[2] = 2 * e, 2 * e + 1, 6 + e
            for q in range(N_EDGE):
                b[idx[q]] += be[q]
                for s in range(N_EDGE):
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
        for q in range(2 * N_LEVELS):
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
    s2 = max(rss, 0.0) / max(m - N_PARAMS, 1)
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


_lag_sums = kernel(globals(), "_lag_sums", _lag_sums)
noise_inflation = kernel(globals(), "noise_inflation", _noise_inflation)
band_pixels = kernel(globals(), "band_pixels", _band_pixels)
cover = kernel(globals(), "cover", _cover)
_cover = kernel(globals(), "_cover", _cover)
_band_pixels = kernel(globals(), "_band_pixels", _band_pixels)
distorted = kernel(globals(), "distorted", _distorted)
band_lines = kernel(globals(), "band_lines", _band_lines)
_phi_of = kernel(globals(), "_phi_of", phi_of)
_across_edge = kernel(globals(), "_across_edge", across_edge)
_pixel_residual = kernel(globals(), "_pixel_residual", pixel_residual)
_pixel_gn = kernel(globals(), "_pixel_gn", _pixel_gn)
_strided = kernel(globals(), "_strided", _strided)
pixel_solve = kernel(globals(), "pixel_solve", _pixel_solve)
