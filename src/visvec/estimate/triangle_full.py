"""The "full" triangle estimator: three attitude parameters from three vertices.

The camera rides on the platform, whose motion is a pure rotation about the lab
origin (the air bearing's centre of rotation). With t_c = -R_BC^T t_B and
R_CN = R_BC^T R_NB^T, a lab point appears at

    P_C = R_CN P_N + t_c,                                               (1)

so the camera-frame translation is known and only R_CN (three parameters) is unknown:
the lever arm of the camera about the centre of rotation is in the model, and there is
no small-angle approximation. The target's height is estimated beside it, with the rig
file's value as a Gaussian prior (``[target] height_sigma_mm``): the image pins the
triangle's size to a few hundredths of a percent, closer than a tape measures a
ceiling, and with the height held fixed a 5 mm error in it (0.25 %) made every frame
fail the chi-square test. With the camera on the rotation axis the height hardly
correlates with the attitude (the image scales about the target's own image point) and
costs the tilts about 1 %; a camera 250 mm off the axis sees the target 7 deg from that
point, and its tilts lose 1.4-1.7x in a frame alone. The height is a constant of the
lab, so the pipeline carries it from frame to frame (:class:`HeightTrack`: each frame's
estimate is the next one's prior), which gives those tilts back.

R_CN is found in closed form from the three bearings (depth from |P_C - t_c| = |P_N|,
then an orthogonal Procrustes fit), then refined by Gauss-Newton on the multiplicative
update R_CN <- exp([d]x) R_CN (and the height), minimising the Mahalanobis distance of
the undistorted vertex positions with the detector's (6, 6) covariance, to which any
error the detector could not take out is added (a rolling shutter's unknown rate, or
its readout's error: generalised least squares). The attitude covariance is the inverse
normal matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from visvec.data import AttitudeSolution, Detection, Status
from visvec.estimate.rotation import ShiftPrior, fit_rotation, residuals_and_jacobian
from visvec.geometry import camera_offset_c
from visvec.rig import Rig

# The vertices' chi-square has 3 degrees of freedom (6 coordinates, 3 parameters), or 2
# when a frame estimates the target's height (a 4th parameter) alone: the rig's prior,
# tens of millimetres where the image pins the height to a fraction of one, takes up
# almost nothing, so its term is judged on its own. A detection that cannot be the
# rig's triangle under any attitude is refused at P(false refusal) = 1e-4:
# chi-square(dof).ppf(1 - 1e-4).
CHI2_REJECT = {2: 18.42, 3: 21.11}
# and a height more than 3.9 of its prior's sigma from the rig's (chi-square(1) at 1e-4)
HEIGHT_REJECT = 15.14
# a height prior this tight (mm; the running estimate over the frames after one or two,
# or a rig's own) holds the height rather than leaving it to the image (a frame's own
# estimate is good to about 0.4 mm at 640x480): its term then joins the vertices'
# chi-square, of 3 degrees of freedom
HELD_HEIGHT_SIGMA_MM = 1.0


@dataclass(frozen=True)
class VertexResidual:
    """A fit's vertex residuals r = model - seen (6,) (normalised units), their weight W
    (6, 6), the Jacobian J (6, p) of the fitted parameters and their covariance C
    (p, p), prior included."""

    r: np.ndarray
    W: np.ndarray
    J: np.ndarray
    C: np.ndarray

    def explain(self, g: np.ndarray):
        """For vertices seen shifted by k g (g (6,), k unknown), the terms (a, b) of k's
        least-squares estimate from the residuals, summed over frames: k = sum a / sum b,
        variance 1 / sum b. The fit takes up the part of g its parameters can mimic and
        leaves r = -(I - J C J^T W)(n + k g) for noise n, so a = -g^T W r and
        b = g^T (W - W J C J^T W) g (the part of g no attitude or height explains).
        With g a (6, m) design of m patterns: the normal equations' a (m,) and b (m, m)."""
        Wg = self.W @ g
        JWg = self.J.T @ Wg
        a, b = -(Wg.T @ self.r), g.T @ Wg - JWg.T @ self.C @ JWg
        return (float(a), float(b)) if g.ndim == 1 else (a, b)

    def unconstrained(self) -> VertexResidual:
        """The same fit with its parameters' prior taken away, to first order: C0 =
        (J^T W J)^-1 and r0 = (I - J C0 J^T W) r. A prior whose mean is not the frame's
        own (the height carried from the frames before) pulls the fit and leaves its
        pull in r; r0 holds only what no parameter value explains."""
        JW = self.J.T @ self.W
        C0 = np.linalg.inv(JW @ self.J)
        return VertexResidual(self.r - self.J @ (C0 @ (JW @ self.r)), self.W, self.J, C0)


