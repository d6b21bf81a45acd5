"""The markers target's pipeline (STASIS): LED spots -> identified markers -> attitude."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.data import Status
from visvec.detect.markers import VISIBLE_MARGIN_PX, MarkerIdentifier
from visvec.detect.spots import Spots, find_spots
from visvec.errors import ConfigError
from visvec.estimate.markers import solve_markers
from visvec.estimate.pnp import PNP_FLAGS, solve_pnp
from visvec.noise import LearnedNoise
from visvec.pipeline.base import AttitudePipeline, Pipeline
from visvec.rig import Rig

MARKER_METHODS = ("full", *PNP_FLAGS)


@dataclass(frozen=True)
class MarkerDetection:
    """Spots of one marker frame and their marker ids (-1: not a marker)."""

    spots: Spots
    ids: np.ndarray
    reason: str = ""


# merged spots (two LEDs, or an LED and a reflection) are longer than round ones
MAX_ELONGATION = 1.8
TRACK_WINDOW_PX = 24


class MarkerPipeline(AttitudePipeline["MarkerDetection"]):
    """LED markers seen by a camera fixed in the lab.

    Parameters
    ----------
    rig : Rig
        A markers rig.
    method : str
        'full' (the constrained 3-parameter solver; default) or a PnP baseline
        ('pnp-sqpnp', 'pnp-ippe', ...).
    """

    methods = MARKER_METHODS
    hints = {
        **Pipeline.hints,
        "not_identified": "the spots do not match the rig's marker layout: check [target] "
        "and the exposure (LEDs only)",
        "too_few_markers": "too few markers identified (LEDs hidden or out of view)",
        "inconsistent_geometry": "no attitude about the centre of rotation fits the markers: "
        "`visvec calibrate system`",
    }

    def __init__(self, rig: Rig, method: str = "full"):
        if rig.kind != "markers":
            raise ConfigError(f"MarkerPipeline needs a markers rig, not {rig.kind!r}")
        super().__init__(rig, method)
        # the centroid noise the rows' covariance and chi-square use, learned from the
        # fits' residuals with the rig's [detect] centroid_sigma_px as its prior; the
        # identification's gates keep the rig's value (a match, not a measurement)
        self.noise = LearnedNoise(rig.detect.centroid_sigma_px)
        self.identifier = MarkerIdentifier(rig, rig.detect.centroid_sigma_px)
        self.R_last: np.ndarray | None = None

    @property
    def sigma_px(self) -> float:
        """The centroid noise the next frame's covariance uses (px)."""
        return self.noise.sigma_px

    def reset(self) -> None:
        self.R_last = None

    def _spots(self, image: np.ndarray, R_pred: np.ndarray | None) -> Spots:
        d = self.rig.detect
        windows = None
        if R_pred is not None:
            uv = self._markers_px(R_pred)
            h = TRACK_WINDOW_PX
            windows = [(u - h, v - h, u + h + 1, v + h + 1) for u, v in uv if np.isfinite(u)]
        return find_spots(image, d.threshold, d.min_spot_px, d.max_spot_px, windows)

    def estimate(self, frame):
        image = frame.image
        warnings: list[str] = []
        tracking = self.R_last is not None
        spots = self._spots(image, self.R_last)
        ident = None
        for attempt in ("track", "search") if tracking else ("search",):
            if attempt == "search" and tracking:
                spots = self._spots(image, None)
            xy = self.rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
            # a spot beyond the lens model's field has no ray (nan): left out, as merged
            # spots are
            beyond = ~np.isfinite(xy).all(axis=1)
            good = (spots.elongation <= MAX_ELONGATION) & ~beyond
            ident = self.identifier.identify(xy[good], self.R_last if attempt == "track" else None)
            ids = np.full(len(spots), -1)
            ids[np.nonzero(good)[0]] = ident.ids
            if ident.R_nb is not None:
                break
        self.last_detection = MarkerDetection(spots, ids, ident.reason)
        if np.any(~good & ~beyond):
            warnings.append("merged_spot")
        if np.any(beyond):
            warnings.append("beyond_lens_model")
        if ident.R_nb is None:
            status = Status.NO_TARGET if len(spots) == 0 else Status.REJECTED
            return status, None, tuple(warnings + [ident.reason or "not_identified"])
        sel = ids >= 0
        n_vis = self._visible_count(ident.R_nb)
        if sel.sum() < n_vis:
            warnings.append("missing_markers")
        if np.any(~sel & good):
            warnings.append("extra_spots")
        if self.method == "full":
            # refused by the rig's noise or the learned, the wider (see solve_markers)
            gate = self.rig.detect.centroid_sigma_px
            sol = solve_markers(xy[sel], ids[sel], self.rig, self.sigma_px, ident.R_nb, gate)
        else:
            sol = solve_pnp(spots.centroids_px[sel], ids[sel], self.rig, self.method, self.sigma_px)
        if sol.status is Status.OK:
            self.R_last = sol.R_nb if self.method == "full" else ident.R_nb
            # its residuals measure the noise (3 parameters, or PnP's 6)
            self.noise.add(sol.n_points, sol.rms_px, 3 if self.method == "full" else 6)
        return sol.status, sol, tuple(warnings) + sol.warnings

    def _markers_px(self, R_nb: np.ndarray) -> np.ndarray:
        """(K, 2) the markers' pixels at attitude R_nb (nan past the lens model's field)."""
        return self.identifier.pixels(R_nb)

    def _visible_count(self, R_nb: np.ndarray) -> int:
        return int(np.sum(self.rig.camera.in_image(self._markers_px(R_nb), VISIBLE_MARGIN_PX)))
