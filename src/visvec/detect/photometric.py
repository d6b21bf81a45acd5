"""The triangle's edges fitted to the pixels themselves (a photometric refinement).

The edge-line fit (visvec.detect.edges) turns profiles across each edge into edge points
and fits lines through them; each step throws a little information away (the profiles'
bilinear sampling, their spacing, levels measured apart from the step, one
Gauss-Newton step of the step's position). Here the lines it found are refined by
fitting a model of the blurred edges to every pixel near them, by Gauss-Newton
(maximum likelihood under white Gaussian pixel noise, whose Fisher information is the
Cramér-Rao bound of benchmarks/triangle_crb.py):

    I(x) = L(x) + C(x) Phi(d_e(x) / w_e),

x a pixel's ideal (undistorted) coordinates, e the one edge the pixel is near,
d_e(x) = n_e . (x - c_e) - o_e its signed distance to that edge's line (inward
positive), w_e the edge's blur width, Phi the standard normal CDF (a Gaussian blur of a
straight step; the pixel's box response is taken as part of the Gaussian,
w^2 = sigma_blur^2 + 1/12), and L, C the board level and the triangle's contrast, each
linear in (1, X, Y, X^2 + Y^2), X, Y the pixel's place about the triangle's centroid: a
lighting gradient and a lens's radial falloff (vignetting, which a plane left in the
residuals: through a simulated webcam its tilts 1.2x the edge lines', 0.8x with it).
Pixels less than CLEAR_WIDTHS blur widths inside another edge (the vertices'
neighbourhoods, where a blurred corner is no longer a step) are left out; under a
rolling shutter each pixel is fitted where the centre row's exposure would have seen it
(see refine). The parameters: each line's rotation about its centre and its offset, the
three widths, the eight level coefficients; the lines give the vertices, whose
covariance follows from the fit's (the residuals' variance times (J^T J)^-1), so that
the lines' errors through the shared levels are correlated as they are.

The fit starts from the edge lines and their blur widths (a run's first fit: two
Gauss-Newton steps, the first on every other pixel) or, once the run has a blur width of
its own (the detector's average of its fits' widths, ``blur``), from that width, with
one step on every pixel (see WIDTH_SETTLED).

Phi and its derivative phi are read from a table of their values and slopes by cubic
Hermite interpolation (_phi_of, to 1e-7 of the contrast). The solve from the bands'
pixels (the Gauss-Newton steps, the bands' check, the noise correlation, the vertices'
covariance) is one function, visvec._kernels.pixel_fit.pixel_solve: compiled with the
fast extra, else run as Python with numpy twins of its loops over the pixels. With the
extra the pixels' selection (_band) runs compiled too (tested equal to its numpy
function here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visvec._kernels import pixel_fit as kernels
from visvec._kernels.edge_fit import vertices
from visvec._kernels.pixel_fit import (
    N_PARAMS,
    PixelFitSettings,
    phi_of,
)
from visvec.camera import CameraModel
from visvec.shutter import RollingShutter, unroll

GN_STEPS = 2
# the steps before the last on every FIRST_STRIDE-th pixel of each band (in its raster
# order): from the lines they only bring the fit near its optimum, which the last step,
# on every pixel, then reaches. On the 480 frames of benchmarks/triangle_crb.py the
# errors over the bound moved by at most 0.011 from two steps on every pixel (at a stride
# of 4 by up to 0.036); the first step costs half as much
FIRST_STRIDE = 2
# pixels within this many blur widths + REACH_PX of an edge are fitted to it
REACH_WIDTHS = 3.0
REACH_PX = 2.0
# and when they lie this many blur widths inside the other two edges. There the other
# edges' steps are short of their full height by Phi(-2) = 2.3 % of the contrast, which
# the model leaves out: on noise-free frames (40 scenes at each resolution and blur of
# triangle_crb.py) the attitude errors stay 0.13-0.28x the Cramer-Rao bound at 3, 2 or
# 1.5 widths alike. At 3 widths a defocused edge lost the stretches near its ends that
# set its direction (yaw 1.21x the bound at 320x240 with a blur of 2 px, 1.13x at 2
# widths; benchmarks/triangle_crb.py)
CLEAR_WIDTHS = 2.0
# A run's blur width (px, the model's w, learned by the detector from its fits: see
# refine's ``blur``) starts a frame's fit in place of the edge lines' widths, which
# measure the blur through their profiles' sampling and read about a quarter wider:
# from there a single Gauss-Newton step on every pixel reaches the optimum as closely as
# the two steps from the lines' widths do (on 30 tracked 640x480 frames, the vertices
# 0.034 sigma from the converged fit's at the median, at most 0.09, against 0.039 and
# 0.14), at the cost of one step instead of one and a half. A step that moves a width by
# more than WIDTH_SETTLED (a blur this frame does not share: a refocus, motion blur) is
# followed by another, up to WARM_STEPS in all: from a width 10 % off one step leaves
# the vertices 0.10 sigma off at the median; a lens refocused from 0.6 to 1.5 px took
# three (the widths 0.64 -> 1.20 -> 1.50 -> 1.52 px)
WIDTH_SETTLED = 0.10
WARM_STEPS = 3
# the residuals' correlation is taken over lags up to this (px, each way: 12 lags in a
# half-plane); 5 px changed no figure of benchmarks/triangle_compression.py
NOISE_LAG_PX = 2
NOISE_MIN_PAIRS = 50
# a band whose residual RMS is this many times the median band's is not fitted by the
# model (clean frames: at most 1.08; through a video codec at most 1.41)
EDGE_RMS_RATIO = 2.0


def _half_plane(L: int) -> np.ndarray:
    """(lags, 2) the lags (dx, dy) up to L each way in a half-plane (the other half are
    their negatives)."""
    return np.array([(dx, dy) for dy in range(L + 1) for dx in range(-L if dy else 1, L + 1)])


_LAGS = _half_plane(NOISE_LAG_PX)
_SQRT_2PI = math.sqrt(2.0 * math.pi)
_SQRT_2 = math.sqrt(2.0)


@dataclass(frozen=True)
class PhotometricFit:
    """Vertices (3, 2) ideal px (vertex i opposite line i), their covariance (6, 6), the
    edges' blur widths (3,), the residual RMS (grey levels), the pixels used, the
    frame's own estimate of the covariance's inflation for the noise's correlation
    (visvec._kernels.pixel_fit.noise_inflation), the Gauss-Newton steps on every pixel
    the fit took, and the run's inflation where the covariance carries it in place of
    the frame's own (visvec.noise.LearnedInflation; None where it does not)."""

    xy: np.ndarray
    cov: np.ndarray
    width: np.ndarray
    rms: float
    n_pixels: int
    ok: bool = True
    inflation: float = 1.0
    steps: int = 0
    run_inflation: float | None = None


