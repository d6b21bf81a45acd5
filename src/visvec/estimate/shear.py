"""An undeclared rolling shutter, seen in the residuals of a turning recording.

A webcam that reads its rows one after another while the platform turns sees each row
at its own instant: the triangle's vertices are those of the centre row's exposure
less A omega readout (:func:`visvec.shutter.shutter_matrix`). A rig that says so
(``[camera] readout_ms``) has the detector take it out; one that does not (0, a global
shutter) gets a yaw biased low at speed with a sigma that does not cover it
(benchmarks/out/triangle_rolling_shutter.json: at 20 deg/s and 640x480, 32 of 79 cold
rows beyond 3 sigma). Every frame ok, or refused only narrowly as a shear refuses it, whose
rate is known from the frame before it measures the readout from its own residuals
(:meth:`VertexResidual.explain`, least squares on the part of the shear no attitude or
height explains); summed over the run, a readout many sigma from zero says the camera
rolls. From then on the pipeline takes the running estimate out of the frames as if
the rig had declared it (its sigma in the vertices' covariance; rows warn
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
a turn through too little yaw to tell the two apart leaves the readout unsuspected.

A calibration error of the camera leaves a pattern fixed in the image instead: a
principal point a few px off (the tilt takes up its shift, a keystone is left) or an
aspect fy / fx off. On a one-way turn at a steady rate it turns with the yaw as a shear
does: a principal point 2 px off read as a 9 ms shutter at 20 deg/s (8 sigma, after
`calibrate zero-tilt`), 4 px off as 15 ms, and the correction then made the rows worse.
Only the rate tells them apart: a shear follows it (none when the platform holds
still, the other sign when it turns back), a calibration error does not. So the
principal point and the aspect are estimated beside the readout too, with priors of
a calibrated camera's errors (PRINCIPAL_POINT_PRIOR, ASPECT_PRIOR). A recording whose
rate changes (turning back and forth, slewing and holding) shows a 25 ms shutter
within about 70-90 frames; a steady one-way turn cannot tell it from a principal point
2 px off, and the readout stays unsuspected for most of it.

Each frame's residuals are judged with its height free (:meth:`VertexResidual.
unconstrained`): the height the pipeline carries from frame to frame lags the frame's
own, and its pull on the fit, which a principal point error makes turn with the yaw,
would read as a -8 ms shutter on an 8 s one-way turn (principal point 4 px off, before
zero-tilt) and hide the principal point itself (1.0 px read for 4). The price: the part
of a shear that looks like a change of height (a stretch along the columns) no longer
counts.

The evidence is believed only when it explains the residuals: after the readout and
the model errors are taken out, the chi-square per degree of freedom must be under
MAX_FIT_CHI2_DOF (a model error of another kind, an aspect error beyond its prior,
leaves them several times the noise), and the readout no longer than a frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visvec._kernels import readout as kernels
from visvec.camera import CameraModel
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
# the priors (1-sigma) of the camera's calibration errors: the principal point, as a
# share of the image width (5 px at 640), and the aspect fy / fx (relative); a
# judgement, wide enough for a camera calibrated with `calibrate camera` or one whose
# principal point is only roughly central
PRINCIPAL_POINT_PRIOR = 0.008
ASPECT_PRIOR = 0.003
# the run's closing note says the camera's aspect or principal point is off when its
# estimate is this many of its sigma and at least this far from 0 (the aspect relative,
# the principal point as a share of the image width: 2 px at 640); calibrate zero-tilt
# says so at the same least errors, with its own significance test
CAMERA_NOTE_SIGMAS = 5.0
ASPECT_MIN = 0.001
PRINCIPAL_POINT_MIN = 0.003
# the residuals' chi-square per degree of freedom, the readout and the model errors
# taken out, above which the evidence is not believed (an honest sigma gives 1; one a
# third short, as on a compressed recording's edges, 2.25)
MAX_FIT_CHI2_DOF = 3.0
# the evidence's parameters: the readout, the static pattern (6), the image-fixed
# errors (principal point x, y in px; aspect)
N_PARAMS = 10
# the camera's errors among them (principal point x, y; aspect)
CAMERA = slice(7, 10)
# the x and y rows of the three vertices in a (6,) pattern (x1, y1, x2, ...)
_X, _Y = np.arange(0, 6, 2), np.arange(1, 6, 2)


def _triangle_frame(xy: np.ndarray) -> np.ndarray:
    """(6, 6) M taking a residual pattern in the triangle's own frame (x along its
    centroid-to-apex direction, per vertex) to the image: a rotation per vertex
    (block-diagonal, written out: np.kron takes 20 us)."""
    v = xy[0] - (xy[0] + xy[1] + xy[2]) / 3.0
    c, s = v / np.hypot(*v)
    M = np.zeros((6, 6))
    M[_X, _X] = M[_Y, _Y] = c
    M[_X, _Y], M[_Y, _X] = -s, s
    return M


def model_error_design(xy: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(6, 9) the vertex patterns of the model errors: the static one (6, in the
    triangle's frame, :func:`_triangle_frame`) and the camera's: the vertices' shift
    (normalised) per px of principal point error in x and in y, and per unit of relative
    error in fy (the aspect): x = (u - cx) / fx and y = (v - cy) / fy move by 1 / fx,
    1 / fy and y."""
    D = np.zeros((6, 9))
    D[:, :6] = _triangle_frame(xy)
    D[_X, 6] = 1.0 / camera.fx
    D[_Y, 7] = 1.0 / camera.fy
    D[_Y, 8] = xy[:, 1]
    return D


