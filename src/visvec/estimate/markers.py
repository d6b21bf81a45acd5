"""The constrained 3-parameter attitude from identified LED markers (STASIS Sec. 2.4).

The camera is fixed in the lab and every marker turns about the centre of rotation, so
with R_CB = R_NC^T R_NB and t_c = -R_NC^T t_N a marker appears at P_C = R_CB M_B + t_c:
the rotation-only model of :mod:`visvec.estimate.rotation`. PnP solvers estimate six
parameters and discard the translation; this estimates the three that exist.
"""

from __future__ import annotations

import math

import numpy as np

from visvec.chi2 import ppf as chi2_ppf
from visvec.data import AttitudeSolution, Status
from visvec.estimate.rotation import fit_rotation
from visvec.geometry import lab_camera_offset_c
from visvec.rig import Rig

# a solution whose residuals exceed the centroid noise this improbably is refused
CHI2_REJECT_P = 1e-4


def chi2_limit(dof: int) -> float:
    return chi2_ppf(1.0 - CHI2_REJECT_P, dof)


def solve_markers(
    xy_n: np.ndarray,
    ids: np.ndarray,
    rig: Rig,
    sigma_px: float,
    R_nb_guess: np.ndarray | None = None,
    gate_px: float | None = None,
) -> AttitudeSolution:
    """Attitude from marker centroids.

    Parameters
    ----------
    xy_n : (K, 2) ndarray
        Undistorted normalised image coordinates of the identified markers.
    ids : (K,) int ndarray
        Their marker ids (rows of ``rig.target.points_b``).
    rig : Rig
    sigma_px : float
        1-sigma centroid noise (pixels) for the weights and the covariance.
    R_nb_guess : (3, 3) ndarray, optional
        Start (tracking); the closed form from the bearings otherwise.
    gate_px : float, optional
        The centroid noise the chi-square test refuses by (default ``sigma_px``): a
        pipeline that learned a narrower noise than the rig states still refuses only
        what the rig's would, so that a change of the noise (a refocus, vibration) is
        learned from the frames instead of refusing them all.
    """
    K = len(ids)
    if K < 3:
        return AttitudeSolution(Status.REJECTED, n_points=K, warnings=("too_few_markers",))
    X = rig.target.points_b[ids]
    t_c = lab_camera_offset_c(rig)
    s_n = sigma_px / rig.camera.fx
    W = 1.0 / s_n**2  # independent centroids with equal noise
    R0 = rig.R_nc.T @ R_nb_guess if R_nb_guess is not None else None
    fit = fit_rotation(t_c, X, xy_n, W, R0)
    if fit is None:
        return AttitudeSolution(Status.NOT_CONVERGED, n_points=K, warnings=("no_initial_solution",))
    rms_px = math.sqrt(fit.chi2 / (W * 2 * K)) * rig.camera.fx  # chi2 = W |r|^2
    if not fit.converged:
        return AttitudeSolution(
            Status.NOT_CONVERGED,
            rms_px=rms_px,
            n_points=K,
            iterations=fit.iterations,
            warnings=("not_converged",),
        )
    dof = 2 * K - 3
    cov_d = fit.cov_d * max(1.0, fit.chi2 / dof)
    R_cb = fit.R
    R_nb = rig.R_nc @ R_cb
    # R_NB_true = R_NC exp([d]x) R_CB = R_NB exp([R_CB^T d]x): body-axis error R_CB^T d
    cov_b = R_cb.T @ cov_d @ R_cb
    status, warnings = Status.OK, ()
    gate = sigma_px if gate_px is None else max(gate_px, sigma_px)
    if fit.chi2 * (sigma_px / gate) ** 2 > chi2_limit(dof):
        status, warnings = Status.REJECTED, ("inconsistent_geometry",)
    return AttitudeSolution(
        status,
        R_nb=R_nb,
        cov_b=cov_b,
        rms_px=rms_px,
        n_points=K,
        iterations=fit.iterations,
        warnings=warnings,
    )