def _refused(V: np.ndarray, w: np.ndarray, m: int) -> PhotometricFit:
    """A fit that is not to be taken (too few pixels, a singular system, a band the
    model does not fit): the starting vertices, no covariance."""
    return PhotometricFit(V, np.full((6, 6), np.nan), w, math.nan, m, ok=False)


class _IdealGrid:
    """Ideal (undistorted, f * normalised) coordinates of a camera's pixel centres:
    the pinhole's (u - cx, (v - cy) fx / fy) plus, for a lens with distortion, the
    distortion's correction at every pixel (float32, to 1e-5 px of a 100 px
    correction), computed once. A frame's fit looks up a few thousand pixels: a
    float64 table of the whole frame's coordinates (5 MB at 640x480) cost cache misses
    on each, and a lens without distortion needs none."""

    _cache: dict[tuple, np.ndarray] = {}
    _NONE = np.zeros((1, 1, 2), np.float32)

    @classmethod
    def of(cls, camera: CameraModel) -> tuple[np.ndarray, float, float, float, bool]:
        """(correction (H, W, 2) float32, cx, cy, fx / fy, whether there is one)."""
        pinhole = (float(camera.cx), float(camera.cy), float(camera.fx / camera.fy))
        if not camera.has_distortion:
            return (cls._NONE, *pinhole, False)
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
               tuple(float(k) for k in camera.dist))  # fmt: skip
        grid = cls._cache.get(key)
        if grid is None:
            u, v = np.meshgrid(np.arange(camera.width, dtype=float),
                               np.arange(camera.height, dtype=float))  # fmt: skip
            xy = camera.undistort(np.column_stack([u.ravel(), v.ravel()])) * camera.fx
            xy -= kernels.pinhole(np.column_stack([u.ravel(), v.ravel()]), *pinhole)
            grid = xy.reshape(camera.height, camera.width, 2).astype(np.float32)
            if len(cls._cache) > 4:
                cls._cache.clear()
            cls._cache[key] = grid
        return (grid, *pinhole, True)


