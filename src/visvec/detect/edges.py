"""Sub-pixel triangle vertices from straight-line fits to its three edges.

Corners of a blurred, noisy, low-contrast triangle are poorly located by corner
detectors (the acute corner rounds off and cornerSubPix is pulled inward). Edges are
long: each is sampled by many intensity profiles across it, each profile gives a
sub-pixel edge point, and a robust total-least-squares line through the points is fitted
in undistorted coordinates (the edges are straight there, whatever the lens). Vertices
are the intersections of the lines, with a covariance from the fit residuals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visvec._kernels import edge_fit as kernels
from visvec._kernels.edge_fit import (
    EdgeLines,
    StepPositions,
    vertices,
)
from visvec.camera import CameraModel
from visvec.noise import CORRELATION_LAGS
from visvec.shutter import RollingShutter, unroll

# Variance inflation of the edge-point residuals for correlated neighbouring profiles
# (profiles 1.5 px apart, bilinear sampling); calibrated by simulation (300 frames at
# each resolution, seed 7, not the benchmarks') so that vertex errors divided by their
# predicted sigma have unit RMS at the default blur and at a defocus of 2 px (vertex z
# RMS 0.95 / 0.96 and 1.00 / 1.01 at 320x240 / 640x480). The levels' error, common to
# an edge and so not in its residuals, is modelled apart (_level_gain): a longer window
# carries more level error, so no single inflation holds both at the default blur and
# on defocused edges.
EDGE_VARIANCE_INFLATION = 1.3
# spacing of the edge profiles along the edge in the fine pass (px)
PROFILE_SPACING_PX = 1.5
# and in the sparse first pass of a cold frame (px)
SPARSE_SPACING_PX = 2.0
# Gauss-Newton steps of the matched (erf) edge refinement
GN_STEPS = 1
_NO_WIDTH = np.zeros(0)
# cv2.remap takes at most 32767 rows; no real edge needs more than this many profiles
MAX_PROFILES_PER_EDGE = 4000
# profiles are re-centred once if a fine pass moves the vertices more than this (px):
# a prediction (tracking) or a first pass (cold) that was off
TRACK_RECENTRE_PX = 0.75
# The fine profiles reach this far (px) beyond the step window on both sides, and the
# board and triangle levels are measured over the outer 1 px + this: an error in a level
# is common to every profile of the edge (the level lines are fitted along it) and moves
# the whole line, so it is not averaged away by more profiles. Measured over 2 px, a
# frame's result does not depend on the window length (which follows the measured blur,
# so the start of the fit): results from different starts spread by 0.2 sigma, where
# over 1 px one frame's tilts moved by 1.5 to 4 sigma.
LEVEL_EXTENT_PX = 1.0
# The fine profiles reach 3 blur widths + 0.75 px each side of the edge, at most this
# far (px). A cap of 4 px (the sparse pass's window) would cut a defocused edge (blur
# sigma 2 px at 640x480) at 2 sigma: a line the first pass left a fraction of a pixel
# off then gives biased steps, the acute vertex scatters 0.05 px (noise-free) and its
# sigma no longer covers the tilt errors (pitch error/sigma RMS 1.4, up to 5 sigma at
# 320x240; benchmarks/triangle_defocus.py). The sparse pass is repeated on a wider
# window when the blur it measures needs one, so that the width itself is not cut short.
MAX_HALF_PX = 8.0
# The blur width is measured over the whole first-pass window, or when that is wider
# than this (px), again within 4 measured widths of the edge (at least this far)
WIDTH_REACH_MIN_PX = 4.0
# How many times the fine profiles are centred again on the lines they gave (moved more
# than TRACK_RECENTRE_PX), on a cold frame and on a tracked one, before a fit that still
# moves is given up (ok False). A tracked frame gets one: its prediction from the last
# frames was off (the platform jerked, or frames were skipped), and the full search
# starts afresh: a single re-centring without this limit would report a prediction 30 px
# off (a 640x480 frame defocused to 2 px) ok, tracked, with a vertex 0.56 px (3.7 sigma)
# off.
MAX_RECENTRES = {False: 2, True: 1}
# A tracked frame measures the blur width on its own profiles; when the median of the
# three edges differs from the widths it was fitted with by more than this factor (a
# lens refocusing mid-run), the widths are measured afresh as on a cold frame.
WIDTH_CHANGE = 1.35
# A profile's own board or triangle level further than this many robust sigmas (and
# LEVEL_OUTLIER_MIN grey levels) from its edge's level line has something else in its
# window: a head darker than the board next to the edge, a light, a smudge. Such a
# profile is left out of the level lines and the edge line: kept in, a head (grey 39
# against a board of 70) in a quarter of one edge's windows pulls that edge's
# least-squares board level line down by 8 grey levels along its whole length, and the
# line moves 0.55 px (attitude 2-4 sigma off on every noise draw).
LEVEL_OUTLIER_SIGMAS = 3.5
LEVEL_OUTLIER_MIN = 1.0
# The robust search for such profiles (about 0.1 ms a pass) runs only on an edge whose
# least-squares level lines leave residuals that the profiles' own noise does not
# explain: an RMS above LEVEL_SUSPECT_RMS times, or one residual above
# LEVEL_SUSPECT_MAX times, the noise measured from neighbouring profiles' differences
# (which a lighting gradient and a head's smooth shadow hardly touch). Below both, an
# outlier moves a line by less than the noise of one profile's level.
LEVEL_SUSPECT_RMS = 1.5
LEVEL_SUSPECT_MAX = 4.5


@dataclass(frozen=True)
class EdgeFit:
    """Lines fitted to the three edges; line i joins vertex i+1 and i+2 (opposite vertex i).

    normals : (3, 2) unit normals (ideal-pixel units, pointing into the triangle)
    offsets : (3,) n . x = offset
    centres : (3, 2) centroid of each edge's inlier points
    spreads : (3,) sum of squared along-line coordinates of the inliers about the centre
    counts : (3,) inlier counts
    sigmas : (3,) per-point standard deviation (px): the residuals' (inflated for
        correlated profiles) and the levels' error common to the edge
    outlier_fraction : (3,)
    contrast : (3,) median triangle-minus-board grey-level step on each edge
    mid_level : (3,) mean of the board and triangle grey levels along each edge
    end_gaps_px : (3, 2) length of edge with no usable profile next to each end
        (vertex i+1, vertex i+2) beyond the planned corner clearance
    width : (3,) RMS blur width of each edge (px)
    ok : False when the lines do not make a triangle near the given corners
    shutter_gain : (6, 3) or None, with ``gain``: how the vertices (normalised) move
        per rad/s of camera rate when the edge points are taken to the centre row's
        exposure (:func:`_shutter_gain`)
    lag_sums : (2, CORRELATION_LAGS + 1) or None: over the three edges' inliers, their
        residuals normalised by the edge's sigma, sum_k z_k z_(k + j) and the number of
        pairs at each lag j (points j profiles apart, both inliers) for
        visvec.noise.LearnedCorrelation
    """

    normals: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray
    spreads: np.ndarray
    counts: np.ndarray
    sigmas: np.ndarray
    outlier_fraction: np.ndarray
    contrast: np.ndarray
    mid_level: np.ndarray
    end_gaps_px: np.ndarray
    width: np.ndarray
    ok: bool = True
    shutter_gain: np.ndarray | None = None
    lag_sums: np.ndarray | None = None

    def vertex_gaps(self) -> np.ndarray:
        """(3,) for each vertex, the longer unsupported stretch of its two edges (px)."""
        g = self.end_gaps_px
        return np.array([max(g[(v + 1) % 3, 1], g[(v + 2) % 3, 0]) for v in range(3)])


def side_lengths(p: np.ndarray) -> np.ndarray:
    """(3,) side lengths, side i opposite vertex i (math on the six scalars: a fifth of
    the time of the array expression, called several times a frame)."""
    (x0, y0), (x1, y1), (x2, y2) = p.tolist()
    a, b, c, d, e, f = x1 - x2, y1 - y2, x2 - x0, y2 - y0, x0 - x1, y0 - y1
    return np.array([math.sqrt(a * a + b * b), math.sqrt(c * c + d * d), math.sqrt(e * e + f * f)])


def corner_angles(p: np.ndarray, sides: np.ndarray | None = None) -> np.ndarray:
    """(3,) interior angles (rad) from the law of cosines (``sides``: side_lengths(p))."""
    a, b, c = (side_lengths(p) if sides is None else sides).tolist()
    cos0 = (b * b + c * c - a * a) / (2 * b * c)
    cos1 = (a * a + c * c - b * b) / (2 * a * c)
    a0 = math.acos(min(max(cos0, -1.0), 1.0))
    a1 = math.acos(min(max(cos1, -1.0), 1.0))
    return np.array([a0, a1, math.pi - a0 - a1])


def _sample(
    roi: np.ndarray,
    corners: np.ndarray,
    off: np.ndarray,
    half: float,
    step: float,
    trims: np.ndarray,
    spacing: float,
):
    """Profiles across the three chords of ``corners``, all in one cv2.remap call.

    Returns bases (M, 2) in full-image px, inward normals (M, 2), edge id (M,) (the
    edges' profiles one after the other), index along the edge (M,), position along the
    edge t in [-1, 1] (M,), distance from the edge's first end (M,), values (M, S), and
    each edge's length (3,).
    """
    offs = np.arange(-half, half + 1e-9, step)
    # (compiled where the kernels are on and the corners finite)
    geometry = kernels.sample_geometry
    if not (np.isfinite(corners).all() and np.isfinite(trims).all()):
        geometry = kernels._sample_geometry_numpy
    g = geometry(corners, off, offs, trims, float(spacing), MAX_PROFILES_PER_EDGE)
    vals = cv2.remap(roi, g.map_x, g.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return g.bases, g.normals, g.gid, g.index, g.t, g.along, vals, g.lengths


def _positions(
    vals: np.ndarray,
    t: np.ndarray,
    gid: np.ndarray,
    half: float,
    step: float,
    width: np.ndarray | None,
    ext: float = 0.0,
) -> StepPositions:
    """Sub-pixel step position of each profile (offset along the inward normal), the
    local step height, the per-edge mid level, the per-edge scatter of the profiles'
    mid levels about it, and the mask of profiles whose levels agree with their edge's
    (visvec._kernels.edge_fit._level_lines; the others have something else in their
    window).

    Area (first-moment) estimator: for a step from level lo to hi, blurred by any
    symmetric kernel narrower than the profile, the integral of the normalised profile
    (I - lo) / (hi - lo) from -half to +half equals half - e. Levels lo and hi are fitted
    as straight lines along each edge to follow the lighting gradient, robustly
    (visvec._kernels.edge_fit._level_lines). With ``width``
    (per edge blur, px), the position is then refined by fitting an erf step of that
    width (GN_STEPS Gauss-Newton steps): this weights the samples by the edge slope
    instead of uniformly and cuts the noise by about 1.5x for a sharp edge.

    With ``ext`` > 0 the profiles in ``vals`` reach ``ext`` px beyond the window on both
    sides: the levels are measured over the outer 1 px + ext, the step inside.
    """
    n_ext = int(round(ext / step))
    ends = max(2, int(1.0 / step)) + n_ext
    w = _NO_WIDTH if width is None else np.asarray(width, float)
    # one function for both paths (compiled, or its Python source on numpy twins)
    return kernels.positions(vals, t, gid, float(half), float(step), w, n_ext, ends, GN_STEPS,
                             LEVEL_OUTLIER_SIGMAS, LEVEL_OUTLIER_MIN, LEVEL_SUSPECT_RMS,
                             LEVEL_SUSPECT_MAX)  # fmt: skip


def _level_gain(width: np.ndarray, half: float, step: float) -> np.ndarray:
    """(3,) px per unit of relative mid-level error: the erf-step position's shift when
    both levels of an edge are off by the same amount d, divided by d / step height.

    An error d common to the board and triangle levels shifts the normalised profile by
    -d / h everywhere; the Gauss-Newton step moves the position by (d / h) sum(g) /
    sum(g^2), g the erf model's slope (about 2 sqrt(pi) w for a window holding the blur).
    The levels are straight-line fits along the edge, so their error is common to its
    profiles: it moves the whole line and is not in the edge points' residuals. A level
    error with opposite signs on the two sides shifts nothing (symmetric slope).
    """
    # one implementation (visvec._kernels.edge_fit), compiled with the fast extra
    return kernels.level_gain(np.asarray(width, float), float(half), float(step))


def _widths(
    vals: np.ndarray, e: np.ndarray, clear: np.ndarray, gid: np.ndarray, half: float, step: float
) -> np.ndarray:
    """(3,) RMS blur width (px) per edge: second moment of the mean profile derivative.

    The profiles of the sparse pass cross chords of the coarse corners, which may be
    several px off the edge and tilted to it (an acute apex from a shrunk image), so the
    step sits at a different offset in each profile. Each profile's derivative is shifted
    by its own step position (to the nearest sample) before averaging, so the mean is
    not smeared by the chord's tilt; profiles without a clear step (``clear`` False:
    step position near the window's end, or step height under 0.4x the edge's median)
    are left out. The
    mean is not clipped at zero: noise then adds no bias (clipping widened a 0.81 px
    edge to 0.87 px median at 2 grey levels of noise). A window wider than
    WIDTH_REACH_MIN_PX (a large image's first pass, see TriangleDetector.scale) is
    measured again within 4 widths of the edge: its far bins add only noise to the
    second moment (10-90 % of a 1920x1080 webcam's cold widths 0.54-1.06 px over 8 px,
    0.77-0.89 within 4 widths).
    """
    # one function for both paths (compiled, or its Python source on numpy twins)
    return kernels.widths(vals, 0, e, clear, gid, float(half), float(step), WIDTH_REACH_MIN_PX)


def _crop(image: np.ndarray, corners_px: np.ndarray,
          tone: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The part of the image (float32) that any profile of the triangle with these
    corners can reach, and its top-left corner (x, y) in the image; with ``tone`` (a
    tone curve's table, visvec.tone.tone_lut) its levels as the linear light they
    encode."""
    reach = MAX_HALF_PX + LEVEL_EXTENT_PX + 3.0
    lo = np.floor(corners_px.min(axis=0) - reach).astype(int)
    hi = np.ceil(corners_px.max(axis=0) + reach).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [image.shape[1] - 1, image.shape[0] - 1])
    roi = image[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
    roi = roi.astype(np.float32) if tone is None else np.take(tone, roi)
    return roi, lo.astype(float)


def _edge_fit(normals, offsets, centres, spreads, sigmas, level_px, h_mid, mid, width, gid,
              keep, along, trims, lengths, lags=None) -> EdgeFit:  # fmt: skip
    """A fine pass's EdgeFit: its lines with their statistics (per edge: inliers,
    outlier share, contrast, and how far the inliers stop short of the ends)."""
    # compiled where the kernels are on, else its numpy twin
    st = kernels.edge_stats(sigmas, level_px, h_mid, gid, keep, along, trims, lengths)
    return EdgeFit(normals, offsets, centres, spreads, st.counts, st.sigmas, st.outliers, h_mid,
                   mid, st.gaps, width.copy(), lag_sums=lags)  # fmt: skip


def _pass_window(npass: int, corners: np.ndarray, w_mid: float, half0: float, step: float,
                 trim: float) -> tuple[float, float, np.ndarray, float]:  # fmt: skip
    """A pass's profiles: their half-length (px), how far beyond it the levels are read,
    how far from each vertex they stop, and their spacing along the edge. The sparse
    pass (0) uses ``half0``; a fine pass as long as the median blur ``w_mid`` needs."""
    ext = LEVEL_EXTENT_PX if npass >= 1 else 0.0
    if npass >= 1:
        half = step * np.ceil(min(max(3.0 * w_mid + 0.75, 1.5), MAX_HALF_PX) / step)
    else:
        half = half0
    # near a vertex of angle alpha the other edge is d sin(alpha) away: keep the
    # profiles (and the blur around them) clear of it
    sides = side_lengths(corners)
    trims = np.maximum(
        trim * sides.min(),
        (half + ext + 2.0 * w_mid + 0.5) / np.sin(np.maximum(corner_angles(corners, sides), 0.2)),
    )
    spacing = SPARSE_SPACING_PX if npass == 0 else PROFILE_SPACING_PX
    return half, ext, trims, spacing


@dataclass(frozen=True)
class _Profiles:
    """One pass's profiles across the edges: where each starts (bases, px) and its
    direction (normals), its edge (gid) and place along it (index, along; the edges'
    lengths), its samples (vals); the step's position on it (e, px from the base); per
    edge the mid level (mid), the levels' scatter (level_sd) and the median step height
    (h_mid); whether the profile has a clear step (clear)."""

    bases: np.ndarray
    normals: np.ndarray
    gid: np.ndarray
    index: np.ndarray
    along: np.ndarray
    lengths: np.ndarray
    vals: np.ndarray
    e: np.ndarray
    mid: np.ndarray
    level_sd: np.ndarray
    h_mid: np.ndarray
    clear: np.ndarray


def _profiles(roi, corners, off, half, ext, step, trims, spacing, width) -> _Profiles:
    """Sample the profiles of one pass and place the step on each (``width``: the blur
    widths the step model takes, or None for the first pass's area estimate)."""
    bases, normals, gid, index, t, along, vals, lengths = _sample(
        roi, corners, off, half + ext, step, trims, spacing
    )
    e, h, mid, level_sd, level_ok = _positions(vals, t, gid, half, step, width, ext)
    # per edge, the median step height; a profile has a clear step if its position is
    # inside the window and its height at least 0.4x that median
    h_mid = kernels.group_median(np.asarray(h, float), gid, index, np.ones(len(h), np.bool_))
    clear = (np.abs(e) < half - 1.0) & (h > 0.4 * np.maximum(h_mid, 1e-6)[gid]) & level_ok
    return _Profiles(bases, normals, gid, index, along, lengths, vals, e, mid, level_sd, h_mid,
                     clear)  # fmt: skip


def _lines(raw, pts_px, pr: _Profiles, camera, shutter, rate_c, sigma_floor,
           rounds) -> tuple[EdgeLines, np.ndarray]:  # fmt: skip
    """The three edge lines through the profiles' step positions, in ideal pixels
    (taken back to the centre row's exposure under a rolling shutter with a known
    rate), their normals pointing into the triangle, and the points (M, 2; ideal px)."""
    f = camera.fx
    ideal = raw * f
    if shutter is not None and rate_c is not None:
        ideal = unroll(raw, pts_px[:, 1], camera, rate_c, shutter.readout_ms, shutter.lever) * f
    # one function for both paths (compiled, or its Python source on numpy twins)
    floor, inflation = float(sigma_floor), EDGE_VARIANCE_INFLATION
    out = kernels.inward_lines(ideal[:, 0], ideal[:, 1], pr.gid, pr.index, pr.clear, floor,
                               int(rounds), inflation)  # fmt: skip
    return out, ideal


def lag_sums(ideal, gid, keep, normals, offsets, sigmas) -> np.ndarray:
    """(2, CORRELATION_LAGS + 1): the edge points' residuals from their lines over the
    edge's sigma (outliers 0), sum_k z_k z_(k + j) and the pairs of inliers j profiles
    apart on one edge, j = 0..CORRELATION_LAGS (see visvec.noise.LearnedCorrelation)."""
    # compiled where the kernels are on, else its numpy twin
    return kernels.edge_lag_sums(ideal, gid, keep, normals, offsets, sigmas, CORRELATION_LAGS)


def fit_edges(
    image: np.ndarray,
    corners_px: np.ndarray,
    camera: CameraModel,
    *,
    sigma_floor: float = 0.02,
    half: float = 4.0,
    step: float = 0.5,
    trim: float = 0.06,
    width: np.ndarray | None = None,
    shutter: RollingShutter | None = None,
    rate_c: np.ndarray | None = None,
    gain: bool = False,
    tone: np.ndarray | None = None,
) -> EdgeFit:
    """Fit the three edges of the triangle whose coarse corners are ``corners_px`` (3, 2).

    Two passes: sparse profiles across the chords of the coarse corners (``half`` px
    each side; repeated once on a longer window if the blur they measure needs one),
    then profiles every PROFILE_SPACING_PX across the lines of the first pass, centred
    on them (symmetric about the edge) and as long as the measured blur needs (3 blur
    widths + 0.75 px, at most MAX_HALF_PX). Lines are in ideal
    (undistorted) pixels: f * (normalised coordinates), f = fx.

    With ``width`` (3,), the blur widths of a previous fit, the corners are taken to be
    good to a pixel (tracking): the sparse pass is skipped, and run only if the widths
    measured on the fine profiles differ from ``width`` by more than WIDTH_CHANGE (a
    lens refocusing); the fine pass is repeated if the vertices move by more than
    ``TRACK_RECENTRE_PX``.

    With ``shutter`` and ``rate_c``, a rolling shutter whose rate is known: image row v
    is exposed t = (v - cy) / H * readout after the centre row while the camera turns
    at ``rate_c`` (rad/s, camera frame) about the platform's centre of rotation. Each edge
    point's ray d is taken back to the centre row's exposure, d0 = d + t omega_c x
    (d + lever) (see :func:`visvec.shutter.unroll`: the rotation, and the camera's
    translation on its lever arm), before the lines are fitted, so the lines and
    vertices are those of one instant. First order in the rotation.

    With ``shutter`` and ``gain``, whether or not the rate is known: the fit also
    carries ``shutter_gain`` (:func:`_shutter_gain`), the vertices' sensitivity to the
    rate, for the covariance of a rate not known yet or of the readout's error.

    With ``tone`` (the camera's tone curve as a table, visvec.tone.tone_lut) the levels
    are read as the linear light they encode, which the step model describes.
    """
    roi, off = _crop(image, corners_px, tone)
    f = camera.fx
    corners = corners_px.astype(float)
    tracked = width is not None
    width = np.full(3, half / 3.0) if width is None else np.asarray(width, float)
    half0 = half  # window of the sparse pass
    fit = None
    passes = [1] if tracked else [0, 1]
    k = 0
    recentres = 0
    while k < len(passes):
        npass = passes[k]
        k += 1
        start = corners
        w_mid = sorted(width)[1]  # median blur width of the three edges
        half, ext, trims, spacing = _pass_window(npass, corners, w_mid, half0, step, trim)
        sides = side_lengths(corners)
        pr = _profiles(roi, corners, off, half, ext, step, trims, spacing,
                       width if npass >= 1 else None)  # fmt: skip
        gid, e, clear = pr.gid, pr.e, pr.clear
        if tracked and k == 1:
            # a tracked frame keeps the widths of the last cold one: check them on this
            # pass's profiles (a lens refocusing mid-run), and measure them afresh from
            # these corners if they are off
            n_ext = int(round(ext / step))
            seen = _widths(pr.vals[:, n_ext : pr.vals.shape[1] - n_ext], e, clear, gid, half, step)
            if abs(np.log(sorted(seen)[1] / w_mid)) > np.log(WIDTH_CHANGE):
                passes.extend([0, 1])
        if npass == 0:
            width = _widths(pr.vals, e, clear, gid, half, step)
            # a blur this wide was cut short by the window: measure it again on a
            # window that holds it (once), from the corners of this pass
            need = 3.0 * sorted(width)[1] + 0.75
            if need > half0 and half0 < MAX_HALF_PX and passes.count(0) == 1:
                half0 = min(step * np.ceil(need / step), MAX_HALF_PX)
                passes.insert(k, 0)
        pts_px = pr.bases + e[:, None] * pr.normals
        raw = camera.undistort(pts_px)
        lines, ideal = _lines(
            raw, pts_px, pr, camera, shutter, rate_c, sigma_floor, 3 if npass == 1 else 1
        )
        normals_l, offsets, keep = lines.normals, lines.offsets, lines.keep
        new = camera.distort(vertices(normals_l, offsets)[0] / f)
        size = float(sides.max())
        failed = not np.isfinite(new).all() or np.abs(new - corners).max() > 0.25 * size + 3.0
        if npass == 0 and not failed:
            # a first pass only places the fine profiles: its lines' statistics are not
            # needed
            corners = new
            continue
        # the levels' share of each edge point's error (fine passes: the first pass's
        # area estimate is only used for its lines, never for a covariance)
        level_px = _level_gain(width, half, step) * pr.level_sd if npass >= 1 else np.zeros(3)
        # a fine pass's residuals along the edges, for the correlation a run learns
        lags = lag_sums(ideal, gid, keep, normals_l, offsets, lines.sigmas) if npass >= 1 else None
        fit = _edge_fit(normals_l, offsets, lines.centres, lines.spreads, lines.sigmas, level_px,
                        pr.h_mid, pr.mid, width, gid, keep, pr.along, trims, pr.lengths,
                        lags)  # fmt: skip
        if gain and shutter is not None and not failed:
            omega = np.zeros(3) if rate_c is None else np.asarray(rate_c, float)
            fit = replace(
                fit,
                shutter_gain=_shutter_gain(
                    raw, pts_px[:, 1], camera, gid, keep, normals_l, offsets / f, omega, shutter
                ),
            )
        if failed:
            # near-parallel lines from a region that is not a clean triangle: stop here
            return replace(fit, ok=False)
        corners = new
        moved = np.abs(corners - start).max()
        if npass == 1 and k == len(passes) and moved > TRACK_RECENTRE_PX:
            # the profiles were not centred on the edge (a prediction or a first pass
            # that was off): their windows cut the blur on one side, which biases the
            # levels and the step fit; centre them again, up to MAX_RECENTRES times
            if recentres == MAX_RECENTRES[tracked]:
                # still moving: the lines have not settled on the edges (a prediction
                # far off); a tracked frame then goes to the full search
                return replace(fit, ok=False)
            recentres += 1
            passes.append(1)
    return fit


# the rate step (rad/s) of the edge fit's shutter gain: 0.6 deg/s, a few hundredths of a
# pixel over a 25 ms readout (linear; far above rounding)
SHUTTER_GAIN_STEP = 0.01


def _shutter_gain(
    xy: np.ndarray,
    rows: np.ndarray,
    camera: CameraModel,
    gid: np.ndarray,
    keep: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    omega_c: np.ndarray,
    shutter: RollingShutter,
) -> np.ndarray:
    """(6, 3) G: the vertices (x1, y1, x2, ...; normalised) of the lines fitted through the
    edge points ``xy`` (normalised, as seen, at image ``rows``) after :func:`~visvec.shutter.unroll`
    with the rate omega_c + dw move by G dw (per rad/s, camera axes), the lines refitted
    through the same inliers ``keep`` (``normals``, ``offsets``: the fit's own lines at
    omega_c, normalised units). At omega_c = 0 it is :func:`visvec.shutter.shutter_matrix` of an
    edge fit: a vertex is the intersection of lines through points on many rows, and a
    turn about the boresight moves each row by an amount that grows with its row and its
    column, which curves the edges; the vertex-level matrix then missed the vertices'
    move by up to half at the apex (10 deg/s, 25 ms), enough to put a first frame's
    chi-square several times over its degrees of freedom."""
    V = [vertices(normals, offsets)[0].ravel()]
    for k in range(1, 4):
        w = np.array(omega_c, float)
        w[k - 1] += SHUTTER_GAIN_STEP
        p = unroll(xy, rows, camera, w, shutter.readout_ms, shutter.lever)
        _, c, _, n, _, _ = kernels._group_tls_numpy(p[:, 0], p[:, 1], gid, keep)
        n = n * np.where(np.sum(n * normals, axis=1) < 0.0, -1.0, 1.0)[:, None]
        V.append(vertices(n, np.sum(n * c, axis=1))[0].ravel())
    return np.column_stack([(V[k] - V[0]) / SHUTTER_GAIN_STEP for k in (1, 2, 3)])


def intersect(fit: EdgeFit, with_cov: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (3, 2) in ideal pixels and their (6, 6) covariance.

    Vertex i lies on lines j = i+1 and k = i+2. Each line is perturbed by an offset
    error (variance sigma^2 / count) and a rotation about its centre (variance
    sigma^2 / spread); at a point x on the line these move it along its normal by
    eps_o + eps_a * s(x), s = along-line distance from the centre. Stacking the six line
    errors, vertex displacements are linear in them: cov = J diag(var) J^T.
    """
    V, invs = vertices(fit.normals, fit.offsets)
    if not with_cov:
        return V, None
    if invs is None:
        return V, np.full((6, 6), np.nan)
    sig2 = np.asarray(fit.sigmas, float) ** 2
    var = np.empty(6)
    var[0::2] = sig2 / np.asarray(fit.counts, float)
    var[1::2] = sig2 / np.maximum(np.asarray(fit.spreads, float), 1e-12)
    nrm, cen = fit.normals.tolist(), fit.centres.tolist()
    J = np.zeros((6, 6))
    for i, inv in enumerate(invs):
        x = V[i].tolist()
        for row, ln in enumerate(((i + 1) % 3, (i + 2) % 3)):
            nx, ny = nrm[ln]
            s = (x[0] - cen[ln][0]) * -ny + (x[1] - cen[ln][1]) * nx  # along-line coordinate
            for q in range(2):
                J[2 * i + q, 2 * ln] += inv[q][row]
                J[2 * i + q, 2 * ln + 1] += inv[q][row] * s
    return V, (J * var) @ J.T
