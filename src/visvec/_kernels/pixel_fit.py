"""The pixel fit's kernels (visvec.detect.photometric: its bands' pixels, Gauss-Newton
steps, solve and noise correlation) and its named results and settings.

The Gauss-Newton steps (_pixel_gn) and the solve (pixel_solve) are each one function,
compiled by Numba with the ``fast`` extra (visvec._kernels.jit) and run as Python
without it. The parts that visit every pixel are loops with a numpy twin each (the
name's function where the kernels are off), as are the bands' selection (band_lines,
band_pixels, cover: photometric._band). tests/detect/test_compiled.py checks each
against the other. The results are NamedTuples, which Numba builds and reads as
it does plain tuples, so that both paths return the same names."""

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
    """After the pixel fit's Gauss-Newton steps (_pixel_gn).

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
    """The pixel fit's answer on a frame's bands (pixel_solve).

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
    """_noise_inflation's sums: per lag (offset in the padded raster), the
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
    """How much wider the lines' errors are than white noise of the residuals' variance
    makes them, from the correlation of the residuals between neighbouring pixels.

    A video codec's errors are not white: JPEG's and MPEG's come in 8 x 8 blocks, and
    neighbouring pixels share them. A line's offset is estimated by sum_k w_k r_k with
    w the pixels' derivatives g (the fit's Jacobian column); its variance is
    sum_jk w_j w_k C(j - k), which for white noise is s^2 sum_k w_k^2. With C(lag) =
    s^2 rho(lag) the correlation of the residuals at that lag (estimated from the band's
    pixel pairs), the ratio of the two is

        1 + 2 sum_(lags in a half-plane) rho(lag) sum_k w_k w_(k + lag) / sum_k w_k^2,

    the 2-D form of a HAC (heteroskedasticity- and autocorrelation-consistent)
    covariance's long-run variance (Newey & West, Econometrica 55 (1987), Eq. 2, the
    lags truncated at ``L`` (photometric.NOISE_LAG_PX) without their taper). It multiplies the fit's
    covariance. Only the part of the sum beyond twice its own sampling scatter counts,
    and never below 1: sensor noise gives 1 (1.00-1.01 on average), Motion-JPEG at
    quality 75 about 2.5.

    ``uv`` (M, 2) the pixels' places in the frame (column, row), ``r`` (M,) their
    residuals, ``w`` (M,) the weights g; ``lags`` (L', 2) a half-plane's lags (px),
    those with fewer than ``min_pairs`` pixel pairs left out. Here as loops: the raster
    of the band's pixels, the sums over their pairs at each lag (_lag_sums), the
    inflation from them; _noise_inflation_numpy on numpy arrays."""
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


def _noise_inflation_numpy(uv, r, w, lags, L, min_pairs):
    """_noise_inflation with numpy: the raster of the band's pixels, the lags of a
    half-plane all in one gather."""
    var = float(r @ r) / len(r)
    den = float(w @ w)
    if not (var > 0 and den > 0):
        return 1.0
    n = len(uv)
    # each pixel's index in the band on a raster of the bands' bounding box padded by
    # L, n (a zero appended to r and w) where no band pixel is; a pixel in two bands:
    # its last place
    uv = uv.astype(np.int64) - uv.min(axis=0)
    width = int(uv[:, 0].max()) + 2 * L + 1
    flat = (uv[:, 1] + L) * width + (uv[:, 0] + L)
    index = np.full(int(flat.max()) + L * width + L + 1, n, np.int32)
    index[flat] = np.arange(n, dtype=np.int32)
    # per lag (n, lags) the neighbours' indices; the pixel pairs, and the sums of r r'
    # and w w' over them
    j = np.take(index, flat[:, None] + (lags[:, 1] * width + lags[:, 0]))
    pairs = np.count_nonzero(j < n, axis=0).astype(float)
    rr = r @ np.take(np.append(r, 0.0), j)
    ww = w @ np.take(np.append(w, 0.0), j)
    use = pairs >= min_pairs
    rho = np.where(use, rr / np.maximum(pairs, 1.0) / var, 0.0)
    share = ww / den  # the weights' overlap at each lag
    excess = 2.0 * float(rho @ share)
    # rho's estimates scatter by 1 / sqrt(pairs) each: only an excess beyond twice its
    # own scatter is taken (white noise would otherwise read as 1.04-1.08 on average)
    scatter = 2.0 * math.sqrt(float(np.sum(np.where(use, share**2 / np.maximum(pairs, 1.0), 0.0))))
    return 1.0 + max(excess - 2.0 * scatter, 0.0)


# ------------------------------------------------------------------- the pixel fit
def _band_pixels(pts, given, grid, cx, cy, aspect, lens, image, n, o, reach, clear):
    """photometric._band's pixels: of the pixels its drawn bands cover (``pts``, (P, 2)
    column and row, in raster order) those each edge's exact rule takes (within
    ``reach`` (3,) of its line n . x = o, more than ``clear`` (3,) inside the other
    two), edge after edge: a BandPixels of their ideal coordinates (M, 2) (``given``
    (P, 2), or when that is empty ideal_coordinates': the pinhole's, plus with ``lens``
    the correction in ``grid``), grey levels (M,), places in the frame (M, 2) and each
    edge's count (3,)."""
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
    """The pixels (column, row) (P, 2) in raster order that the three convex
    quadrilaterals ``q`` (12, 2) (px, four corners each) cover with a pixel's margin,
    within columns lo0..hi0 and rows lo1..hi1: per row the columns from each
    quadrilateral's least x, less one, to its greatest plus one, over the strip of rows
    within one of the row; their union (_cover_numpy says why so)."""
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
    """photometric._band without a rolling shutter: the three bands' quadrilaterals
    from the lines n_i . (x - c_i) = 0 (band_quads), their corners through the lens
    (camera.distort's polynomial), the box they span in the frame, the pixels they cover
    (cover) and those each edge's rule takes (band_pixels). Returns whether there were
    any, then band_pixels' BandPixels."""
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
    pts = cover(q, lo0, lo1, hi0, hi1)
    if len(pts) == 0:
        return False, BandPixels(*empty)
    return True, band_pixels(pts, np.empty((0, 2)), grid, gcx, gcy, aspect, lens, image, n, o,
                              reach, clear)  # fmt: skip


