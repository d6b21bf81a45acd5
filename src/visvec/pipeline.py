"""Pipelines: frame -> detection -> attitude -> row, one per target kind.

:class:`Pipeline` holds what every kind shares (frame checks, the safety net for bugs,
the physically-possible tilt check, latency); a subclass turns one good image into an
attitude solution. :func:`make_pipeline` picks the class for a rig.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from visvec.data import AttitudeSolution, Frame, Status
from visvec.detect import TriangleDetector
from visvec.detect.markers import MarkerIdentifier
from visvec.detect.spots import Spots, find_spots
from visvec.errors import ConfigError
from visvec.estimate import ESTIMATORS
from visvec.estimate.markers import solve_markers
from visvec.estimate.pnp import PNP_FLAGS, solve_pnp
from visvec.output import AttitudeRow, Row, attitude_row
from visvec.rig import Rig

TRIANGLE_METHODS = tuple(ESTIMATORS)
MARKER_METHODS = ("full", *PNP_FLAGS)
METHODS = tuple(dict.fromkeys(TRIANGLE_METHODS + MARKER_METHODS))


class Pipeline:
    """Shared frame loop of every target kind. Subclasses implement :meth:`estimate`
    and :meth:`make_row`."""

    methods: tuple[str, ...] = ()
    row_type: type[Row] = Row

    def __init__(self, rig: Rig, method: str = "full"):
        if method not in self.methods:
            raise ConfigError(
                f"method = {method!r} for a {rig.kind} rig: expected one of {list(self.methods)}"
            )
        self.rig = rig
        self.method = method
        self.last_detection: object | None = None
        self.last_solution: AttitudeSolution | None = None
        self.last_error = ""

    def check_frame(self, frame: Frame) -> str:
        """Why a frame cannot be used at all ("" if it can)."""
        if frame.image is None:
            return frame.error or "unreadable frame"
        img = frame.image
        cam = self.rig.camera
        if img.ndim != 2 or img.size == 0:
            return f"{frame.name}: expected a grey image, got shape {img.shape}"
        if img.shape != (cam.height, cam.width):
            return (
                f"{frame.name}: image is {img.shape[1]}x{img.shape[0]}, expected "
                f"{cam.width}x{cam.height} (the rig's camera)"
            )
        return ""

    def reset(self) -> None:
        """Forget the previous frame."""

    def estimate(self, frame: Frame) -> tuple[Status, object | None, tuple[str, ...]]:
        """Status, solution (or None) and warnings of one readable frame."""
        raise NotImplementedError

    def make_row(
        self,
        frame: Frame,
        status: Status,
        sol: object | None,
        warnings: tuple[str, ...],
        latency_ms: float,
    ) -> Row:
        raise NotImplementedError

    def check_solution(
        self, status: Status, sol: object | None, warnings: tuple[str, ...]
    ) -> tuple[Status, tuple[str, ...]]:
        """A last physical check of an ok solution (none by default)."""
        return status, warnings

    def process(self, frame: Frame, t_in: float | None = None) -> Row:
        """The row of one frame; never raises on frame content."""
        t_in = time.perf_counter() if t_in is None else t_in
        self.last_detection, self.last_solution, self.last_error = None, None, ""
        if self.check_frame(frame):
            self.reset()
            return self.make_row(frame, Status.READ_ERROR, None, ("read_error",), _ms(t_in))
        try:
            status, sol, warnings = self.estimate(frame)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not end the run
            # a bug met on this frame's content: refuse the frame, keep the run going,
            # and keep the message for the caller to report
            self.last_error = f"{type(exc).__name__}: {exc}"
            self.reset()
            return self.make_row(frame, Status.REJECTED, None, ("internal_error",), _ms(t_in))
        self.last_solution = sol
        if status is Status.OK and sol is not None:
            status, warnings = self.check_solution(status, sol, warnings)
        if status is not Status.OK:
            self.reset()
        return self.make_row(frame, status, sol, warnings, _ms(t_in))

    def run(
        self, frames: Iterable[Frame], on_frame: Callable[[Frame, Row], None] | None = None
    ) -> Iterator[Row]:
        """Rows of all frames, lazily; ``on_frame`` sees each frame with its row."""
        for frame in frames:
            row = self.process(frame)
            if on_frame is not None:
                on_frame(frame, row)
            yield row


class AttitudePipeline(Pipeline):
    """Attitude rows (triangle, markers), with the physically-possible tilt check."""

    row_type = AttitudeRow

    def make_row(self, frame, status, sol, warnings, latency_ms):
        return attitude_row(frame.index, frame.time_s, sol, status, warnings, latency_ms)

    def check_solution(self, status, sol, warnings):
        tilt = np.degrees(np.arccos(np.clip(sol.R_nb[2, 2], -1.0, 1.0)))
        if tilt > self.rig.max_tilt_deg:
            return Status.REJECTED, warnings + ("impossible_tilt",)
        return status, warnings


class TrianglePipeline(AttitudePipeline):
    """The triangle target; ``method`` "full" (default) or "paper"."""

    methods = TRIANGLE_METHODS

    def __init__(self, rig: Rig, method: str = "full"):
        if rig.kind != "triangle":
            raise ConfigError(f"TrianglePipeline needs a triangle rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.detector = TriangleDetector(rig)
        self.solve = ESTIMATORS[method]

    def reset(self) -> None:
        self.detector.reset()

    def estimate(self, frame):
        det = self.detector.detect(frame.image)
        self.last_detection = det
        if det.status is not Status.OK:
            return det.status, None, det.warnings
        sol = self.solve(det, self.rig)
        return sol.status, sol, det.warnings + sol.warnings


@dataclass(frozen=True)
class MarkerDetection:
    """Spots of one marker frame and their marker ids (-1: not a marker)."""

    spots: Spots
    ids: np.ndarray
    reason: str = ""


# merged spots (two LEDs, or an LED and a reflection) are longer than round ones
MAX_ELONGATION = 1.8
TRACK_WINDOW_PX = 24


class MarkerPipeline(AttitudePipeline):
    """LED markers seen by a camera fixed in the lab; ``method`` "full" (the constrained
    3-parameter solver) or a PnP baseline ("pnp-sqpnp", "pnp-ippe", ...)."""

    methods = MARKER_METHODS

    def __init__(self, rig: Rig, method: str = "full"):
        if rig.kind != "markers":
            raise ConfigError(f"MarkerPipeline needs a markers rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.sigma_px = rig.detect.centroid_sigma_px
        self.identifier = MarkerIdentifier(rig, self.sigma_px)
        self.R_last: np.ndarray | None = None

    def reset(self) -> None:
        self.R_last = None

    def _spots(self, image: np.ndarray, R_pred: np.ndarray | None) -> Spots:
        d = self.rig.detect
        windows = None
        if R_pred is not None:
            uv = self.rig.camera.distort(self.identifier.project(R_pred))
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
            good = spots.elongation <= MAX_ELONGATION
            xy = self.rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
            ident = self.identifier.identify(xy[good], self.R_last if attempt == "track" else None)
            ids = np.full(len(spots), -1)
            ids[np.nonzero(good)[0]] = ident.ids
            if ident.R_nb is not None:
                break
        self.last_detection = MarkerDetection(spots, ids, ident.reason)
        if np.any(~good):
            warnings.append("merged_spot")
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
            sol = solve_markers(xy[sel], ids[sel], self.rig, self.sigma_px, ident.R_nb)
        else:
            sol = solve_pnp(spots.centroids_px[sel], ids[sel], self.rig, self.method, self.sigma_px)
        if sol.status is Status.OK:
            self.R_last = sol.R_nb if self.method == "full" else ident.R_nb
        return sol.status, sol, tuple(warnings) + sol.warnings

    def _visible_count(self, R_nb: np.ndarray) -> int:
        uv = self.rig.camera.distort(self.identifier.project(R_nb))
        return int(np.sum(self.rig.camera.in_image(uv, 3.0)))


def make_pipeline(rig: Rig, method: str = "full") -> Pipeline:
    """The pipeline for the rig's target kind."""
    if rig.kind == "triangle":
        return TrianglePipeline(rig, method)
    if rig.kind == "markers":
        return MarkerPipeline(rig, method)
    raise ConfigError(f"target kind {rig.kind!r} has no pipeline in this version")


def _ms(t_in: float) -> float:
    return (time.perf_counter() - t_in) * 1000.0
