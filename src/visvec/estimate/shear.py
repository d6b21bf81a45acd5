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

A model error that is the same in every frame also leaves residuals: the target 15 mm
from where the rig file puts it (before `calibrate zero-tilt`), a board hung out of
level, a distortion residual. The fit's tilt takes up the shift, and what is left (a
keystone of a few hundredths of a pixel) is fixed in the triangle's own frame, where
a shear is not: a shear's pattern turns with the image rows as the yaw changes. Both
are estimated together (the static part, 6 numbers in the triangle's frame, with a
prior of STATIC_PRIOR_PX; without it a target 15 mm off read as a -4 ms shutter at 20
deg/s and -16 ms at 5 deg/s, 7 and 20 sigma), and the readout's sigma is its marginal:
a turn through too little yaw to tell the two apart leaves the readout unsuspected
(a pure yaw turn at 20 deg/s and 640x480 needs about 45 frames, 30 deg of yaw; one
that also tilts, fewer).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visvec.camera import CameraModel
from visvec.detect.edges import shutter_shift
from visvec.estimate.triangle_full import VertexResidual

# a rolling shutter is reported when the run's readout estimate is this many of its
# sigma from zero and at least this long (ms)
MIN_SIGMAS = 5.0
MIN_READOUT_MS = 2.0
# the prior sigma (px, each vertex coordinate in the triangle's frame) of a model error
# the same in every frame: a target 15 mm off leaves up to 0.07 px, 30 mm 0.15 px (at
# 5 deg/s that one still reads 3.6 sigma at most); wider, a real shutter takes longer
# to be told apart (0.1: 60 frames of a 20 deg/s turn, 0.03: 44 but a 30 mm error
# taken for a -34 ms shutter)
STATIC_PRIOR_PX = 0.05


def _triangle_frame(xy: np.ndarray) -> np.ndarray:
    """(6, 6) M taking a residual pattern in the triangle's own frame (x along its
    centroid-to-apex direction, per vertex) to the image: a rotation per vertex."""
    v = xy[0] - xy.mean(axis=0)
    c, s = v / np.hypot(*v)
    return np.kron(np.eye(3), np.array([[c, -s], [s, c]]))


@dataclass
class ReadoutEvidence:
    """The run's readout (s) and a static residual pattern (6, triangle frame) estimated
    together from its frames' residuals: the normal equations ``info`` theta = ``rhs``
    of :meth:`VertexResidual.explain` with the design [g, M], plus the static part's
    prior; ``static_sigma_n`` is STATIC_PRIOR_PX in normalised units (over fx)."""

    static_sigma_n: float
    info: np.ndarray = field(default_factory=lambda: np.zeros((7, 7)))
    rhs: np.ndarray = field(default_factory=lambda: np.zeros(7))
    n: int = 0
    # readout_ms() since the last frame added
    _cached: tuple[float, float] | None = field(default=None, repr=False, init=False)

    @classmethod
    def for_camera(cls, camera: CameraModel) -> ReadoutEvidence:
        return cls(STATIC_PRIOR_PX / camera.fx)

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
        measure what is left, k - applied, and k0 = applied is added back)."""
        # seen = centre row - A omega readout: the pattern of a unit (1 s) readout
        g = -shutter_shift(xy, rows, camera, 1.0, omega_c, lever)
        design = np.column_stack([g, _triangle_frame(xy)])
        a, b = residual.explain(design)
        self.info += b
        self.rhs += a + b[:, 0] * applied_ms / 1000.0
        self.n += 1
        self._cached = None

    def readout_ms(self) -> tuple[float, float]:
        """(estimate, 1-sigma) in ms, the static pattern marginalised; NaN before any
        frame with a rate."""
        if self._cached is not None:
            return self._cached
        if self.info[0, 0] <= 0:
            return float("nan"), float("nan")
        info = self.info.copy()
        info[1:, 1:] += np.eye(6) / self.static_sigma_n**2
        cov = np.linalg.inv(info)
        k = float(cov[0] @ self.rhs)
        self._cached = (1000.0 * k, 1000.0 * float(np.sqrt(cov[0, 0])))
        return self._cached

    def suspected(self) -> bool:
        """True when the frames say the camera rolls (MIN_SIGMAS, MIN_READOUT_MS)."""
        k, s = self.readout_ms()
        return bool(np.isfinite(k) and abs(k) > max(MIN_SIGMAS * s, MIN_READOUT_MS))