def model_error_prior(camera: CameraModel, principal_point_px: float | None = None) -> np.ndarray:
    """(9,) the model errors' prior 1-sigma, in the units of model_error_design; the
    principal point's ``principal_point_px`` (default PRINCIPAL_POINT_PRIOR of the
    width)."""
    pp = PRINCIPAL_POINT_PRIOR * camera.width if principal_point_px is None else principal_point_px
    return np.r_[np.full(6, STATIC_PRIOR_PX / camera.fx), np.full(2, pp), ASPECT_PRIOR]


@dataclass
class ReadoutEvidence:
    """The run's readout (s), a static residual pattern (6, triangle frame) and the
    camera's principal point and aspect errors (3) estimated together from its frames'
    residuals: the normal equations ``info`` theta = ``rhs`` of
    :meth:`VertexResidual.explain` with the design [g, M, F], plus the model errors'
    priors (``prior_sigma``, their 9 1-sigma in the parameters' units), and what the
    fit leaves: the chi-square ``chi2`` before it and its degrees of freedom ``dof``.
    ``max_ms``: no readout is longer than a frame."""

    prior_sigma: np.ndarray
    max_ms: float = float("inf")
    info: np.ndarray = field(default_factory=lambda: np.zeros((N_PARAMS, N_PARAMS)))
    rhs: np.ndarray = field(default_factory=lambda: np.zeros(N_PARAMS))
    chi2: float = 0.0
    dof: float = 0.0
    n: int = 0
    # _posterior() since the last frame added
    _cached: tuple[np.ndarray, np.ndarray, float] | None = field(
        default=None, repr=False, init=False
    )
    # the priors' information, added to ``info`` (none on the readout)
    _prior_info: np.ndarray = field(repr=False, init=False)

    def __post_init__(self) -> None:
        self._prior_info = np.diag(np.r_[0.0, 1.0 / np.asarray(self.prior_sigma) ** 2])

    @classmethod
    def for_camera(
        cls,
        camera: CameraModel,
        fps: float = float("inf"),
        principal_point_px: float | None = None,
    ) -> ReadoutEvidence:
        """The evidence for a camera at ``fps`` frames per second whose principal point
        is known to ``principal_point_px`` (1-sigma; default: see model_error_prior)."""
        return cls(model_error_prior(camera, principal_point_px), 1000.0 / fps)

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
        # each frame judged with its height free: the height carried from the frames
        # before lags the frame's own, and its pull, which a principal point error makes
        # turn with the yaw, read as a -8 ms shutter (4 px off, before zero-tilt)
        # (VertexResidual.unconstrained and .explain in one, written for speed: with
        # C0 = (J^T W J)^-1 the weight the free fit leaves is P = W - W J C0 J^T W; the
        # free residual r0 has W r0 = P r and r0^T W r0 = r^T P r, so a = -D^T P r and
        # b = D^T P D for the design D)
        J, W, r = residual.J, residual.W, residual.r
        ka = applied_ms / 1000.0
        # one implementation (visvec._kernels.readout), compiled with the fast extra
        # (60 -> 10 us a frame); its arguments C-ordered float64 arrays
        c = np.ascontiguousarray
        lever_ = np.zeros(3) if lever is None else c(lever, float)
        ok, term = kernels.readout_frame(
            c(J, float), c(W, float), c(r, float), c(xy, float), c(rows, float),
            c(omega_c, float), lever_, float(camera.cy), float(camera.height),
            1.0 / camera.fx, 1.0 / camera.fy, ka, self.info, self.rhs,
        )  # fmt: skip
        if ok:  # (vertices that alone do not fix the parameters measure nothing here)
            self._added(float(term), J.shape[1])

    def _added(self, chi2_term: float, n_fitted: int) -> None:
        """A frame's chi-square term added; its degrees of freedom are 6 less the fit's
        ``n_fitted`` parameters (with no prior left, trace(C J^T W J) is their number)."""
        self.chi2 += chi2_term
        self.dof += 6.0 - n_fitted
        self.n += 1
        self._cached = None

    def _posterior(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(covariance, estimate) of all the parameters, the priors included, and the
        chi-square per degree of freedom they leave. Frames without a rate (the readout
        unseen: info[0, 0] = 0) leave the readout at 0."""
        if self._cached is None:
            # one implementation (visvec._kernels.readout), compiled with the fast extra
            self._cached = kernels.readout_solve(self.info, self._prior_info, self.rhs, self.chi2,
                                                 self.dof)  # fmt: skip
        return self._cached

    def _solve(self) -> tuple[float, float, float]:
        """(k, its 1-sigma, chi-square per degree of freedom left), k in s."""
        cov, theta, fit = self._posterior()
        return float(theta[0]), float(np.sqrt(cov[0, 0])), float(fit)

    def readout_ms(self) -> tuple[float, float]:
        """(estimate, 1-sigma) in ms, the model errors marginalised; NaN before any frame
        with a rate."""
        if self.info[0, 0] <= 0:
            return float("nan"), float("nan")
        k, s, _ = self._solve()
        return 1000.0 * k, 1000.0 * s

    def fit_chi2_per_dof(self) -> float:
        """The residuals' chi-square per degree of freedom once the readout and the
        model errors are taken out (about 1 when they explain the residuals)."""
        return self._solve()[2] if self.n else float("nan")

    def camera_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """(estimate, 1-sigma), each (3,), of the camera's calibration errors: the true
        principal point less the rig's (cx, cy in px), and the aspect error e (the frames
        see y = (v - cy) / fy as (1 + e) times the true one: the true fy is about
        fy (1 + e)); the readout and the other model errors marginalised. NaN before any
        frame."""
        if not self.n:
            return np.full(3, np.nan), np.full(3, np.nan)
        cov, theta, _ = self._posterior()
        return theta[CAMERA].copy(), np.sqrt(np.diag(cov)[CAMERA])

    def suspected(self) -> bool:
        """True when the frames say the camera rolls: the readout MIN_SIGMAS from zero
        and at least MIN_READOUT_MS, no longer than a frame, and the residuals explained
        (MAX_FIT_CHI2_DOF)."""
        k, s = self.readout_ms()
        return bool(
            np.isfinite(k)
            and max(MIN_SIGMAS * s, MIN_READOUT_MS) < abs(k) <= self.max_ms
            and self.fit_chi2_per_dof() <= MAX_FIT_CHI2_DOF
        )