def _unrolled(xy: np.ndarray, rows: np.ndarray, camera: CameraModel, roll) -> np.ndarray:
    """Normalised points seen at image ``rows`` taken to the centre row's exposure, for
    ``roll`` = (RollingShutter, the camera's rate (rad/s, camera axes))."""
    shutter, rate_c = roll
    return unroll(xy, rows, camera, rate_c, shutter.readout_ms, shutter.lever)


def _intersections(n: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, list | None]:
    """Vertices (3, 2) of the lines n_i . (x - c_i) = 0 (vertex i on lines i+1, i+2),
    and per vertex the inverse of its lines' 2x2 normal matrix
    (visvec._kernels.edge_fit.vertices)."""
    return vertices(n, np.add.reduce(n * c, axis=1))


def _band(image, n, c, reach, clear, camera, roll=None):
    """The pixels fitted to each edge: within its reach, and clear inside the other two
    edges. The band of each edge is a quadrilateral in the image (its corners taken
    through the lens, 1.5 px wider against the curvature a distortion gives it); the
    pixels it covers with a pixel's margin (cover) are checked exactly on their ideal
    coordinates. With ``roll`` (a rolling
    shutter and the camera's rate, see :func:`refine`) the lines are the centre row's
    exposure's: each pixel's coordinates are taken there (visvec.shutter.unroll) before
    the check, and the quadrilaterals' corners back to where their rows see them.
    Returns the pixels edge after edge (a pixel may be two edges', deep inside the
    triangle near a vertex), each edge's in raster order: their ideal coordinates
    (M, 2), grey levels (M,), places in the frame (column, row) (M, 2), and each edge's
    count (3,), as a BandPixels (numpy and compiled alike); or None."""
    grid, cx, cy, aspect, lens = _IdealGrid.of(camera)
    reach, clear = np.asarray(reach, float), np.asarray(clear, float)
    if roll is None:  # compiled where the kernels are on, else its numpy twin
        found, bands = kernels.band_lines(
            image, n, c, reach, clear, camera.fx, camera.fy, camera.cx, camera.cy, camera.dist,
            camera.width - 1, camera.height - 1, grid, cx, cy, aspect, lens)  # fmt: skip
        return bands if found else None
    o = np.einsum("ij,ij->i", n, c)
    q = kernels.band_quads(n, o, reach, clear) / camera.fx
    # where the rows see the corners: the centre row's point less its unroll shift (to
    # first order; the 1.5 px margin holds the rest)
    rows = camera.distort(q)[:, 1]
    q = q - (_unrolled(q, rows, camera, roll) - q)
    q_px = camera.distort(q)
    box = kernels.band_box(q_px, camera.width - 1, camera.height - 1)
    if box is None:
        return None
    # the pixels the three bands cover; band_pixels' exact check gives each pixel to
    # each edge whose rule it meets, on its coordinates taken to the centre row
    pts = kernels.cover(q_px, *box)
    if not len(pts):
        return None
    x = kernels.ideal_coordinates(pts, grid, cx, cy, aspect, lens)
    x = _unrolled(x / camera.fx, pts[:, 1], camera, roll) * camera.fx
    return kernels.band_pixels(pts, x, grid, cx, cy, aspect, lens, image, n, o, reach, clear)


# The blurred step Phi(u) and its slope phi(u) (the standard normal CDF and density) by
# cubic Hermite interpolation between nodes PHI_STEP apart on [-PHI_RANGE, PHI_RANGE],
# each node's value and slope exact (Phi' = phi, phi' = -u phi): the error is at most
# h^4 / 384 times the function's largest fourth derivative (Burden & Faires, Numerical
# Analysis, Thm. 3.9), 2e-8 for Phi and 5e-8 for phi at h = 1/16 (of the contrast:
# far below a grey level; the exp(-u^2 / 2) and Abramowitz & Stegun's erf 7.1.26 it
# replaces were good to 1e-7). Beyond the range the ends' values (Phi within 1e-15 of 0
# or 1). Less than half the time of exp and erf in the fit's innermost loop.
PHI_STEP = 1.0 / 16.0
PHI_RANGE = 8.0


def _phi_nodes() -> np.ndarray:
    """(N + 1, 4) per node u_i: Phi(u_i), h phi(u_i), phi(u_i), h phi'(u_i)."""
    u = np.linspace(-PHI_RANGE, PHI_RANGE, int(round(2.0 * PHI_RANGE / PHI_STEP)) + 1)
    p = np.exp(-0.5 * u * u) / _SQRT_2PI
    big = np.array([0.5 * math.erfc(-v / _SQRT_2) for v in u])  # (scipy not imported here)
    return np.ascontiguousarray(np.column_stack([big, PHI_STEP * p, p, -PHI_STEP * u * p]))