def pinhole(uv, cx, cy, aspect):
    """(M, 2) the ideal coordinates of pixels (column, row) (M, 2) through a pinhole."""
    out = np.empty((len(uv), 2))
    out[:, 0] = uv[:, 0] - cx
    out[:, 1] = (uv[:, 1] - cy) * aspect
    return out


def ideal_coordinates(pts, grid, cx, cy, aspect, lens):
    """(M, 2) the ideal coordinates of pixels (column, row) ``pts`` (M, 2): the
    pinhole's, plus with ``lens`` the distortion's correction ``grid`` (H, W, 2) there
    (photometric._IdealGrid)."""
    x = pinhole(pts, cx, cy, aspect)
    if lens:
        x += np.take(grid.reshape(-1, 2), pts[:, 1] * grid.shape[1] + pts[:, 0], axis=0)
    return x


def band_quads(n, o, reach, clear):
    """(12, 2) the corners (ideal px) of the three bands' quadrilaterals, four per
    edge: edge i's band is within reach[i] + 1.5 px of its line n_i . x = o_i, between
    its neighbours' lines moved clear[j] px inward (each corner where two lines meet,
    by Cramer's rule)."""
    nn, ol = n.tolist(), o.tolist()
    quads = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        for sgn, other in ((-1.0, j), (-1.0, k), (1.0, k), (1.0, j)):
            oi = ol[i] + sgn * (reach[i] + 1.5)
            o2 = ol[other] + clear[other]
            (a, b), (c, d) = nn[i], nn[other]
            det = a * d - b * c
            quads.append(((oi * d - o2 * b) / det, (a * o2 - c * oi) / det))
    return np.array(quads)


