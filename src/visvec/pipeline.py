"""The triangle pipeline: frame -> detection -> attitude -> row."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from visvec.data import AttitudeSolution, Detection, Frame, Status
from visvec.detect import TriangleDetector
from visvec.errors import ConfigError
from visvec.estimate import ESTIMATORS
from visvec.output import AttitudeRow, attitude_row
from visvec.rig import Rig

METHODS = tuple(ESTIMATORS)


class TrianglePipeline:
    """Turns frames of the rig's camera into attitude rows.

    Parameters
    ----------
    rig : Rig
    method : "full" (default) or "paper"
    """

    def __init__(self, rig: Rig, method: str = "full"):
        if method not in ESTIMATORS:
            raise ConfigError(f"method = {method!r}: expected one of {list(ESTIMATORS)}")
        self.rig = rig
        self.method = method
        self.detector = TriangleDetector(rig)
        self.solve = ESTIMATORS[method]
        self.last_detection: Detection | None = None
        self.last_error = ""
        self.last_solution: AttitudeSolution | None = None

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

    def process(self, frame: Frame, t_in: float | None = None) -> AttitudeRow:
        """The row of one frame; never raises on frame content."""
        t_in = time.perf_counter() if t_in is None else t_in
        self.last_detection, self.last_solution = None, None
        problem = self.check_frame(frame)
        if problem:
            self.detector.reset()
            return attitude_row(
                frame.index, frame.time_s, None, Status.READ_ERROR, ("read_error",), _ms(t_in)
            )
        self.last_error = ""
        try:
            det = self.detector.detect(frame.image)
            self.last_detection = det
            if det.status is not Status.OK:
                return attitude_row(
                    frame.index, frame.time_s, None, det.status, det.warnings, _ms(t_in)
                )
            sol = self.solve(det, self.rig)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not end the run
            # a bug met on this frame's content: refuse the frame, keep the run going, and
            # keep the message for the caller to report
            self.last_error = f"{type(exc).__name__}: {exc}"
            self.detector.reset()
            return attitude_row(
                frame.index, frame.time_s, None, Status.REJECTED, ("internal_error",), _ms(t_in)
            )
        self.last_solution = sol
        warnings = det.warnings + sol.warnings
        status = sol.status
        if status is Status.OK:
            tilt = np.degrees(np.arccos(np.clip(sol.R_nb[2, 2], -1.0, 1.0)))
            if tilt > self.rig.max_tilt_deg:
                status, warnings = Status.REJECTED, warnings + ("impossible_tilt",)
        if status is not Status.OK:
            self.detector.reset()
        return attitude_row(frame.index, frame.time_s, sol, status, warnings, _ms(t_in))

    def run(
        self, frames: Iterable[Frame], on_frame: Callable[[Frame, AttitudeRow], None] | None = None
    ) -> Iterator[AttitudeRow]:
        """Rows of all frames, lazily; ``on_frame`` sees each frame with its row."""
        for frame in frames:
            row = self.process(frame)
            if on_frame is not None:
                on_frame(frame, row)
            yield row


def _ms(t_in: float) -> float:
    return (time.perf_counter() - t_in) * 1000.0