# The height's random walk from one frame to the next (mm, 1-sigma per frame): the running
# estimate's memory. With a frame's own estimate good to r (0.4 mm at 640x480, about
# 1.2 at 320x240 on the rig files' camera), the prior settles at about sqrt(q r) (0.09
# and 0.15 mm) and forgets over about r / q frames (20 and 60): a lens that slowly
# refocuses (its focal length looks like a height) is followed, a sudden change is
# caught by the fallback (see HeightTrack).
HEIGHT_DRIFT_MM = 0.02


@dataclass
class HeightTrack:
    """The target's height against the rig file's as a constant of the lab, estimated
    over the frames rather than in each: a scalar Kalman filter on a random walk.

    The ok frames' fits are its updates (a frame's MAP estimate with the track's
    prediction as its prior is the filter's posterior: mean ``height_mm``, variance
    ``height_sigma_mm`` squared); the prediction adds HEIGHT_DRIFT_MM^2 and never
    exceeds the rig's prior. A camera off the rotation axis sees the target away from
    the zenith point about which a height change scales the image, so a frame's own
    height correlates with its tilts (1.4-1.7x their sigma for 250 mm off the axis at
    2 m); a height known over many frames gives them back. The track survives lost
    frames (the lab did not change); a frame its prediction refuses but the rig's
    prior passes restarts it (see TrianglePipeline).
    """

    rig_sigma_mm: float
    mean_mm: float = 0.0
    var_mm2: float = field(init=False)
    n: int = 0  # ok frames since the (re)start

    def __post_init__(self) -> None:
        self.restart()

    def restart(self) -> None:
        """Back to the rig file's prior."""
        self.mean_mm, self.var_mm2, self.n = 0.0, self.rig_sigma_mm**2, 0

    def prior(self) -> tuple[float, float]:
        """(mean_mm, sigma_mm): the prediction for the next frame."""
        var = min(self.var_mm2 + HEIGHT_DRIFT_MM**2, self.rig_sigma_mm**2)
        return self.mean_mm, float(np.sqrt(var))

    def update(self, sol: AttitudeSolution) -> None:
        """Take an ok frame's estimate, fitted with :meth:`prior`."""
        if np.isfinite(sol.height_sigma_mm) and sol.height_sigma_mm > 0:
            self.mean_mm, self.var_mm2 = sol.height_mm, sol.height_sigma_mm**2
            self.n += 1


