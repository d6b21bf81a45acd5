"""The ceiling lamps' pipeline (LuVeX): lamp spots -> identified lamps -> planar pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.chi2 import ppf as chi2_ppf
from visvec.data import Status
from visvec.detect.lamps import TRACK_GATE_PX, LampIdentifier
from visvec.detect.spots import Spots, find_spots
from visvec.errors import ConfigError
from visvec.estimate.planar import PlanarSolution, solve_planar
from visvec.lamps import Catalog
from visvec.noise import LearnedNoise
from visvec.output import PoseRow
from visvec.pipeline.base import Pipeline
from visvec.rig import Rig


@dataclass(frozen=True)
class LampDetection:
    """Spots of one lamp frame, their lamp ids (-1: none) and how they were found."""

    spots: Spots
    ids: np.ndarray
    mode: str = ""  # "track" or "lost_in_space"
    reason: str = ""
    votes: int = 0


EDGE_PX = 5.0  # lamp spots closer than this to the image border may be cut
# tracking goes on while at least MIN_TRACKED lamps and MIN_TRACKED_FRACTION of the spots
# match the map from the predicted pose
MIN_TRACKED = 5
MIN_TRACKED_FRACTION = 0.5
# through the dark: with fewer lamps than that and none identified lost in space, a
# prediction at most DARK_MAX_AGE_S old may still assign DARK_MIN or more (every spot),
# and the fitted pose must lie within a tracking gate of it
DARK_MIN = 2
DARK_MAX_AGE_S = 1.0
# lost-in-space fits of this many spots or fewer must explain them within the noise
FEW_CHECKED = 8
# ... at p = 0.001 (the chi-square limit of their 2n - 3 degrees of freedom)
CONSISTENT_P = 0.001


class LampPipeline(Pipeline["LampDetection", PlanarSolution]):
    """Position and heading of a mock-up from ceiling lamps (LuVeX, Keldysh preprint
    2011-24): spots, identification (tracking from the predicted pose, else the paper's
    Delaunay lookup), and a least-squares fit over every identified lamp.

    Parameters
    ----------
    rig : Rig
        A lamps rig (its map of the ceiling's lamps, mm).
    method : str
        'full' (the only one).
    """

    methods = ("full",)
    hints = {
        **Pipeline.hints,
        "no_lamps": "no bright spots: are the lamps on and in view?",
        "too_few_lamps": "too few lamps seen or identified",
        "ambiguous": "the lamps in view fit more than one place on the map, or fit it only "
        "loosely: too few to be sure",
        "no_catalogue_match": "the lamps' triangles match none of the lamp map's: check the "
        "map and the [camera] model",
        "no_consensus": "no pose agreed by the lamps' triangles: check the map and the "
        "[camera] model",
    }
    row_type = PoseRow

    def __init__(self, rig: Rig, method: str = "full", catalog: Catalog | None = None):
        if rig.kind != "lamps":
            raise ConfigError(f"LampPipeline needs a lamps rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.identifier = LampIdentifier(rig, catalog)
        # the centroid noise, learned from the fits' residuals; the rig's [detect]
        # centroid_sigma_px is its prior
        self.noise = LearnedNoise(rig.detect.centroid_sigma_px)
        self.track_state: tuple[float, np.ndarray, np.ndarray | None] | None = None

    def reset(self) -> None:
        self.track_state = None

    def _predict(self, t: float) -> np.ndarray | None:
        if self.track_state is None:
            return None
        t0, pose, vel = self.track_state
        return pose if vel is None else pose + vel * (t - t0)

    def _fit(self, xy: np.ndarray, ident, check: bool = False) -> PlanarSolution | None:
        """The pose fitted to the identified spots; with ``check``, None when it does
        not explain them within the noise (see _consistent)."""
        sel = ident.ids >= 0
        lamps = self.identifier.lamps[ident.ids[sel]]
        sol = solve_planar(xy[sel], lamps, self.rig, self.sigma_px, ident.pose)
        if sol.status is Status.OK:
            if check and not self._consistent(sol):
                return None
            self._learn_noise(sol)
        return sol

    def _through_the_dark(self, xy: np.ndarray, pred: np.ndarray | None, t: float):
        """(identification, solution) of a frame with too few lamps for tracking and
        lost in space, from the predicted pose (LampIdentifier.track_few), or None.
        Two identified lamps fix x, y and heading; their distance checks them."""
        if pred is None or t - self.track_state[0] > DARK_MAX_AGE_S:
            return None
        if not DARK_MIN <= len(xy) < MIN_TRACKED:
            return None
        ident = self.identifier.track_few(xy, pred)
        if ident.pose is None:
            return None
        lamps = self.identifier.lamps[ident.ids]
        sol = solve_planar(xy, lamps, self.rig, self.sigma_px, pred, min_lamps=DARK_MIN)
        if not sol.ok or (sol.inliers is not None and not sol.inliers.all()):
            return None
        # the lamps' distance is the one check two of them give (_consistent), and the
        # pose must lie near the prediction
        gate_mm = TRACK_GATE_PX * self.identifier.mm_per_px
        if not self._consistent(sol) or np.hypot(*(sol.pose[:2] - pred[:2])) > gate_mm:
            return None
        self._learn_noise(sol)
        return ident, sol

    def _learn_noise(self, sol: PlanarSolution) -> None:
        """The fit's residuals join the learned centroid noise (x, y and heading: 3
        parameters)."""
        self.noise.add(sol.n_points, sol.rms_px, 3)

    @property
    def sigma_px(self) -> float:
        """The centroid noise the next frame's covariance uses (px)."""
        return self.noise.sigma_px

    def _consistent(self, sol: PlanarSolution) -> bool:
        """Whether a fit of few lamps explains its spots within the noise (chi-square
        over its 2n - 3 degrees of freedom, p = 0.001). With few lamps an identification
        that is wrong (a stray spot completing a triangle that matches the map's
        somewhere else within its tolerance) still fits to a fraction of a pixel:
        only the learned noise tells it from the lamps' own scatter."""
        dof = 2 * sol.n_points - 3
        if dof <= 0:
            return True
        chi2 = 2 * sol.n_points * (sol.rms_px / self.sigma_px) ** 2
        return chi2 <= chi2_ppf(1.0 - CONSISTENT_P, dof)

    def estimate(self, frame):
        d = self.rig.detect
        spots = find_spots(frame.image, d.threshold, d.min_spot_px, d.max_spot_px)
        # a lamp cut by the image border has a biased centroid: left out (and one beyond
        # the lens model's field, which has no ray: nan)
        xy = self.rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
        keep = self.rig.camera.in_image(spots.centroids_px, EDGE_PX) & np.isfinite(xy).all(1)
        if not keep.all():
            spots = Spots(*(a[keep] for a in (spots.centroids_px, spots.flux, spots.area_px,
                                               spots.elongation, spots.saturated)),
                          spots.threshold)  # fmt: skip
            xy = xy[keep]
        self.last_detection = LampDetection(spots, np.full(len(spots), -1))
        if len(spots) == 0:
            return Status.NO_TARGET, None, ("no_lamps",)
        pred = self._predict(frame.time_s)
        sol, ident, mode = None, None, "track"
        if pred is not None:
            ident = self.identifier.track(xy, pred)
            if ident.n_identified >= max(MIN_TRACKED, MIN_TRACKED_FRACTION * len(xy)):
                sol = self._fit(xy, ident)
        if sol is None or not sol.ok:
            mode = "lost_in_space"
            ident = self.identifier.lost_in_space(xy)
            if ident.pose is None:
                dark = self._through_the_dark(xy, pred, frame.time_s)
                if dark is None:
                    self.last_detection = LampDetection(spots, ident.ids, mode, ident.reason)
                    return Status.REJECTED, None, (ident.reason,)
                mode, ident, sol = "dark", *dark
            else:
                sol = self._fit(xy, ident, check=len(xy) <= FEW_CHECKED)
                if sol is None:
                    self.last_detection = LampDetection(spots, ident.ids, mode, "ambiguous")
                    return Status.REJECTED, None, ("ambiguous",)
        ids = ident.ids.copy()
        if sol.inliers is not None:
            ids[np.nonzero(ids >= 0)[0][~sol.inliers]] = -1
        self.last_detection = LampDetection(spots, ids, mode, ident.reason, ident.votes)
        if not sol.ok:
            return sol.status, sol, sol.warnings
        warnings = list(sol.warnings)
        if np.sum(ids < 0) > 0:
            warnings.append("extra_spots")
        if mode == "dark":
            warnings.append("few_lamps")
        if self.track_state is not None and frame.time_s > self.track_state[0]:
            t0, p0, _ = self.track_state
            dp = sol.pose - p0
            dp[2] = (dp[2] + np.pi) % (2 * np.pi) - np.pi
            vel = dp / (frame.time_s - t0)
        else:
            vel = None
        self.track_state = (frame.time_s, sol.pose.copy(), vel)
        return Status.OK, sol, tuple(warnings)

    def make_row(self, frame, status, sol, warnings, latency_ms):
        if status is not Status.OK or sol is None:
            n = sol.n_points if sol is not None else 0
            return PoseRow(frame.index, frame.time_s, status, np.nan, n, latency_ms, warnings)
        sig = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))
        sig[2] = np.degrees(sig[2])
        pose = np.array([sol.pose[0], sol.pose[1], np.degrees(sol.pose[2])])
        to_deg = np.diag([1.0, 1.0, np.degrees(1.0)])  # (mm, mm, rad) -> (mm, mm, deg)
        return PoseRow(
            frame.index, frame.time_s, status, sol.rms_px, sol.n_points, latency_ms, warnings,
            pose=pose, sigma=sig, cov=to_deg @ sol.cov @ to_deg,
        )  # fmt: skip