def band_box(q_px, last_col, last_row):
    """The frame's columns and rows (lo0, lo1, hi0, hi1) the quadrilaterals' corners
    ``q_px`` (12, 2) (px) span, a pixel wider; None where a corner is not finite or the
    box is empty."""
    if not np.all(np.isfinite(q_px)):
        return None
    lo = np.maximum(np.floor(q_px.min(axis=0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(q_px.max(axis=0)).astype(int) + 1, [last_col, last_row])
    if np.any(hi <= lo):
        return None
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _cover_numpy(q, lo0, lo1, hi0, hi1):
    """The pixels (column, row) (P, 2) in raster order that the three convex
    quadrilaterals ``q`` (12, 2) (px, four corners each) cover with a pixel's margin,
    within columns lo0..hi0 and rows lo1..hi1: per row the columns from each
    quadrilateral's least x, less one, to its greatest plus one, over the strip of rows
    within one of the row; their union. (A superset of the pixels whose centres the
    quadrilaterals hold, for the exact check of band_pixels; cheaper than drawing
    them.) With numpy: every row's strip at once."""
    v = np.arange(lo1, hi1 + 1, dtype=float)
    a, b = v - 1.0, v + 1.0
    # the twelve sides (a quadrilateral's k-th from its corner k to corner k + 1), each
    # clipped to each row's strip: the part between t0 and t1 of it
    x0, y0 = q[:, :1], q[:, 1:]
    nxt = q.reshape(3, 4, 2)[:, [1, 2, 3, 0]].reshape(12, 2)
    x1, y1 = nxt[:, :1], nxt[:, 1:]
    flat = (y1 == y0)[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (a - y0) / (y1 - y0), (b - y0) / (y1 - y0)
    t0, t1 = np.maximum(np.minimum(ta, tb), 0.0), np.minimum(np.maximum(ta, tb), 1.0)
    # a side along a row: all of it or none
    inside = (a <= y0[flat]) & (y0[flat] <= b)
    t0[flat], t1[flat] = np.where(inside, 0.0, 1.0), np.where(inside, 1.0, 0.0)
    meets = t0 <= t1
    xa, xb = x0 + t0 * (x1 - x0), x0 + t1 * (x1 - x0)
    xmin = np.where(meets, np.minimum(xa, xb), np.inf).reshape(3, 4, -1).min(axis=1)
    xmax = np.where(meets, np.maximum(xa, xb), -np.inf).reshape(3, 4, -1).max(axis=1)
    seen = xmin <= xmax
    c0 = np.maximum(np.ceil(np.where(seen, xmin, 0.0) - 1.0).astype(np.int64), lo0).T.copy()
    c1 = np.minimum(np.floor(np.where(seen, xmax, 0.0) + 1.0).astype(np.int64), hi0).T.copy()
    # per row (R, 3) the three ranges by their first column (an empty one's past hi0)
    empty = ~seen.T | (c1 < c0)
    c0[empty], c1[empty] = hi0 + 1, hi0
    order = (np.argsort(c0, axis=1, kind="stable") + np.arange(0, c0.size, 3)[:, None]).ravel()
    c0, c1 = c0.ravel()[order].reshape(-1, 3), c1.ravel()[order].reshape(-1, 3)
    # their union, each column once: a range starts past the ends of those before it
    start = c0.copy()
    start[:, 1:] = np.maximum(c0[:, 1:], np.maximum.accumulate(c1, axis=1)[:, :-1] + 1)
    count = np.maximum(c1 - start + 1, 0).ravel()
    first = np.cumsum(count) - count
    u = np.repeat(start.ravel() - first, count) + np.arange(int(count.sum()))
    rows = np.repeat(np.arange(lo1, hi1 + 1), count.reshape(-1, 3).sum(axis=1))
    return np.column_stack([u, rows])


def _band_pixels_numpy(pts, given, grid, cx, cy, aspect, lens, image, n, o, reach, clear):
    """_band_pixels with numpy."""
    x = given if len(given) else ideal_coordinates(pts, grid, cx, cy, aspect, lens)
    grey = np.take(image.reshape(-1), pts[:, 1] * image.shape[1] + pts[:, 0])
    d = x @ n.T - o  # (P, 3)
    keeps = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        # a pixel is the nearest edge's: within its reach and clear of the other two
        keeps.append((np.abs(d[:, i]) < reach[i]) & (d[:, j] > clear[j]) & (d[:, k] > clear[k]))
    counts = np.array([np.count_nonzero(k) for k in keeps], np.int64)
    return BandPixels(np.concatenate([x[k] for k in keeps]),
                      np.concatenate([grey[k] for k in keeps]).astype(float),
                      np.concatenate([pts[k] for k in keeps]), counts)  # fmt: skip


def _band_lines_numpy(image, n, c, reach, clear, fx, fy, cx, cy, dist, last_col, last_row, grid,
                      gcx, gcy, aspect, lens):  # fmt: skip
    """_band_lines with numpy: the quadrilaterals (band_quads) through the lens, their
    box (band_box), the pixels they cover (_cover_numpy) and those each edge's rule
    takes (_band_pixels_numpy)."""
    empty = BandPixels(np.empty((0, 2)), np.empty(0), np.empty((0, 2), np.int64),
                       np.zeros(3, np.int64))  # fmt: skip
    o = np.einsum("ij,ij->i", n, c)
    q = band_quads(n, o, reach, clear) / fx
    xd, yd = _distorted(q[:, 0], q[:, 1], *dist)
    q_px = np.column_stack([fx * xd + cx, fy * yd + cy])
    box = band_box(q_px, last_col, last_row)
    if box is None:
        return False, empty
    pts = _cover_numpy(q_px, *box)
    if not len(pts):
        return False, empty
    return True, _band_pixels_numpy(pts, np.empty((0, 2)), grid, gcx, gcy, aspect, lens, image,
                                    n, o, reach, clear)  # fmt: skip


def phi_of(u, table, rng, inv_step):
    """Phi(u) and phi(u), the blurred step and its slope, by cubic Hermite interpolation
    in ``table`` (photometric._PHI: values and slopes at nodes 1 / ``inv_step`` apart
    from -``rng``). Written once for both paths: ``u`` an array (the numpy twins, a
    band at once) or one float (the compiled loops, pixel by pixel, as _phi_of)."""
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


# ------------------------------------------- the Gauss-Newton steps' per-pixel parts
# Each edge's Jacobian is an (N_EDGE, m_e) C-ordered block of one buffer, the edges' one
# after another (_edge_jacobian), so that BLAS takes each in place: its rows are the
# line's turn and offset, the width, then the level coefficients (the board's 1, X, Y,
# X^2 + Y^2, then T = Phi(u) times them: the contrast's). The parts that visit every
# pixel are written twice, as loops (compiled) and with numpy on the edge's arrays (the
# path without Numba, where the loops run as Python would be several times slower):
# the same equations (across_edge, phi_of, pixel_residual), the same order within a
# value (tests/detect/test_compiled.py checks them against each other).
def _edge_jacobian(buf, start, count):
    """The Jacobian block (N_EDGE, count) of the edge whose pixels start at ``start``."""
    return buf[N_EDGE * start : N_EDGE * (start + count)].reshape((N_EDGE, count))


def _board_columns(x, counts, centroid, scale, buf):
    """The board's level rows of each edge's Jacobian: 1, X, Y, X^2 + Y^2 (X, Y the
    pixel's ideal coordinates about the centroid, over ``scale``)."""
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        for k in range(counts[e]):
            X = (x[start + k, 0] - centroid[0]) / scale
            Y = (x[start + k, 1] - centroid[1]) / scale
            Je[3, k] = 1.0
            Je[4, k] = X
            Je[5, k] = Y
            Je[6, k] = X * X + Y * Y
        start += counts[e]


def _board_columns_numpy(x, counts, centroid, scale, buf):
    """_board_columns with numpy."""
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        xe = x[start : start + counts[e]]
        Je[3] = 1.0
        Je[4] = (xe[:, 0] - centroid[0]) / scale
        Je[5] = (xe[:, 1] - centroid[1]) / scale
        Je[6] = Je[4] * Je[4] + Je[5] * Je[5]
        start += counts[e]


def _step_columns(x, counts, n, c, w, buf, u, perp, slope, table, rng, inv_step):
    """Each pixel against its edge's line (across_edge: u (M,) in blur widths, perp
    (M,) along it, px) and the blurred step there (phi_of: T, and its slope (M,)); the
    contrast's rows of the Jacobians, T times the board's."""
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        nx, ny, cx, cy, we = n[e, 0], n[e, 1], c[e, 0], c[e, 1], w[e]
        for k in range(counts[e]):
            p = start + k
            u[p], perp[p] = _across_edge(x[p, 0], x[p, 1], cx, cy, nx, ny, we)
            T, slope[p] = _phi_of(u[p], table, rng, inv_step)
            for q in range(N_LEVELS):
                Je[3 + N_LEVELS + q, k] = T * Je[3 + q, k]
        start += counts[e]


def _step_columns_numpy(x, counts, n, c, w, buf, u, perp, slope, table, rng, inv_step):
    """_step_columns with numpy."""
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        end = start + counts[e]
        xe = x[start:end]
        u[start:end], perp[start:end] = across_edge(xe[:, 0], xe[:, 1], c[e, 0], c[e, 1],
                                                    n[e, 0], n[e, 1], w[e])  # fmt: skip
        T, slope[start:end] = phi_of(u[start:end], table, rng, inv_step)
        Je[3 + N_LEVELS :] = Je[3 : 3 + N_LEVELS] * T
        start = end


def _residual_columns(y, counts, buf, u, perp, slope, level, w, r, g):
    """Each pixel's residual r (M,) and slope across its line g (M,) under the levels
    (pixel_residual), and the line's rows of the Jacobians from them (its turn g perp,
    its offset -g, its width -g u). Returns the residual sum of squares."""
    rss = 0.0
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        we = w[e]
        for k in range(counts[e]):
            p = start + k
            r[p], g[p] = _pixel_residual(y[p], Je[4, k], Je[5, k], Je[6, k],
                                         Je[3 + N_LEVELS, k], slope[p], level, we)  # fmt: skip
            rss += r[p] * r[p]
            Je[0, k] = g[p] * perp[p]
            Je[1, k] = -g[p]
            Je[2, k] = -g[p] * u[p]
        start += counts[e]
    return rss


def _residual_columns_numpy(y, counts, buf, u, perp, slope, level, w, r, g):
    """_residual_columns with numpy (the sum of squares edge by edge)."""
    rss = 0.0
    start = 0
    for e in range(3):
        Je = _edge_jacobian(buf, start, counts[e])
        end = start + counts[e]
        r[start:end], g[start:end] = pixel_residual(y[start:end], Je[4], Je[5], Je[6],
                                                    Je[3 + N_LEVELS], slope[start:end],
                                                    level, w[e])  # fmt: skip
        rss += float(r[start:end] @ r[start:end])
        Je[0] = g[start:end] * perp[start:end]
        Je[1] = -g[start:end]
        Je[2] = -g[start:end] * u[start:end]
        start = end
    return rss


# --------------------------------------------- the Gauss-Newton steps and the solve
def _add_edge(H, b, He, be, e):
    """Edge e's normal equations (He = Je Je^T, be = Je r) into the fit's (H, b): its
    rows are the fit's parameters 2e and 2e + 1 (its line's turn and offset), 6 + e
    (its width) and 9 on (the levels, shared)."""
    a, wd = 2 * e, 6 + e
    b[a : a + 2] += be[0:2]
    b[wd] += be[2]
    b[9:] += be[3:]
    H[a : a + 2, a : a + 2] += He[0:2, 0:2]
    H[a : a + 2, wd] += He[0:2, 2]
    H[a : a + 2, 9:] += He[0:2, 3:]
    H[wd, a : a + 2] += He[2, 0:2]
    H[wd, wd] += He[2, 2]
    H[wd, 9:] += He[2, 3:]
    H[9:, a : a + 2] += He[3:, 0:2]
    H[9:, wd] += He[3:, 2]
    H[9:, 9:] += He[3:, 3:]


def _pixel_gn(x, y, counts, n, c, w, centroid, scale, steps, table, rng, inv_step):
    """``steps`` Gauss-Newton steps of the model's N_PARAMS parameters from the lines
    (n, c) and widths w on the bands' pixels (x (M, 2) ideal px, y (M,) grey levels,
    counts (3,) per edge), the levels first fitted to the starting lines by linear least
    squares (X, Y about ``centroid``, over ``scale``; the step from ``table``, phi_of).
    A GaussNewtonSteps: the lines, widths and levels after the steps; the last step's
    normal equations H, b; the residual sum of squares after it, as Gauss-Newton
    predicts it (the last step is a small one: no pass of its own is needed to measure
    it); the last pass's residuals and offset derivatives dI / d(distance) (M,) each;
    and False where a system was singular.

    One function for both paths: compiled, or run as Python with the per-pixel parts'
    numpy twins (visvec._kernels.jit.kernel)."""
    m = len(y)
    n = n.copy()
    c = c.copy()
    w = w.copy()
    H = np.zeros((N_PARAMS, N_PARAMS))
    b = np.zeros(N_PARAMS)
    level = np.zeros(2 * N_LEVELS)
    r = np.empty(m)
    g = np.empty(m)
    u = np.empty(m)
    perp = np.empty(m)
    slope = np.empty(m)
    buf = np.empty(N_EDGE * m)
    _board_columns(x, counts, centroid, scale, buf)
    rss = 0.0
    for it in range(steps):
        _step_columns(x, counts, n, c, w, buf, u, perp, slope, table, rng, inv_step)
        if it == 0:
            # the levels from the starting lines, by linear least squares
            AtA = np.zeros((2 * N_LEVELS, 2 * N_LEVELS))
            Aty = np.zeros(2 * N_LEVELS)
            start = 0
            for e in range(3):
                A = _edge_jacobian(buf, start, counts[e])[3:]
                AtA += A @ A.T
                Aty += A @ y[start : start + counts[e]]
                start += counts[e]
            try:
                level = np.linalg.solve(AtA, Aty)
            except Exception:  # noqa: BLE001 - Numba catches no narrower class
                return GaussNewtonSteps(n, c, w, level, H, b, rss, r, g, False)
        rss = _residual_columns(y, counts, buf, u, perp, slope, level, w, r, g)
        H[:, :] = 0.0
        b[:] = 0.0
        start = 0
        for e in range(3):
            Je = _edge_jacobian(buf, start, counts[e])
            _add_edge(H, b, Je @ Je.T, Je @ r[start : start + counts[e]], e)
            start += counts[e]
        try:
            step = np.linalg.solve(H, b)
        except Exception:  # noqa: BLE001
            return GaussNewtonSteps(n, c, w, level, H, b, rss, r, g, False)
        for e in range(3):
            th, oo = step[2 * e], step[2 * e + 1]
            cs, sn = math.cos(th), math.sin(th)
            n0 = cs * n[e, 0] - sn * n[e, 1]
            n1 = sn * n[e, 0] + cs * n[e, 1]
            n[e, 0], n[e, 1] = n0, n1
            c[e, 0] += oo * n0
            c[e, 1] += oo * n1
            w[e] = max(w[e] + step[6 + e], 0.2)
        level += step[9:]
        rss -= step @ b
    return GaussNewtonSteps(n, c, w, level, H, b, rss, r, g, True)


def _strided(x, y, counts, stride):
    """Every ``stride``-th pixel of each band (x, y and the bands' counts)."""
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


def _strided_numpy(x, y, counts, stride):
    """_strided with numpy."""
    bounds = np.concatenate([[0], np.cumsum(counts)])
    pick = np.concatenate([np.arange(bounds[e], bounds[e + 1], stride) for e in range(3)])
    return x[pick], y[pick], (counts + stride - 1) // stride


def _vertices_and_gain(n, c):
    """The vertices V (3, 2) of the lines n_i . (x - c_i) = 0 (vertex i on lines i + 1
    and i + 2, by Cramer's rule, as edge_fit.vertices) and how the lines move them, G
    (6, 6) = d(vertices) / d(lines): line i turned by a small angle about c_i, or moved
    by an offset along n_i, moves vertex v on it (v on lines j, k) by A_v^-1 times the
    change of those lines' equations n . x = n . c at v: the offset adds 1 to its row's
    right side; the turn d(theta) (n -> n + d(theta) n_perp) takes n_perp . (v - c_i)
    d(theta) from it. Returns False, and NaN, where two lines are parallel."""
    V = np.empty((3, 2))
    invs = np.empty((3, 2, 2))
    G = np.zeros((6, 6))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        a, b, cc, d = n[j, 0], n[j, 1], n[k, 0], n[k, 1]
        det = a * d - b * cc
        if det == 0.0:
            return False, np.full((3, 2), np.nan), G
        invs[i, 0, 0], invs[i, 0, 1] = d / det, -b / det
        invs[i, 1, 0], invs[i, 1, 1] = -cc / det, a / det
        oj = n[j, 0] * c[j, 0] + n[j, 1] * c[j, 1]
        ok = n[k, 0] * c[k, 0] + n[k, 1] * c[k, 1]
        V[i, 0] = invs[i, 0, 0] * oj + invs[i, 0, 1] * ok
        V[i, 1] = invs[i, 1, 0] * oj + invs[i, 1, 1] * ok
    for v in range(3):
        for row in range(2):
            ln = (v + 1 + row) % 3
            nx, ny = n[ln, 0], n[ln, 1]
            sv = (V[v, 0] - c[ln, 0]) * -ny + (V[v, 1] - c[ln, 1]) * nx
            for q in range(2):
                G[2 * v + q, 2 * ln] -= invs[v, q, row] * sv
                G[2 * v + q, 2 * ln + 1] += invs[v, q, row]
    return True, V, G


def _pixel_solve(x, y, uv, counts, n, c, w, V, centroid, scale, warm, st):
    """The pixel fit from the starting lines (n, c), widths w and vertices V on the
    bands' pixels (x, y, their places in the frame uv, counts: a BandPixels'), ``st``
    its constants (PixelFitSettings): st.steps Gauss-Newton steps (those before the last
    on every st.stride-th pixel), or with ``warm`` (w the run's blur) one on every
    pixel, another while the last moved a width by more than st.settled (st.warm_steps
    at most); the bands' residuals checked against each other (st.rms_ratio), the
    covariance inflated for the noise's correlation (noise_inflation) and taken to the
    vertices. A PixelSolve: whether it is to be taken, the vertices (3, 2) (the starting
    ones when it is not), their covariance (6, 6) (NaN when not), the widths, the
    residuals' variance, the inflation and the steps on every pixel.

    One function for both paths (visvec.detect.photometric.refine calls it): compiled,
    or run as Python with the per-pixel parts' numpy twins."""
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
    s2 = max(rss, 0.0) / max(len(y) - N_PARAMS, 1)
    # the residuals of a band the model fits are the pixels' noise, alike in the three
    # bands (the same board and triangle): one band's twice the others' has something
    # else in it (a head just off an edge, which the lines' robust fit may carry as a
    # wider scatter without an outlier), and the fit, not robust, is not taken
    rms = np.empty(3)
    start = 0
    for e in range(3):
        re = r[start : start + counts[e]]
        rms[e] = math.sqrt(np.dot(re, re) / counts[e])
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
    found, V2, G = _vertices_and_gain(n, c)
    if not found:
        return PixelSolve(False, V, fail, w, s2, inflation, steps)
    return PixelSolve(True, V2, G @ cov_p @ G.T, w, s2, inflation, steps)


_lag_sums = kernel(globals(), "_lag_sums", _lag_sums)
noise_inflation = kernel(globals(), "noise_inflation", _noise_inflation,
                         numpy=_noise_inflation_numpy)  # fmt: skip
band_pixels = kernel(globals(), "band_pixels", _band_pixels, numpy=_band_pixels_numpy)
cover = kernel(globals(), "cover", _cover, numpy=_cover_numpy)
distorted = kernel(globals(), "distorted", _distorted)
band_lines = kernel(globals(), "band_lines", _band_lines, numpy=_band_lines_numpy)
_phi_of = kernel(globals(), "_phi_of", phi_of)
_across_edge = kernel(globals(), "_across_edge", across_edge)
_pixel_residual = kernel(globals(), "_pixel_residual", pixel_residual)
_edge_jacobian = kernel(globals(), "_edge_jacobian", _edge_jacobian)
_board_columns = kernel(globals(), "_board_columns", _board_columns, numpy=_board_columns_numpy)
_step_columns = kernel(globals(), "_step_columns", _step_columns, numpy=_step_columns_numpy)
_residual_columns = kernel(globals(), "_residual_columns", _residual_columns,
                           numpy=_residual_columns_numpy)  # fmt: skip
_add_edge = kernel(globals(), "_add_edge", _add_edge)
_pixel_gn = kernel(globals(), "_pixel_gn", _pixel_gn)
_strided = kernel(globals(), "_strided", _strided, numpy=_strided_numpy)
_vertices_and_gain = kernel(globals(), "_vertices_and_gain", _vertices_and_gain)
pixel_solve = kernel(globals(), "pixel_solve", _pixel_solve)
