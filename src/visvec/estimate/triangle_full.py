"""The "full" triangle estimator: three attitude parameters from three vertices.

The camera rides on the platform, whose motion is a pure rotation about the lab
origin (the air bearing's centre of rotation). With t_c = -R_BC^T t_B and
R_CN = R_BC^T R_NB^T, a lab point appears at

    P_C = R_CN P_N + t_c,                                               (1)

so the camera-frame translation is known and only R_CN (three parameters) is unknown:
the lever arm of the camera about the centre of rotation is in the model, and there is
no small-angle approximation. R_CN is found in closed form from the three bearings
(depth from |P_C - t_c| = |P_N|, then an orthogonal Procrustes fit), then refined by
Gauss-Newton on the multiplicative update R_CN <- exp([d]x) R_CN, minimising the
Mahalanobis distance of the undistorted vertex positions with the detector's (6, 6)
covariance. The attitude covariance is the inverse normal matrix.
"""

from __future__ import annotations

import numpy as np

from visvec.data import AttitudeSolution, Detection, Status
from visvec.geometry import camera_offset_c
from visvec.rig import Rig
from visvec.rotations import expmap

MAX_ITERATIONS = 15
STEP_TOL_RAD = 1e-8  # 0.002 arcsec
# chi-square with 3 degrees of freedom (6 coordinates, 3 parameters): a detection that
# cannot be the rig's triangle under any attitude is refused (P(false refusal) = 1e-4).
CHI2_REJECT = 21.1
DOF = 3


def residuals_and_jacobian(
    R_cn: np.ndarray, t_c: np.ndarray, p_n: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) of normalised projections and their Jacobian (2N, 3) with respect
    to a left rotation increment d (R_CN <- exp([d]x) R_CN).

    With q = R_CN P_N and p = q + t_c: dp/dd = -[q]x, and the pinhole projection
    (x/z, y/z) has d/dp = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]].
    """
    q = p_n @ R_cn.T
    p = q + t_c
    iz = 1.0 / p[:, 2]
    proj = p[:, :2] * iz[:, None]
    r = (proj - xy).ravel()
    # row k of -(dproj/dp) [q]x is -a_k^T [q]x = (q x a_k)^T, with the rows of dproj/dp
    # a_u = (1, 0, -u) / z and a_v = (0, 1, -v) / z
    qx, qy, qz = q[:, 0], q[:, 1], q[:, 2]
    u, v = proj[:, 0], proj[:, 1]
    J = np.empty((len(p), 2, 3))
    J[:, 0, 0] = -qy * u * iz
    J[:, 0, 1] = (qz + qx * u) * iz
    J[:, 0, 2] = -qy * iz
    J[:, 1, 0] = -(qy * v + qz) * iz
    J[:, 1, 1] = qx * v * iz
    J[:, 1, 2] = qx * iz
    return r, J.reshape(-1, 3)


def initial_rotation(t_c: np.ndarray, p_n: np.ndarray, xy: np.ndarray) -> np.ndarray | None:
    """Closed-form R_CN from bearings, given the known camera offset t_c.

    Each bearing b (unit vector of (x, y, 1)) meets P_C = lambda b with
    |lambda b - t_c| = |P_N|, the positive root
    lambda = b.t + sqrt((b.t)^2 - |t|^2 + |P|^2); then R_CN maps P_N to
    lambda b - t_c for all three, solved by SVD (Kabsch, with the det < 0 branch
    corrected to a proper rotation).
    """
    b = np.column_stack([xy, np.ones(len(xy))])
    b /= np.linalg.norm(b, axis=1)[:, None]
    bt = b @ t_c
    disc = bt**2 - t_c @ t_c + np.einsum("ij,ij->i", p_n, p_n)
    if np.any(disc < 0):
        return None
    v = (bt + np.sqrt(disc))[:, None] * b - t_c
    H = p_n.T @ v
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def solve_full(det: Detection, rig: Rig, R_nb_guess: np.ndarray | None = None) -> AttitudeSolution:
    """Attitude from the three identified vertices of ``det``.

    Parameters
    ----------
    det : Detection
        With ``points_n`` (3, 2) and ``cov_n`` (6, 6).
    rig : Rig
    R_nb_guess : (3, 3) ndarray, optional
        Previous attitude (tracking); the closed form is used otherwise.

    Returns
    -------
    AttitudeSolution
        ``NOT_CONVERGED`` if Gauss-Newton does not settle, ``REJECTED`` (warning
        ``inconsistent_geometry``) if no attitude explains the vertices.
    """
    p_n = rig.target.vertices_mm
    t_c = camera_offset_c(rig)
    xy = det.points_n
    W = np.linalg.inv(det.cov_n)
    R_cn = None
    if R_nb_guess is not None:
        R_cn = rig.R_bc.T @ R_nb_guess.T
    if R_cn is None:
        R_cn = initial_rotation(t_c, p_n, xy)
        if R_cn is None:
            return AttitudeSolution(Status.NOT_CONVERGED, warnings=("no_initial_solution",))
    converged = False
    it = 0
    while it < MAX_ITERATIONS:
        it += 1
        r, J = residuals_and_jacobian(R_cn, t_c, p_n, xy)
        JtW = J.T @ W
        d = -np.linalg.solve(JtW @ J, JtW @ r)
        R_cn = expmap(d) @ R_cn
        if np.sqrt(d @ d) < STEP_TOL_RAD:
            converged = True
            break
    r, J = residuals_and_jacobian(R_cn, t_c, p_n, xy)
    rms_px = float(np.sqrt(np.mean(r**2)) * rig.camera.fx)
    if not converged:
        return AttitudeSolution(
            Status.NOT_CONVERGED,
            rms_px=rms_px,
            n_points=3,
            iterations=it,
            warnings=("not_converged",),
        )
    chi2 = float(r @ W @ r)
    N = J.T @ W @ J
    cov_d = np.linalg.inv(N) * max(1.0, chi2 / DOF)
    R_nb = R_cn.T @ rig.R_bc.T
    # R_nb_true = R_nb exp(-[R_BC d]x): body-axis error eps = -R_BC d
    cov_b = rig.R_bc @ cov_d @ rig.R_bc.T
    status, warnings = Status.OK, ()
    if chi2 > CHI2_REJECT:
        status, warnings = Status.REJECTED, ("inconsistent_geometry",)
    return AttitudeSolution(
        status, R_nb=R_nb, cov_b=cov_b, rms_px=rms_px, n_points=3, iterations=it, warnings=warnings
    )
