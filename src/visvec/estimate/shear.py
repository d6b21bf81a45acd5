"""An undeclared rolling shutter, seen in the residuals of a turning recording.

A webcam that reads its rows one after another while the platform turns sees each row
at its own instant: the triangle's vertices are those of the centre row's exposure
less A omega readout (:func:`visvec.detect.edges.shutter_matrix`). A rig that says so
(``[camera] readout_ms``) has the detector take it out; one that does not (0, a global
shutter) gets a yaw biased low at speed with a sigma that does not cover it
(benchmarks/RESULTS.md, rolling shutter: at 20 deg/s and 640x480, 31 of 78 cold rows
beyond 3 sigma). Every frame ok, or refused only narrowly as a shear refuses it, whose
rate is known from the frame before it measures the readout from its own residuals
(:meth:`VertexResidual.explain`, least squares on the part of the shear no attitude or
height explains); summed over the run, a readout many sigma from zero says the camera
rolls. From then on the pipeline takes the running estimate out of the frames as if
the rig had declared it (its sigma a consider covariance; rows warn
``rolling_shutter_estimated``), frames so corrected measure what is left, and the run's
closing note says to set it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.camera import CameraModel
from visvec.detect.edges import shutter_shift
from visvec.estimate.triangle_full import VertexResidual

# a rolling shutter is reported when the run's readout estimate is this many of its
# sigma from zero and at least this long (ms)
MIN_SIGMAS = 5.0
MIN_READOUT_MS = 2.0


@dataclass
class ReadoutEvidence:
    """The run's least-squares readout from its frames' residuals (sums a, b of
    :meth:`VertexResidual.explain`; the readout in seconds is a / b)."""

    a: float = 0.0
    b: float = 0.0
    n: int = 0

    def add(
        self,
        residual: VertexResidual,
        xy: np.ndarray,
        rows: np.ndarray,
        camera: CameraModel,
        omega_c: np.ndarray,
        lever: np.ndarray | None,
        applied_ms: float = 0.0,
    ) -> None:
        """One frame: its fit's residuals, its normalised vertices xy (3, 2) at image
        ``rows`` and the camera rate omega_c (rad/s, camera axes) at the time; its
        vertices already taken out with a readout of ``applied_ms`` (the residuals then
        measure what is left, k - applied)."""
        # seen = centre row - A omega readout: the pattern of a unit (1 s) readout
        g = -shutter_shift(xy, rows, camera, 1.0, omega_c, lever)
        a, b = residual.explain(g)
        self.a += a + b * applied_ms / 1000.0
        self.b += b
        self.n += 1

    def readout_ms(self) -> tuple[float, float]:
        """(estimate, 1-sigma) in ms; NaN before any frame with a rate."""
        if self.b <= 0:
            return float("nan"), float("nan")
        return 1000.0 * self.a / self.b, 1000.0 / np.sqrt(self.b)

    def suspected(self) -> bool:
        """True when the frames say the camera rolls (MIN_SIGMAS, MIN_READOUT_MS)."""
        k, s = self.readout_ms()
        return bool(np.isfinite(k) and abs(k) > max(MIN_SIGMAS * s, MIN_READOUT_MS))