_PHI = _phi_nodes()
# the constants as the solve takes them (visvec._kernels.pixel_fit.pixel_solve)
SETTINGS = PixelFitSettings(GN_STEPS, FIRST_STRIDE, _LAGS, NOISE_LAG_PX, NOISE_MIN_PAIRS,
                            EDGE_RMS_RATIO, WIDTH_SETTLED, WARM_STEPS, _PHI, PHI_RANGE,
                            1.0 / PHI_STEP)  # fmt: skip


def _phi_of(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Phi(u) and phi(u) from the table _PHI (visvec._kernels.pixel_fit.phi_of, which
    the compiled fit evaluates too)."""
    return phi_of(u, _PHI, PHI_RANGE, 1.0 / PHI_STEP)


def _lines_and_bands(image, normals, offsets, width, camera, roll=None):
    """:func:`refine`'s start: the lines' normals n (3, 2), their vertices V (3, 2), each
    line's centre c (3, 2) (the middle between its two vertices), the widths w (3,) (at
    least 0.3 px) and the bands' pixels (_band: a BandPixels, or None)."""
    n = np.asarray(normals, float).copy()
    V, _ = _intersections(n, n * np.asarray(offsets, float)[:, None])
    c = 0.5 * (V[[1, 2, 0]] + V[[2, 0, 1]])
    w = np.maximum(np.asarray(width, float), 0.3)
    bands = _band(image, n, c, REACH_WIDTHS * w + REACH_PX, CLEAR_WIDTHS * w, camera, roll)
    return n, V, c, w, bands


def refine(image: np.ndarray, normals: np.ndarray, offsets: np.ndarray, width: np.ndarray,
           camera: CameraModel, shutter: RollingShutter | None = None,
           rate_c: np.ndarray | None = None, blur: float | None = None,
           tone: np.ndarray | None = None) -> PhotometricFit:  # fmt: skip
    """Refine the edge lines n_i . x = offset_i (ideal px, normals into the triangle)
    on the pixels of ``image``; ``width`` (3,) the edge lines' blur widths, which set the
    bands (and start the fit without ``blur``).

    ``blur``: the run's blur width in the model's terms (the fits' widths so far); the
    fit then starts from it and takes one Gauss-Newton step on every pixel, another
    while the last moved a width by more than WIDTH_SETTLED (WARM_STEPS in all at most).
    Without it (a run's first fit), a step on every FIRST_STRIDE-th pixel first
    (GN_STEPS in all).

    With a rolling ``shutter`` and the camera's rate ``rate_c`` (rad/s, camera axes),
    the lines are those of the centre row's exposure (edges.fit_edges takes its edge
    points there): each pixel is fitted at its coordinates taken there too
    (visvec.shutter.unroll: the lab point a pixel sees at its row's time, where the
    centre row's exposure would see it). The blurred step model then holds as for a
    still image: the shift varies smoothly, a fraction of a pixel across a band.

    ``tone``: the camera's tone curve as a table (visvec.tone.tone_lut); the pixels'
    levels are then read as the linear light they encode, which the model describes."""
    roll = None
    if shutter is not None and shutter.readout_ms and rate_c is not None:
        roll = (shutter, np.asarray(rate_c, float))
    n, V, c, w, bands = _lines_and_bands(image, normals, offsets, width, camera, roll)
    counts = np.zeros(3, np.int64) if bands is None else bands[3]
    m = int(counts.sum())
    if m < 3 * N_PARAMS or counts.min() < 10:
        return _refused(V, w, m)
    x, y, uv, _ = bands
    if tone is not None:
        # the levels as the linear light they encode (the camera's tone curve)
        y = np.take(tone, y.astype(np.int64)).astype(float)
    centroid = V.mean(axis=0)
    scale = max(float(np.abs(V - centroid).max()), 1.0)
    warm = blur is not None and math.isfinite(blur)
    if warm:
        w = np.full(3, max(float(blur), 0.3))
    # compiled with the fast extra, else its Python source on numpy (one function)
    fit = kernels.pixel_solve(x, y, uv, counts, n, c, w, V, centroid, scale, warm, SETTINGS)
    if not fit.ok:
        return _refused(fit.V, fit.w, m)
    return PhotometricFit(fit.V, fit.cov, fit.w, math.sqrt(fit.s2), m, inflation=fit.inflation,
                          steps=int(fit.steps))  # fmt: skip
