"""The star field's pipeline (Fasano et al.): two frames' stars -> matches -> body rate."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from visvec.data import Status
from visvec.detect.flow import MARGIN_PX, Matches, match_stars, signal
from visvec.detect.stars import (
    Residual,
    StarField,
    background,
    residual,
    segment_edges,
    stars_of,
)
from visvec.errors import ConfigError
from visvec.estimate.rate import MIN_STARS, RateSolution, estimate_rate, unit_vectors
from visvec.output import RateRow
from visvec.pipeline.base import Pipeline
from visvec.rig import Rig
from visvec.rotations import expmap

RATE_METHODS = ("poisson", "crassidis")
SATURATED_FRACTION = 0.02
BOOTSTRAP_STARS = 12
FULL_SEARCH_EVERY = 20
# a detection whose peak is less than 1 sigma over the mu + 3 sigma threshold is not
# matched once the rate is known: at 4 sigma, pure noise still lights about 40 pixels
# of a 1280 x 1024 frame (at 3 sigma about 1800), and such faint stars would weigh
# little anyway
MIN_PEAK_SNR = 1.0
BACKGROUND_EVERY = 5
FRAME_GAP_TOLERANCE = 1.5  # a frame later than this many periods is a jump


@dataclass(frozen=True)
class RateDetection:
    """Stars of the current frame and the matches from the previous one."""

    stars: StarField
    matches: Matches | None = None
    inliers: np.ndarray | None = None


@dataclass
class _PreviousFrame:
    time_s: float
    stars: StarField
    sig: np.ndarray


class RatePipeline(Pipeline["RateDetection", RateSolution]):
    """Angular rate of a star camera from consecutive frames (Fasano et al. 2013);
    ``method`` "poisson" (the paper, default) or "crassidis". One row per frame: the
    rate over the interval from the previous frame to this one.

    Beyond the paper, stars are tracked: once a rate is known, a frame's stars are the
    ones matched into it from the previous frame plus those found in the bands along
    the image edges where new stars enter; the whole frame is searched again every
    FULL_SEARCH_EVERY (20) frames, after any failure, or when few stars remain. This
    skips the connected-component labelling of most frames, the largest cost at
    1280 x 1024. The smooth background is re-estimated every BACKGROUND_EVERY (5)
    frames while tracking (every frame otherwise); noise and threshold every frame.

    Parameters
    ----------
    rig : Rig
        A starfield rig.
    method : str
        'poisson' (the paper; default) or 'crassidis'.
    """

    methods = RATE_METHODS
    hints = {
        **Pipeline.hints,
        "too_few_stars": "too few stars: a longer exposure, or a part of the sky with more",
        "saturated": "the frames saturate: a shorter exposure",
        "frame_jump": "frames not 1 / fps apart (dropped frames, or a folder without its times)",
        "rate_beyond_max": "a rate above [target] max_rate_dps",
    }
    row_type = RateRow

    def __init__(self, rig: Rig, method: str = "poisson"):
        if rig.kind != "starfield":
            raise ConfigError(f"RatePipeline needs a starfield rig, not {rig.kind!r}")
        super().__init__(rig, method)
        cam = rig.camera
        self.f_px = float(min(cam.fx, cam.fy))
        self.dt_nominal = 1.0 / rig.fps
        self.w_max = np.radians(rig.target.max_rate_dps)
        self.exposure_s = (rig.exposure_ms / 1000.0) if rig.exposure_ms else self.dt_nominal
        corner = np.hypot(cam.width, cam.height) / 2.0 / self.f_px
        self.flow_gain = self.f_px * (1.0 + corner**2)  # px per rad at the field's corner
        self.streak_px = self.w_max * self.exposure_s * self.flow_gain
        self.sigma_px = rig.detect.centroid_sigma_px
        self.prev: _PreviousFrame | None = None
        self.omega: np.ndarray | None = None
        self.since_full = 0
        self.bg: np.ndarray | None = None

    def reset(self) -> None:
        self.prev = None
        self.omega = None

    def after_failure(self) -> None:
        """:meth:`estimate` keeps the frame as the next one's predecessor when it can."""

    def _full_radius(self, dt: float) -> int:
        return int(np.ceil(self.w_max * dt * self.flow_gain)) + 2

    def _shifts(self, uv1: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
        """Predicted pixel displacement of each star after dt at rate omega."""
        cam = self.rig.camera
        u = unit_vectors(cam.undistort(uv1))
        p = u @ expmap(-omega * dt).T
        # a star beyond the lens model's field (nan): no prediction, searched where it was
        return np.nan_to_num(cam.project(p) - uv1)

    def _solve(self, m: Matches, dt: float, noise: tuple[float, float]) -> RateSolution:
        """The rate from matched stars; ``noise`` the pixel noise sigma of the first
        and second frame, which with each centroid's spread gives its variance."""
        cam = self.rig.camera
        xy1 = cam.undistort(m.uv1) if len(m) else np.zeros((0, 2))
        xy2 = cam.undistort(m.uv2) if len(m) else np.zeros((0, 2))
        var = (noise[0] ** 2 * m.spread1 + noise[1] ** 2 * m.spread2) / 2.0  # per axis
        return estimate_rate(xy1, xy2, dt, self.f_px, self.sigma_px, self.method, var)

    def _match(
        self, prev: _PreviousFrame, sig: np.ndarray, dt: float, noise: tuple[float, float]
    ) -> Matches:
        first = prev.stars
        n = len(first)
        zero = np.zeros((n, 2))
        omega = self.omega
        if omega is None:
            # bootstrap: the brightest stars searched over the whole range give a first rate
            bright = np.argsort(-first.flux)[:BOOTSTRAP_STARS]
            rad = np.full(n, self._full_radius(dt))
            m = self._with_rays(match_stars(first, prev.sig, sig, zero, rad, bright))
            if len(m) >= MIN_STARS:
                sol = self._solve(m, dt, noise)
                if sol.ok:
                    omega = sol.omega
            if omega is None:
                return self._with_rays(match_stars(first, prev.sig, sig, zero, rad))
        shifts = self._shifts(first.centroids_px, omega, dt)
        # detections whose peak is clearly above the noise (carried stars have an
        # infinite one: they were matched before)
        which = np.nonzero(first.peak_snr >= MIN_PEAK_SNR)[0]
        radius = np.full(n, self._radius(omega, dt))
        return self._with_rays(match_stars(first, prev.sig, sig, shifts, radius, which))

    def _with_rays(self, m: Matches) -> Matches:
        """The matches whose stars both have a ray: one beyond the lens model's field
        (CameraModel.field_r2) has none, and is left out."""
        cam = self.rig.camera
        if not cam.has_distortion or len(m) == 0:
            return m
        ok = (np.isfinite(cam.undistort(m.uv1)) & np.isfinite(cam.undistort(m.uv2))).all(axis=1)
        return m if ok.all() else Matches(*(getattr(m, f.name)[ok] for f in fields(Matches)))

    def _bands(self, dt: float) -> tuple[int, int, int, int]:
        """Widths (top, bottom, left, right) of the edge bands where this frame may hold
        stars that tracking did not carry: on each edge the largest inward flow (new
        stars), plus the search radius and margin (stars near an edge whose search
        window left the image), plus a star's extent (its streak and 8 px of blur)."""
        cam = self.rig.camera
        w, h = cam.width - 1.0, cam.height - 1.0
        s = np.linspace(0.0, 1.0, 9)
        z, one = np.zeros(9), np.ones(9)
        pts = np.vstack(
            [np.c_[s * w, z], np.c_[s * w, one * h], np.c_[z, s * h], np.c_[one * w, s * h]]
        )
        d = self._shifts(pts, self.omega, dt).reshape(4, 9, 2)
        inward = (d[0, :, 1].max(), -d[1, :, 1].min(), d[2, :, 0].max(), -d[3, :, 0].min())
        streak = np.linalg.norm(d, axis=2).max(axis=1) * self.exposure_s / dt
        extent = self._radius(self.omega, dt) + MARGIN_PX + 8 + 4
        return tuple(
            int(np.ceil(max(a, 0.0) + b + extent)) for a, b in zip(inward, streak, strict=True)
        )

    def _radius(self, omega: np.ndarray, dt: float) -> int:
        """Search half-width around a tracked star's predicted shift: the rate may have
        changed by 10 % (and 3 px) since it was measured."""
        return 3 + int(np.ceil(0.1 * np.linalg.norm(omega) * dt * self.flow_gain))

    def _carry(self, m: Matches, inliers: np.ndarray, res: Residual, dt: float) -> StarField:
        """This frame's stars when tracking: the matched ones, and new ones entering
        through the bands along the edges."""
        cents, boxes = [m.uv2[inliers]], [m.bbox2[inliers]]
        flux, area = [m.flux2[inliers]], [self.prev.stars.area_px[m.index[inliers]]]
        snr = [np.full(len(cents[0]), np.inf)]  # carried: matched whatever their peak
        seg = segment_edges(res, self._bands(dt), self.streak_px)
        if len(seg.cents):
            d = np.linalg.norm(seg.cents[:, None] - cents[0][None], axis=2)
            new = d.min(axis=1) > 4.0 if d.size else np.ones(len(seg.cents), bool)
            cents.append(seg.cents[new])
            boxes.append(seg.boxes[new])
            flux.append(seg.flux[new])
            area.append(seg.area[new])
            snr.append(seg.snr[new])
        c = np.vstack(cents)
        spread = np.zeros(len(c))
        spread[: len(boxes[0])] = m.spread2[inliers]
        return StarField(
            c, np.concatenate(flux), np.concatenate(area), np.concatenate(snr), True, "",
            res.sigma, 0.0, 1.0, threshold=res.threshold, signal=res.sig,
            bbox_px=np.vstack(boxes), windowed=np.arange(len(c)) < len(boxes[0]),
            spread=spread,
        )  # fmt: skip

    def estimate(self, frame):
        img = frame.image
        top = 255 if img.dtype == np.uint8 else int(np.iinfo(img.dtype).max)
        if img.max() >= top and np.count_nonzero(img >= top) > SATURATED_FRACTION * img.size:
            self.reset()
            return Status.REJECTED, None, ("saturated",)
        if self.bg is None or not self.since_full % BACKGROUND_EVERY or self.omega is None:
            self.bg = background(img)  # a smooth sky changes slowly: refreshed every 5
        res = residual(img, self.bg)
        sig = signal(res)
        prev = self.prev
        dt = frame.time_s - prev.time_s if prev is not None else 0.0
        jump = prev is not None and not 0.0 < dt <= FRAME_GAP_TOLERANCE * self.dt_nominal
        tracking = (
            prev is not None
            and not jump
            and self.omega is not None
            and self.since_full < FULL_SEARCH_EVERY
        )
        stars = None
        if not tracking:
            stars = stars_of(res, self.streak_px)
            self.since_full = 0
            self.last_detection = RateDetection(stars)
            if not stars.usable:
                self.reset()
                return Status.NO_TARGET, None, (stars.reason,)
        if prev is None or jump:
            self.prev, self.omega = _PreviousFrame(frame.time_s, stars, sig), None
            return (Status.NO_TARGET, None, ("first_frame",)) if not jump else (
                Status.REJECTED, None, ("frame_jump",))  # fmt: skip
        noise = (prev.stars.noise_sigma, res.sigma)
        m = self._match(prev, sig, dt, noise)
        sol = self._solve(m, dt, noise)
        if stars is None:
            if sol.ok:
                stars = self._carry(m, sol.inliers, res, dt)
                self.since_full += 1
            if stars is None or len(stars) < 4 * MIN_STARS:
                stars = stars_of(res, self.streak_px)
                self.since_full = 0
        self.last_detection = RateDetection(stars, m, sol.inliers)
        self.prev = _PreviousFrame(frame.time_s, stars, sig)
        if not sol.ok:
            self.omega = None
            return Status.REJECTED, sol, (sol.reason,)
        if np.linalg.norm(sol.omega) > 1.2 * self.w_max:
            self.omega = None
            return Status.REJECTED, sol, ("rate_beyond_max",)
        self.omega = sol.omega
        warnings = ("few_stars",) if sol.n_points < 3 * MIN_STARS else ()
        return Status.OK, sol, warnings

    def make_row(self, frame, status, sol, warnings, latency_ms):
        if status is not Status.OK or sol is None:
            n = sol.n_points if sol is not None else 0
            return RateRow(frame.index, frame.time_s, status, np.nan, n, latency_ms, warnings)
        return RateRow(
            frame.index,
            frame.time_s,
            status,
            sol.rms_px,
            sol.n_points,
            latency_ms,
            warnings,
            w_dps=np.degrees(sol.omega),
            sigma_dps=np.degrees(np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))),
            cov=np.degrees(np.degrees(sol.cov)),
        )
