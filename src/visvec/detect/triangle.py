"""The triangle detector: region search, sub-pixel vertices, identification, checks.

Follows the paper (Virginia Tech Visual Vector Sensor, Sec. IV.B-D): three corners
with a minimum separation, the most acute vertex first, the centroid, and an area
check against the known triangle. Made robust: the triangle is found as a region
first (see :mod:`visvec.detect.candidates`), vertices come from edge-line fits
(:mod:`visvec.detect.edges`) or cornerSubPix, and shape, angles, contrast, the dark
surround, saturation and the field-of-view edge are checked so that a wrong triangle
is rejected with a reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from visvec.chi2 import ppf as chi2_ppf
from visvec.data import Detection, Status
from visvec.detect.candidates import Candidate, iter_candidates, partial_triangle
from visvec.detect.edges import (
    LEVEL_EXTENT_PX,
    MAX_HALF_PX,
    corner_angles,
    fit_edges,
    intersect,
    side_lengths,
)
from visvec.detect.photometric import PhotometricFit, refine
from visvec.detect.warm import warm_up
from visvec.errors import ConfigError
from visvec.geometry import project_target
from visvec.noise import LearnedCorrelation, LearnedInflation
from visvec.rig import Rig
from visvec.shutter import RollingShutter, shutter_matrix, shutter_shift
from visvec.tone import tone_lut

# Tolerances of the shape checks (relative, or degrees), chosen to pass every tilt
# within max_tilt_deg of the paper's geometry with a wide margin.
AREA_TOL = 0.30
SIDE_RATIO_TOL = 0.06
APEX_ANGLE_TOL_DEG = 4.0
MAX_VERIFICATIONS = 4
VERTEX_GAP_MIN_PX = 3.0
VERTEX_GAP_FRACTION = 0.05
# reasons meaning "this region is not the triangle" (as opposed to "the triangle, unusable")
NOT_THE_TARGET = frozenset(
    {
        "area_mismatch",
        "shape_mismatch",
        "edge_fit_failed",
        "angle_mismatch",
        "degenerate_triangle",
        "corners_not_found",
    }
)
REGION_AREA_TOL = 0.08
EDGE_OUTLIER_MAX = 0.25
BORDER_MARGIN_PX = 3.0
SATURATED_MAX = 0.2
# the pixel checks' polygons (see TriangleDetector._pixel_reason): the triangle scaled
# about its centre: saturation inside, the region, the surround's band (outer, inner
# edge) and the inside it is compared with
_CHECK_SCALES = np.array([0.8, 1.2, 1.25, 1.08, 0.75])
# a region showing a corner of the triangle (no last frame to go by) with less than this
# share of its outline an edge is the triangle joined to a brighter part of the board
# (measured: 0.5-0.74 for 98 % of such regions, 0.9-1.0 for most of those joined to a
# person or a light)
PARTIAL_EDGE_FRACTION = 0.75
# nodes per side of the table of the triangle's expected image area over the field
AREA_GRID = 17
# a candidate's coarse corners must lie this far (px, plus a shrunk pixel of the region
# search) inside the lens model's field (CameraModel.field_r2): the edge profiles reach
# MAX_HALF_PX and LEVEL_EXTENT_PX beyond the edges
FIELD_MARGIN_PX = MAX_HALF_PX + LEVEL_EXTENT_PX + 2.0
# and there, a region is taken for the triangle when its corners' angles in the image
# are within this of the triangle's (deg; loose: no rays to measure it by)
FOLD_ANGLE_TOL_DEG = 12.0
# and a region showing one of its corners there (no last frame to go by) when it is
# smaller than this many times its expected area (near the fold the model's area is no
# guide: a triangle hung 2.4 m off the axis shows 2x the area the model expects there)
FOLD_AREA_FACTOR = 4.0
# a corner whose inside averages this grey level or more is saturated
SATURATED_LEVEL = 250.0
# per-coordinate noise of cornerSubPix vertices, measured on simulated frames (0.26 px
# at the base vertices, 0.45 px at the blunted acute one; tests/benchmarks)
CORNER_SIGMA_PX = 0.35
# the pixel fit's vertices are taken when they agree with the edge lines' (see _pixel_fit)
PIXEL_FIT_GATE_P = 1e-4
# the run's blur width that starts the pixel fit (photometric.refine's ``blur``): the
# median of the three edges' widths of each detection's pixel fit, averaged over the
# frames with this forgetting factor (about ten frames); a fit that needed more than one
# step from it (the blur changed: a refocus) replaces it, and one not taken clears it
BLUR_FORGET = 0.9


# the (6,) covariance index of each identification's vertex order (x0, y0, x1, ...)
_PERM_INDEX = {
    perm: np.array([c for v in perm for c in (2 * v, 2 * v + 1)])
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
}


def _signed_area(p: np.ndarray) -> float:
    a, b = p[1] - p[0], p[2] - p[0]
    return 0.5 * float(a[0] * b[1] - a[1] * b[0])


def facing(xy_n: np.ndarray) -> np.ndarray:
    """(N, 2) normalised image points as a camera at the same place turned to face them
    would see them: their bearings rotated so that the unit bearings' mean is the
    boresight (about the axis perpendicular to both), then projected.

    The triangle's angles, side ratios and area in the image change with where it falls
    in the field (an image plane cuts a cone of rays off its axis obliquely: the area
    grows as 1 / cos^3 of the angle off the boresight); seen faced, they change only with
    the target's own obliqueness to the line of sight. A rig whose target hangs 450 mm
    off the axis, seen by a camera tilted 12 deg towards it: the apex angle in the image
    differs from its zero-attitude value by up to 4.1 deg within 5 deg of tilt (a whole
    triangle refused as ``angle_mismatch``), faced by 0.2 deg.
    """
    b = np.empty((len(xy_n), 3))
    b[:, :2] = xy_n
    b[:, 2] = 1.0
    b /= np.sqrt(np.einsum("ij,ij->i", b, b))[:, None]
    dx, dy, dz = (b.sum(axis=0) / len(b)).tolist()
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = dx / n, dy / n, dz / n
    s = math.hypot(dx, dy)  # sin of the turn; cos is dz
    if s < 1e-12:
        return np.array(xy_n, float)
    # Rodrigues' formula about k = d x z / s = (dy, -dx, 0) / s, which takes d to z
    kx, ky = dy / s, -dx / s
    c1 = 1.0 - dz
    Q = np.array(
        [
            [1.0 - c1 * ky * ky, c1 * kx * ky, s * ky],
            [c1 * kx * ky, 1.0 - c1 * kx * kx, -s * kx],
            [-s * ky, s * kx, dz],
        ]
    )
    q = b @ Q.T
    return q[:, :2] / q[:, 2:3]


def _masked_mean(image: np.ndarray, mask255: np.ndarray) -> float:
    """cv2.mean(image, mask) of a uint8 image under a 0/255 mask (0 for an empty mask),
    as a masked sum: 5x faster than cv2.mean's masked path."""
    n = cv2.countNonZero(mask255)
    return cv2.sumElems(image & mask255)[0] / n if n else 0.0