def solve_full(
    det: Detection,
    rig: Rig,
    R_nb_guess: np.ndarray | None = None,
    height_prior: tuple[float, float] | None = None,
) -> AttitudeSolution:
    """Attitude from the three identified vertices of ``det``.

    Parameters
    ----------
    det : Detection
        With ``points_n`` (3, 2) and ``cov_n`` (6, 6).
    rig : Rig
    R_nb_guess : (3, 3) ndarray, optional
        Previous attitude (tracking); the closed form is used otherwise.
    height_prior : (mean_mm, sigma_mm), optional
        The prior of the target's height against the rig file's: the running estimate
        over the frames (:class:`HeightTrack`); the rig's (0, ``height_sigma_mm``)
        otherwise. Ignored when the rig holds the height (``height_sigma_mm = 0``).

    Returns
    -------
    AttitudeSolution
        ``NOT_CONVERGED`` if Gauss-Newton does not settle, ``REJECTED`` (warning
        ``inconsistent_geometry``) if no attitude explains the vertices.
    """
    p_n = rig.target.vertices_mm
    t_c = camera_offset_c(rig)
    # an error the detector could not take out (a rolling shutter's unknown rate, or the
    # readout's error at a known rate), passed as a covariance C of the vertices: the
    # fit weighs them with cov_n + C, the generalised least squares that marginalises
    # that error's zero-mean prior. (Fitting with cov_n alone and adding C's share to the
    # covariance afterwards, Schmidt's consider form, left the residual of the part of
    # C the fit could not absorb to the chi-square: a first frame turning at 10 deg/s
    # read chi-square 17-25 for 2 degrees of freedom, and a third of them were refused.)
    cov_n = det.cov_n if det.consider_n is None else det.cov_n + det.consider_n
    W = np.linalg.inv(cov_n)
    R0 = rig.R_bc.T @ R_nb_guess.T if R_nb_guess is not None else None
    # the target's height as a fourth parameter, with the rig's value as its prior (or
    # the running estimate's)
    height = None
    if rig.target.height_sigma_mm > 0:
        mean, sigma = height_prior or (0.0, rig.target.height_sigma_mm)
        height = ShiftPrior(np.array([0.0, 0.0, 1.0]), mean, sigma)
    fit = fit_rotation(t_c, p_n, det.points_n, W, R0, height)
    if fit is None:
        return AttitudeSolution(Status.NOT_CONVERGED, warnings=("no_initial_solution",))
    rms_px = float(np.sqrt(np.mean(fit.r**2)) * rig.camera.fx)
    if not fit.converged:
        return AttitudeSolution(
            Status.NOT_CONVERGED,
            rms_px=rms_px,
            n_points=3,
            iterations=fit.iterations,
            warnings=("not_converged",),
        )
    held = height is None or height.sigma <= HELD_HEIGHT_SIGMA_MM
    dof = 3 if held else 2
    # the height prior's term: in the chi-square when it holds the height, judged on
    # its own when loose (HEIGHT_REJECT)
    prior = 0.0 if height is None else (fit.shift - height.mean) ** 2 / height.sigma**2
    chi2 = fit.chi2 - (0.0 if held else prior)
    # the fit's Jacobian in its parameters (d, and s with the height) and their covariance
    if fit.jac is not None:
        residual = VertexResidual(fit.r, W, fit.jac, fit.cov_p)
    else:
        _, J = residuals_and_jacobian(fit.R, t_c, p_n, det.points_n)
        residual = VertexResidual(fit.r, W, J, fit.cov_d)
    scale = max(1.0, chi2 / dof)
    cov_d = fit.cov_d * scale
    height_sigma = float("nan")
    if fit.cov_p is not None:
        height_sigma = float(np.sqrt(fit.cov_p[3, 3] * scale))
    R_cn = fit.R
    it = fit.iterations
    R_nb = R_cn.T @ rig.R_bc.T
    # R_nb_true = R_nb exp(-[R_BC d]x): body-axis error eps = -R_BC d
    cov_b = rig.R_bc @ cov_d @ rig.R_bc.T
    # the zero-tilt calibration's own error, the same in every row (Rig.ZeroTilt)
    cal = rig.zero_tilt.cov_body(
        R_nb, float(rig.target.vertices_mm[:, 2].mean()), float(rig.t_b[2])
    )
    if cal is not None:
        cov_b = cov_b + cal
    status, warnings = Status.OK, ()
    if chi2 > CHI2_REJECT[dof] or (not held and prior > HEIGHT_REJECT):
        status, warnings = Status.REJECTED, ("inconsistent_geometry",)
    return AttitudeSolution(
        status,
        R_nb=R_nb,
        cov_b=cov_b,
        rms_px=rms_px,
        n_points=3,
        iterations=it,
        warnings=warnings,
        chi2=chi2,
        height_mm=fit.shift,
        height_sigma_mm=height_sigma,
        dof=dof,
        residual=residual,
    )