# the 3x3 neighbourhood of a pixel (rows, columns), for TriangleDetector._still_there
_LOOK_DV, _LOOK_DU = np.mgrid[-1:2, -1:2].reshape(2, 9)


@dataclass(frozen=True)
class _Measured:
    """A candidate's measured vertices: undistorted (xy, px at fx) and in the image
    (pts_px), their covariance (6x6), the edges' weakest contrast and largest outlier
    share, the largest gap between an edge's end and its vertex (px), the level
    halfway between the triangle and its surround, the shutter gain (or None), and the
    edge points' lag sums (EdgeFit.lag_sums, or None)."""

    xy: np.ndarray
    pts_px: np.ndarray
    cov: np.ndarray
    contrast: float
    outliers: float
    vertex_gap: float
    level_mid: float
    gain: np.ndarray | None
    lags: np.ndarray | None


def _centre(p: np.ndarray) -> np.ndarray:
    """The mean of the (3, 2) vertices, as ndarray.mean takes it (the sum over 3) without
    its wrapper's cost."""
    return np.add.reduce(p, axis=0) / 3


def _pixel_fit(image, fit, xy, cov, camera, shutter=None, rate_c=None, blur=None,
               tone=None, inflation=None):  # fmt: skip
    """The vertices of the edge lines refined on the pixels (visvec.detect.photometric,
    started from the run's blur width ``blur`` where there is one), and the fit, when
    the refinement agrees with them: the edge lines are robust (their profiles'
    outliers left out, something in a window found), the pixel fit is not, so a pixel
    fit that moved the vertices by more than the lines' own covariance allows (chi-square,
    6 dof, p = 1e-4: a head in an edge's band, a light), or whose covariance is the wider
    of the two, is not taken, and the lines' vertices and covariance stand. Under a
    rolling ``shutter`` the pixels are taken to the centre row's exposure with the rate
    ``rate_c``; without a rate yet (a first frame) the lines stand, their covariance
    widened for the rate they could not take out. The fit is False where it was made and
    not taken, None where none was made. With the run's learned ``inflation``
    (visvec.noise.LearnedInflation), a fit whose own estimate of its noise's correlation
    is a draw of the run's takes the run's in its covariance."""
    if shutter is not None and rate_c is None:
        return xy, cov, None
    pf = refine(image, fit.normals, fit.offsets, fit.width, camera, shutter, rate_c, blur,
                tone)  # fmt: skip
    if not pf.ok or not np.isfinite(pf.cov).all():
        return xy, cov, False
    if inflation is not None and inflation.within(pf.inflation):
        run = inflation.value
        pf = replace(pf, cov=pf.cov * (run / pf.inflation), run_inflation=run)
    dv = (pf.xy - xy).ravel()
    try:
        chi2_ = float(dv @ np.linalg.solve(cov + pf.cov, dv))
    except np.linalg.LinAlgError:
        return xy, cov, False
    if not chi2_ < chi2_ppf(1.0 - PIXEL_FIT_GATE_P, 6):
        return xy, cov, False
    # and when it is the more precise: residuals with a structure of their own (a head
    # in a band) widen its covariance through their correlation
    # (visvec._kernels.pixel_fit.noise_inflation) beyond the lines'
    if not pf.cov.trace() < cov.trace():
        return xy, cov, False
    return pf.xy, pf.cov, pf


class TriangleDetector:
    """Finds the rig's triangle in frames of the rig's camera.

    Parameters
    ----------
    rig : Rig
        Camera model, target geometry and detector settings.

    Notes
    -----
    Keeps the last good detection's threshold so that a tracked sequence tries one
    grey level before searching the whole histogram.
    """

    def __init__(self, rig: Rig):
        self.rig = rig
        cam = rig.camera
        # the camera's tone curve: the fits read linear light through it (visvec.tone)
        self._tone = tone_lut(rig.tone_curve)
        # the compiled kernels loaded before the first frame, not on it
        warm_up(pixel_fit=rig.detect.refine == "pixels")
        self.expected_px = project_target(rig, np.eye(3))
        if not np.all(np.isfinite(self.expected_px)):
            # (a rig file is refused for it when loaded; this is one made in code)
            raise ConfigError(
                "[target] vertices_mm: at zero attitude the triangle lies behind the camera "
                "or beyond the lens model's field; expected it in view"
            )
        xy_n = cam.undistort(self.expected_px)
        xy = xy_n * cam.fx
        # the shape checks' references: the triangle at zero attitude, faced (see facing)
        seen = facing(xy_n) * cam.fx
        self.expected_area = abs(_signed_area(seen))
        self.expected_sign = np.sign(_signed_area(xy))
        sides = side_lengths(seen)
        self.expected_side_ratio = sides / sides.sum()
        self.expected_apex_deg = float(np.degrees(corner_angles(seen, sides))[0])
        # the region search's and the partial corners' references: in the image (its
        # regions' areas in pixels as seen, through the lens's distortion: a barrel lens
        # of 115 deg shows the triangle hung 950 mm off the axis at 0.76 of its
        # undistorted area)
        self.expected_image_area = abs(_signed_area(self.expected_px))
        sides = side_lengths(xy)
        self.expected_angles_deg = np.degrees(corner_angles(xy))
        self.expected_sides_px = sides
        # search on a shrunk image where the triangle is 40-80 px tall: the image halved
        # as often as that allows (cv2.resize has a fast path for exactly 2x; a 7x step
        # took 350 us on a 1280x720 frame, three halvings 50 us)
        height_px = (
            float(
                np.ptp(self.expected_px @ np.array([1.0, 0.0]))
                + np.ptp(self.expected_px @ np.array([0.0, 1.0]))
            )
            / 1.5
        )
        self.scale = 1 << max(0, int(math.log2(max(height_px, 1.0) / 40.0)))
        # the paper's minimum corner distance, 45 px at 320x240, scaled with resolution
        # (and kept below the shortest side the rig's triangle can show)
        self.min_corner_distance = min(45.0 * cam.width / 320.0, 0.8 * float(np.min(sides)))
        # the rate prior for a rolling-shutter frame without a measured rate: uniform
        # within +-max_rate_dps about b3 and +-max_tilt_rate_dps about b1 and b2
        # (sigma = bound / sqrt(3)), in camera axes
        sd = np.radians([rig.max_tilt_rate_dps, rig.max_tilt_rate_dps, rig.max_rate_dps])
        self._cov_omega = rig.R_bc.T @ np.diag(sd**2 / 3.0) @ rig.R_bc
        # a rolling shutter's lever arm b / Z (see visvec.shutter.unroll): the camera's position
        # in B in camera axes over the target's depth (at zero attitude: within 2 % at
        # the tilts an air bearing allows)
        b_c = rig.R_bc.T @ rig.t_b
        depth = float(np.mean((rig.target.vertices_mm - rig.t_b) @ rig.R_bc[:, 2]))
        self.lever_c = b_c / depth
        # the readout in use (ms) and its 1-sigma: the rig's (as `calibrate readout`
        # measured it), or one the pipeline estimates from the frames of a camera the rig
        # file says has a global shutter
        self.readout_ms = rig.readout_ms
        self.readout_sigma_ms = rig.readout_sigma_ms
        self._area_grid = self._area_table()  # see _image_area_at
        self._folds = not math.isinf(cam.field_r2)  # the lens model's field ends in view
        self._last_level: float | None = None
        self._last_points: np.ndarray | None = None
        self._prev_points: np.ndarray | None = None
        self._last_width: np.ndarray | None = None
        self._fit_width: np.ndarray | None = None
        # the run's blur width for the pixel fit (BLUR_FORGET), and the last verified
        # candidate's pixel fit (False: made and not taken, None: none made); a property
        # of the lens and its focus, kept through reset
        self._blur: float | None = None
        self._pixel: PhotometricFit | bool | None = None
        # the pixel fit's noise inflation learned over the run (a property of the
        # camera's demosaicing and codec), kept through reset
        self.inflation = LearnedInflation()
        # the last detection came from the previous frame's vertices (small motion)
        self.last_was_tracked = False
        # the edge points' correlation along the edges, learned over the run's frames
        # (a video codec's, a camera's smoothing): it widens the edge lines' covariance
        self.correlation = LearnedCorrelation()
        self._lags: np.ndarray | None = None  # the last verified detection's lag sums
        # the grey level halfway between the triangle and its surround, at the last
        # verified detection (the tracked frame's quick look, _still_there)
        self._mid_level: float | None = None
        # the frame came through a codec that predicts frames from earlier ones
        # (visvec.data.inter_frame of its Frame.codec, set by the pipeline): the pixel
        # fit is not taken (see _measure)
        self.inter_frame = False

    def _tracked_candidate(self, pts: np.ndarray) -> Candidate:
        inside = bool(self.rig.camera.in_image(pts, 2.0).all())
        return Candidate(
            corners_px=pts,
            contour_px=pts,
            area_px=abs(_signed_area(pts)),
            level=self._last_level or 0.0,
            touches_border=not inside,
            fill=1.0,
            tracked=True,
        )

    def _area_table(self) -> list:
        """The triangle's expected image area (px) at AREA_GRID x AREA_GRID nodes over the
        image: its solid angle (the faced area at zero attitude, see facing) times the
        lens's pixels per steradian there (the lens's undistortion takes 15 us a call, so
        :meth:`_image_area_at` interpolates this table)."""
        cam = self.rig.camera
        u = np.linspace(-0.5, cam.width - 0.5, AREA_GRID)
        v = np.linspace(-0.5, cam.height - 0.5, AREA_GRID)
        uu, vv = np.meshgrid(u, v)
        ppsr = cam.pixels_per_steradian(np.column_stack([uu.ravel(), vv.ravel()]))
        area = self.expected_area / cam.fx**2 * ppsr  # solid angle x px per sr
        # beyond the lens model's field (nan, see CameraModel.field_r2), and wherever the
        # value is implausible: the area at zero attitude
        ref = self.expected_image_area
        area[~(np.abs(np.log(area / ref)) < np.log(3.0))] = ref
        return area.reshape(AREA_GRID, AREA_GRID).tolist()

    def _image_area_at(self, uv: tuple[float, float]) -> float:
        """The triangle's expected area (px) in the image when it is centred at pixel
        ``uv`` (u, v), bilinear in :meth:`_area_table`. Off the boresight, and through a wide
        lens's distortion, the same triangle covers more or fewer pixels (1.3x the
        centre's at 20-25 deg off the boresight through a 56 deg lens)."""
        cam, g, n = self.rig.camera, self._area_grid, AREA_GRID - 1
        fu = min(max((float(uv[0]) + 0.5) / cam.width * n, 0.0), n - 1e-9)
        fv = min(max((float(uv[1]) + 0.5) / cam.height * n, 0.0), n - 1e-9)
        i, j = int(fv), int(fu)
        a, b = fv - i, fu - j
        return (1 - a) * ((1 - b) * g[i][j] + b * g[i][j + 1]) + a * (
            (1 - b) * g[i + 1][j] + b * g[i + 1][j + 1]
        )

    def reset(self) -> None:
        """Forget the previous frame (start of a new, unrelated sequence)."""
        self._last_level = None
        self._last_points = None
        self._prev_points = None
        self._last_width = None
        self._mid_level = None

    def _still_there(self, image: np.ndarray, pts: np.ndarray) -> bool:
        """A quick look before a tracked frame's edge fit: is the triangle still where
        ``pts`` (the predicted vertices) put it? Its inside (the centroid and three
        points 60 % of the way to the vertices) brighter than the last frame's mid
        level, and outside it (two or more of the edges' midpoints pushed out by a fifth
        of the inscribed radius, at least 3 px) darker, each a 3x3 mean. A frame whose
        triangle jumped (a new attitude, a dropped stretch of frames) skips the fit that
        would fail (about a third of a cold frame) and goes to the search at once; a
        look it cannot take (points out of the image, no level yet) lets the fit
        decide."""
        level = self._mid_level
        if level is None:
            return True
        (ax, ay), (bx, by), (cx, cy) = pts.tolist()
        gx, gy = (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0
        look = [(gx, gy)] + [(gx + 0.6 * (x - gx), gy + 0.6 * (y - gy))
                             for x, y in ((ax, ay), (bx, by), (cx, cy))]  # fmt: skip
        sides = (
            math.hypot(bx - ax, by - ay)
            + math.hypot(cx - bx, cy - by)
            + math.hypot(ax - cx, ay - cy)
        )
        area = 0.5 * abs((bx - ax) * (cy - ay) - (cx - ax) * (by - ay))
        push = max(3.0, 0.2 * 2.0 * area / max(sides, 1e-9))  # a fifth of the inradius
        for (px, py), (qx, qy) in (((ax, ay), (bx, by)), ((bx, by), (cx, cy)),
                                   ((cx, cy), (ax, ay))):  # fmt: skip
            mx, my = 0.5 * (px + qx), 0.5 * (py + qy)
            dx, dy = mx - gx, my - gy
            n = max(math.hypot(dx, dy), 1e-9)
            look.append((mx + push * dx / n, my + push * dy / n))
        uv = np.rint(np.array(look)).astype(np.intp)
        h, w = image.shape[:2]
        if not (uv.min() >= 1 and uv[:, 0].max() < w - 1 and uv[:, 1].max() < h - 1):
            return True
        # each point's 3x3 mean, in one gather
        vals = image[uv[:, 1, None] + _LOOK_DV, uv[:, 0, None] + _LOOK_DU].mean(axis=1).tolist()
        return min(vals[:4]) > level and sum(x < level for x in vals[4:]) >= 2

    # ------------------------------------------------------------------ public
    def detect(self, image: np.ndarray, omega_c: np.ndarray | None = None) -> Detection:
        """Detection of the triangle in one (H, W) uint8 image (never raises on content).

        ``omega_c``: the camera's angular rate (rad/s, camera frame) for a rolling-shutter
        rig (``readout_ms`` != 0): the vertices are then those of the centre row's
        exposure (see fit_edges)."""
        rate_c = (
            np.asarray(omega_c, float) if omega_c is not None and self.readout_ms != 0 else None
        )
        mean, warnings = self._brightness(image)
        reason, contour = "", np.zeros((0, 2))
        self.last_was_tracked = False
        self._lags = None
        if self._last_points is not None:
            # tracking: refine straight from the last frame's vertices; any failed check
            # falls back to the full search below
            pred = self._last_points
            if self._prev_points is not None:
                pred = 2.0 * self._last_points - self._prev_points  # constant velocity
            det = (
                self._verify(image, self._tracked_candidate(pred), warnings, mean, rate_c)
                if self._still_there(image, pred)
                else None
            )
            if det is not None and det.status is Status.OK:
                self._prev_points, self._last_points = self._last_points, det.points_px
                self._last_width = self._fit_width
                self.last_was_tracked = True
                self._learn()
                return det
        levels = None if self._last_level is None else np.array([self._last_level])
        for _attempt in range(2):
            tried = 0
            for cand in iter_candidates(
                image,
                self.expected_image_area,
                scale=self.scale,
                levels=levels,
                area_at=self._image_area_at,
            ):
                det = self._verify(image, cand, warnings, mean, rate_c)
                if det.status is Status.OK:
                    self._last_level = cand.level
                    self._prev_points, self._last_points = None, det.points_px
                    self._last_width = self._fit_width
                    self._learn()
                    return det
                # a region that is not the triangle's shape says nothing; one that is
                # but fails a later check is the triangle, unusable for that reason
                if det.reason not in NOT_THE_TARGET and not reason:
                    reason, contour = det.reason, det.contour_px
                tried += 1
                if tried >= MAX_VERIFICATIONS:
                    break
            if levels is None:
                break
            levels = None  # the tracked level failed: search the whole histogram
        last = self._last_points
        self.reset()
        if not reason and last is not None:
            # the triangle was there in the last frame: it left the view or something
            # is in front of it
            near_edge = not np.all(self.rig.camera.in_image(last, 0.05 * self.rig.camera.width))
            reason = "partly_out_of_view" if near_edge else "obstructed"
        elif not reason:
            # no last frame to go by: a region showing one of the triangle's corners
            # says it is there, but not whole or not usable
            reason, contour = self._partial_reason(image)
        if not reason:
            return Detection(
                Status.NO_TARGET,
                warnings=tuple(warnings + ["no_triangle"]),
                reason="no_triangle",
                mean_brightness=mean,
            )
        return Detection(
            Status.REJECTED,
            warnings=tuple(warnings + [reason]),
            reason=reason,
            mean_brightness=mean,
            contour_px=contour,
        )

    def redetect(self, image: np.ndarray, omega_c: np.ndarray) -> Detection:
        """The last detection's triangle in the same ``image`` again, its edge points
        taken to the centre row's exposure with the camera rate ``omega_c`` (rad/s,
        camera frame): a rolling-shutter frame whose rate became known only from its
        own first detection. On success it replaces the last detection's vertices."""
        if self._last_points is None or self.readout_ms == 0:
            raise ValueError("redetect needs a rolling-shutter rig and a last detection")
        rate_c = np.asarray(omega_c, float)
        mean, warnings = self._brightness(image)
        det = self._verify(
            image, self._tracked_candidate(self._last_points), warnings, mean, rate_c
        )
        if det.status is Status.OK:
            self._last_points = det.points_px
            self._last_width = self._fit_width
        return det

    def _learn(self) -> None:
        """The frame's edge points join the correlation learned over the run; its pixel
        fit's widths, the run's blur, and its noise inflation, the run's."""
        if self._lags is not None:
            sums, pairs = self._lags.tolist()
            self.correlation.add(sums, pairs, 3)
        pf = self._pixel
        if pf is False:
            # a pixel fit not taken (a head in a band, or a start from a blur that no
            # longer holds): the next one starts from the lines' widths and relearns it
            self._blur = None
        elif pf is not None:
            self.inflation.add(pf.inflation)
            w = sorted(pf.width.tolist())[1]  # the three edges' median
            if self._blur is None or pf.steps > 1:
                self._blur = w
            else:
                self._blur = BLUR_FORGET * self._blur + (1.0 - BLUR_FORGET) * w

    # ------------------------------------------------------------------ steps
    def _brightness(self, image: np.ndarray) -> tuple[float, list[str]]:
        """Mean grey level and its warning when outside the rig's brightness band."""
        band = self.rig.detect.brightness_band
        # the sum over the pixels (cv2.sumElems) over their count: the same mean in a
        # quarter of cv2.mean's time (30 us at 640x480)
        mean = cv2.sumElems(image)[0] / (image.shape[0] * image.shape[1])
        if mean < band[0]:
            return mean, ["low_brightness"]
        if mean > band[1]:
            return mean, ["high_brightness"]
        return mean, []

    def _reject(
        self,
        reason: str,
        warnings: list[str],
        mean: float,
        cand: Candidate,
        pts: np.ndarray | None = None,
    ) -> Detection:
        return Detection(
            Status.REJECTED,
            points_px=pts if pts is not None else np.full((3, 2), np.nan),
            warnings=tuple(warnings + [reason]),
            reason=reason,
            mean_brightness=mean,
            contour_px=cand.contour_px,
        )

    def _verify(
        self,
        image: np.ndarray,
        cand: Candidate,
        warnings: list[str],
        mean: float,
        rate_c: np.ndarray | None = None,
    ) -> Detection:
        """The candidate's vertices and covariance, or the reason it is refused
        (``rate_c``: the camera's rate, rad/s, camera axes, for a rolling-shutter rig;
        see fit_edges). Steps: 1. measure the vertices; 2. name them (the most acute
        first, then the rig's handedness); 3. check the shape against the known
        triangle; 4. check that the image can be trusted there; 5. add what a rolling
        shutter leaves in the vertices."""
        cam, s = self.rig.camera, self.rig.detect
        m = self._measure(image, cand, rate_c)
        if isinstance(m, str):
            return self._reject(m, warnings, mean, cand)
        if not np.isfinite(m.xy).all() or not side_lengths(m.xy).min() > 0.0:
            return self._reject("degenerate_triangle", warnings, mean, cand)
        m, seen, seen_angles = self._named(m)
        reason = self._shape_reason(m, seen, seen_angles) or self._usability_reason(image, cand, m)
        if reason:
            return self._reject(reason, warnings, mean, cand, m.pts_px)
        w = list(warnings)
        if not cam.in_image(m.pts_px, BORDER_MARGIN_PX + 0.02 * cam.width).all():
            w.append("near_fov_edge")
        consider, gain = self._shutter_consider(m, rate_c)
        self._lags = m.lags
        self._mid_level = m.level_mid
        return Detection(
            Status.OK,
            points_px=m.pts_px,
            points_n=m.xy / cam.fx,
            # sigma_scale: measured by `calibrate zero-tilt` where the frames' noise is
            # wider than the edge model's (a codec's block errors)
            cov_n=m.cov * (s.sigma_scale / cam.fx) ** 2,
            consider_n=consider,
            shutter_gain_n=gain,
            warnings=tuple(w),
            mean_brightness=mean,
            contour_px=cand.contour_px,
        )

    def _measure(
        self, image: np.ndarray, cand: Candidate, rate_c: np.ndarray | None
    ) -> _Measured | str:
        """Step 1: the vertices from the edge lines (or the corners), or a reason."""
        cam, s = self.rig.camera, self.rig.detect
        self._pixel = None
        # beyond the fold of a strong distortion's polynomial the model has no rays (a
        # calibration's fit extrapolated past the photos' corners): a triangle there
        # cannot be measured; whether it is the triangle, only its corners' angles as
        # the image shows them can say
        if self._folds and not np.all(cam.in_field(cand.corners_px, FIELD_MARGIN_PX + self.scale)):
            seen_deg = np.sort(np.degrees(corner_angles(cand.corners_px)))
            if np.abs(seen_deg - np.sort(self.expected_angles_deg)).max() > FOLD_ANGLE_TOL_DEG:
                return "shape_mismatch"
            return "beyond_lens_model"
        if s.refine == "corners":
            mask = np.zeros(image.shape, np.uint8)
            cv2.fillPoly(mask, [np.rint(cand.contour_px).astype(np.int32)], 1)
            pts_px, cov, fit_contrast, outliers, level_mid = self._corners(image, cand, mask)
            if pts_px is None:
                return "corners_not_found"
            xy = cam.undistort(pts_px) * cam.fx
            return _Measured(xy, pts_px, cov, fit_contrast, outliers, 0.0, level_mid, None, None)
        shutter = RollingShutter(self.readout_ms, self.lever_c) if self.readout_ms else None
        fit = fit_edges(
            image,
            cand.corners_px,
            cam,
            sigma_floor=s.pixel_sigma_floor,
            # the first pass's window, 4 px or a shrunk pixel's width: a coarse corner
            # from the shrunk image may be half a shrunk pixel or more off the edge
            # (with 4 px at a scale of 8, two 1920x1080 cold frames in three needed a
            # third pass)
            half=max(4.0, float(self.scale)),
            width=self._last_width if cand.tracked else None,
            shutter=shutter,
            rate_c=rate_c,
            # the shutter gain, for the covariance of a rate not known yet or of the
            # readout's error (not computed when neither is there)
            gain=bool(self.readout_ms) and (rate_c is None or self.readout_sigma_ms > 0),
            tone=self._tone,
        )
        self._fit_width = fit.width
        if not fit.ok:
            return "edge_fit_failed"
        xy, cov = intersect(fit)
        # neighbouring edge points' errors correlated (a codec's, a camera's smoothing),
        # as the run's frames say: the lines are less precise than their points'
        # scatter alone says
        cov = cov * self.correlation.factor
        if s.refine == "pixels" and not self.inter_frame:
            # (through a codec that predicts frames from earlier ones its errors move
            # with the image: the pixel fit, at its bound on sensor noise, then puts rows
            # beyond 5 sigma even on a yaw sweep, where the edge lines, which learn the
            # codec's correlation, do not; visvec.pipeline.triangle.codec_advice,
            # benchmarks/triangle_compression.py)
            xy, cov, self._pixel = _pixel_fit(image, fit, xy, cov, cam, shutter, rate_c,
                                              self._blur, self._tone, self.inflation)  # fmt: skip
        level_mid = float(np.add.reduce(fit.mid_level)) / 3
        if self._tone is not None:
            # (the image's own level, which the checks compare with its pixels)
            level_mid = float(np.interp(level_mid, self._tone, np.arange(256.0)))
        return _Measured(
            xy, cam.distort(xy / cam.fx), cov, fit.contrast.min(), fit.outlier_fraction.max(),
            float(fit.vertex_gaps().max()), level_mid, fit.shutter_gain, fit.lag_sums,
        )  # fmt: skip

    def _named(self, m: _Measured) -> tuple[_Measured, np.ndarray, np.ndarray]:
        """Step 2: the vertices in the rig's order (the most acute first, then the
        rig's handedness), and the corner angles (deg) of the shape as a camera turned
        to face the triangle would see it: its image position then changes neither
        its angles nor its area (see facing), in the same order."""
        cam = self.rig.camera
        seen = facing(m.xy / cam.fx) * cam.fx
        ang = np.degrees(corner_angles(seen, side_lengths(seen)))
        apex = int(np.argmin(ang))
        perm = (apex, (apex + 1) % 3, (apex + 2) % 3)
        if np.sign(_signed_area(m.xy[list(perm)])) != self.expected_sign:
            perm = (apex, perm[2], perm[1])
        p, idx = list(perm), _PERM_INDEX[perm]
        gain = m.gain[idx] if m.gain is not None else None
        named = _Measured(m.xy[p], m.pts_px[p], m.cov[idx][:, idx], m.contrast, m.outliers,
                          m.vertex_gap, m.level_mid, gain, m.lags)  # fmt: skip
        return named, seen[p], ang[p]

    def _shape_reason(self, m: _Measured, seen: np.ndarray, angles_deg: np.ndarray) -> str | None:
        """Step 3: area, side ratios and apex angle against the known triangle, as a
        camera facing it would see them (``seen``, ``angles_deg``)."""
        sides = side_lengths(seen)
        if abs(abs(_signed_area(seen)) / self.expected_area - 1.0) > AREA_TOL:
            return "area_mismatch"
        if np.max(np.abs(sides / sides.sum() - self.expected_side_ratio)) > SIDE_RATIO_TOL:
            return "shape_mismatch"
        if abs(angles_deg[0] - self.expected_apex_deg) > APEX_ANGLE_TOL_DEG:
            return "angle_mismatch"
        return None

    def _usability_reason(self, image: np.ndarray, cand: Candidate, m: _Measured) -> str | None:
        """Step 4: it is the triangle's shape; can its image be trusted? In view,
        contrasted, unobstructed, not saturated, the whole region, a dark surround."""
        cam, s = self.rig.camera, self.rig.detect
        if cand.touches_border or not cam.in_image(m.pts_px, 1.0).all():
            return "partly_out_of_view"
        if m.contrast < s.min_contrast:
            return "low_contrast"
        if m.outliers > EDGE_OUTLIER_MAX:
            return "edge_obstructed"
        # a vertex whose edges stop short of it is extrapolated: something covers it
        area = abs(_signed_area(m.xy))
        if m.vertex_gap > max(VERTEX_GAP_MIN_PX, VERTEX_GAP_FRACTION * np.sqrt(area)):
            return "obstructed"
        return self._pixel_reason(image, m.pts_px, m.level_mid, s.min_contrast)

    def _shutter_consider(
        self, m: _Measured, rate_c: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Step 5: the covariance a rolling shutter leaves in the vertices (a consider
        term) and the shutter gain, for a rig with a readout time."""
        cam, gain = self.rig.camera, m.gain
        if rate_c is None and self.readout_ms != 0:
            # a rolling shutter whose rate is not known yet (first frame): the rows'
            # exposure times stay in the vertices, by up to the platform's fastest turn
            # (an estimated readout k +- s: E[k^2] = k^2 + s^2). With edge lines, the
            # sensitivity of their fit (the edges curve under a turn about the
            # boresight); with corners, the vertices' own
            if gain is None:
                gain = shutter_matrix(m.xy / cam.fx, m.pts_px[:, 1], cam, self.readout_ms,
                                      self.lever_c)  # fmt: skip
            consider = (gain @ self._cov_omega @ gain.T) * (
                1.0 + (self.readout_sigma_ms / self.readout_ms) ** 2
            )
            return consider, gain
        if rate_c is not None and self.readout_sigma_ms > 0:
            # taken out with a measured or estimated readout: what its sigma s leaves,
            # the shift of a readout error s at the rate omega (linear in the readout)
            if gain is None:
                g = shutter_shift(m.xy / cam.fx, m.pts_px[:, 1], cam, self.readout_sigma_ms,
                                  rate_c, self.lever_c)  # fmt: skip
            else:
                g = gain @ rate_c * (self.readout_sigma_ms / self.readout_ms)
            return np.outer(g, g), gain
        return None, gain

    def _partial_reason(self, image: np.ndarray) -> tuple[str, np.ndarray]:
        """Why no region had the triangle's shape, when one shows a corner of it (see
        partial_triangle): the corner's inside saturated, its edges too faint, the image
        border across the triangle, the lens model's field ending on it, or something
        over it; ("", empty) when none does."""
        s = self.rig.detect
        seen = partial_triangle(
            image,
            self.expected_angles_deg,
            self.expected_sides_px,
            scale=self.scale,
            min_step=0.5 * s.min_contrast,
        )
        if seen is None:
            return "", np.zeros((0, 2))
        outline = seen.outline_px
        if seen.inside_level >= SATURATED_LEVEL:
            reason = "overexposed"
        elif seen.step < s.min_contrast or (
            seen.edge_fraction < PARTIAL_EDGE_FRACTION and seen.step < 1.5 * s.min_contrast
        ):
            # faint edges, or marginal ones on a region joined to a brighter part of the
            # board (no step where the threshold crosses its lighting gradient): the
            # triangle stands out too little from the board's lighting
            reason = "low_contrast"
        elif seen.area_px < FOLD_AREA_FACTOR * self.expected_image_area and not np.all(
            self.rig.camera.in_field(outline, FIELD_MARGIN_PX + self.scale)
        ):
            # a region of about the triangle's size that reaches past the lens model's
            # field (see _verify); a far larger one is something else, or the triangle
            # joined to it
            reason = "beyond_lens_model"
        elif seen.area_px < (1.0 + AREA_TOL) * self.expected_image_area and not np.all(
            self.rig.camera.in_image(outline, self.scale)
        ):
            # a region no larger than the triangle that reaches the border (its outline
            # on the shrunk image's first or last pixels) is the triangle cut by it (a
            # larger one is the triangle joined to something)
            reason = "partly_out_of_view"
        else:
            reason = "obstructed"
        return reason, outline

    def _pixel_reason(
        self, image: np.ndarray, pts_px: np.ndarray, level: float, min_contrast: float
    ) -> str | None:
        """Step 4's checks on the pixels, in turn; the first one's reason that fails:

        - "overexposed": saturated pixels (>= 254) are more than SATURATED_MAX of the
          triangle shrunk by 20 % (the edges are clipped, their positions biased);
        - "obstructed": the pixels above the board/triangle mid-level ``level`` in the
          triangle grown by 20 % do not fill the fitted triangle's area to within
          REGION_AREA_TOL (an occluder over it, a light or clutter touching it);
        - "no_dark_surround": a band 8-25 % outside the triangle is not darker than the
          triangle shrunk by 25 % by half ``min_contrast`` (not checked when the band
          leaves the image).

        Each polygon is the triangle scaled about its centre, its vertices rounded to
        pixels, all in one box of the image (the largest polygon's, clamped to the
        image: a corner within half a pixel of the border floors to -1, which as a
        slice start is the last row or column)."""
        c = _centre(pts_px)
        scaled = c + (pts_px - c) * _CHECK_SCALES[:, None, None]
        outer = scaled[2]
        x0, y0 = np.maximum(np.floor(outer.min(axis=0)), 0).astype(int).tolist()
        x1, y1 = (np.ceil(outer.max(axis=0)).astype(int) + 1).tolist()
        roi = image[y0:y1, x0:x1]
        polys = (np.rint(scaled) - [x0, y0]).astype(np.int32)
        # saturated pixels inside: (roi >= 254) as a 0/1 image, counted under the mask
        # (none to count when the box holds none, as in most frames)
        if cv2.minMaxLoc(roi)[1] >= 254:
            mask = np.zeros(roi.shape, np.uint8)
            cv2.fillPoly(mask, [polys[0]], 1)
            n_in = cv2.countNonZero(mask)
            n_sat = cv2.countNonZero(cv2.threshold(roi, 253, 1, cv2.THRESH_BINARY)[1] & mask)
            if n_in and n_sat / n_in > SATURATED_MAX:
                return "overexposed"
        # pixels above the level inside the grown triangle
        mask = np.zeros(roi.shape, np.uint8)
        cv2.fillPoly(mask, [polys[1]], 1)
        above = cv2.threshold(roi, np.floor(level), 1, cv2.THRESH_BINARY)[1]
        bright = float(cv2.countNonZero(above & mask))
        area = abs(_signed_area(pts_px))
        if not abs(bright / max(area, 1.0) - 1.0) <= REGION_AREA_TOL:
            return "obstructed"
        if not self.rig.camera.in_image(outer).all():
            return None  # cannot tell near the image edge; other checks apply
        ring = np.zeros(roi.shape, np.uint8)
        cv2.fillPoly(ring, [polys[2]], 255)
        cv2.fillPoly(ring, [polys[3]], 0)
        inner = np.zeros(roi.shape, np.uint8)
        cv2.fillPoly(inner, [polys[4]], 255)
        if not _masked_mean(roi, inner) - _masked_mean(roi, ring) >= 0.5 * min_contrast:
            return "no_dark_surround"
        return None

    def _corners(self, image: np.ndarray, cand: Candidate, mask: np.ndarray):
        """The paper's corners: goodFeaturesToTrack on the region, then cornerSubPix."""
        cam = self.rig.camera
        m = cv2.dilate(mask, np.ones((9, 9), np.uint8))
        pts = cv2.goodFeaturesToTrack(image, 3, 0.01, self.min_corner_distance, mask=m, blockSize=5)
        if pts is None or len(pts) < 3:
            return None, None, 0.0, 1.0, 0.0
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 1e-3)
        win = max(2, int(round(3 * cam.width / 320)))
        pts = cv2.cornerSubPix(image, pts.astype(np.float32), (win, win), (-1, -1), crit)
        pts_px = pts.reshape(3, 2).astype(float)
        cov = np.eye(6) * CORNER_SIGMA_PX**2
        inside = image[mask.astype(bool)].astype(float)
        ring = image[(cv2.dilate(mask, np.ones((7, 7), np.uint8)) - mask).astype(bool)]
        contrast = float(np.median(inside) - np.median(ring)) if ring.size else 0.0
        mid = float(np.median(inside) + np.median(ring)) / 2 if ring.size else 0.0
        return pts_px, cov, contrast, 0.0, mid
