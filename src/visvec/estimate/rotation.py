"""Rotation-only pose with a known translation: the core of the attitude estimators.

Both target kinds reduce to one model. A point X with known coordinates appears in the
camera at

    P_C = R X + t_c,                                                    (1)

with t_c known and only the rotation R unknown: for the triangle (camera on the
platform) R = R_CN, X = P_N, t_c = -R_BC^T t_B; for markers (camera in the lab)
R = R_CB = R_NC^T R_NB, X = M_B, t_c = -R_NC^T t_N. Because every point turns about the
one centre of rotation, three parameters describe the pose, not six (the premise of
the STASIS paper, Sec. 2.4). R is found in closed form from bearings (depths from
|P_C - t_c| = |X|, then an SVD Procrustes fit), then refined by Gauss-Newton on a
multiplicative update R <- exp([d]x) R minimising the Mahalanobis distance of the
undistorted normalised image points (STASIS Eqs. 13-17, with the analytic Jacobian of
Appendix A written for this update; d is the paper's minimal quaternion vector to
first order, d = 4 p for its Eqs. 14-15). The covariance of d is the inverse normal
matrix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visvec._kernels import rotation as kernels
from visvec._kernels.rotation import residuals_and_jacobian_shift
from visvec.rotations import expmap, expmap_xyz

MAX_ITERATIONS = 15
# Gauss-Newton converges about quadratically here (small residuals): after a step
# shorter than this the remaining error is of the order of its square, 1e-12 rad
STEP_TOL_RAD = 1e-6
# equal weights: the Jacobian is kept while the rotation stays within this of where it
# was taken (see _fit_equal_weights)
RELINEARISE_RAD = 1e-2


# with a ShiftPrior, its step must also fall under this (in the shift's units, mm)
STEP_TOL_SHIFT = 1e-3


@dataclass(frozen=True)
class RotationFit:
    """Result of :func:`fit_rotation`.

    R : (3, 3) rotation of Eq. (1); cov_d : (3, 3) covariance of the left increment d
    (rad^2, camera axes), not scaled by the residuals; chi2 : Mahalanobis residual (with
    a ShiftPrior, plus the prior's term); r : (2N,) final residuals (normalised units);
    iterations; converged. With a ShiftPrior also: shift, the estimated s; jac (2N, 4)
    and cov_p (4, 4), the final Jacobian in (d, s) and the covariance of (d, s).
    """

    R: np.ndarray
    cov_d: np.ndarray
    chi2: float
    r: np.ndarray
    iterations: int
    converged: bool
    shift: float = 0.0
    jac: np.ndarray | None = None
    cov_p: np.ndarray | None = None


@dataclass(frozen=True)
class ShiftPrior:
    """A fourth parameter for :func:`fit_rotation`: every point X moves by s along
    ``axis`` (X's frame), s with the Gaussian prior N(mean, sigma^2). For the triangle,
    the target's height above the centre of rotation, known from a tape measure to
    millimetres while its image pins it to a fraction of one."""

    axis: np.ndarray
    mean: float
    sigma: float


def residuals_and_jacobian(
    R_cn: np.ndarray, t_c: np.ndarray, p_n: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) of normalised projections and their Jacobian (2N, 3) with respect
    to a left rotation increment d (R_CN <- exp([d]x) R_CN).

    With q = R_CN P_N and p = q + t_c: dp/dd = -[q]x, and the pinhole projection
    (x/z, y/z) has d/dp = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]: the first three columns
    of visvec._kernels.rotation.residuals_and_jacobian_shift, the one place the
    equations are written.
    """
    r, J = residuals_and_jacobian_shift(R_cn, t_c, p_n, xy, _NO_AXIS)
    return r, np.ascontiguousarray(J[:, :3])


# no shift: the Jacobian's fourth column, which residuals_and_jacobian leaves out
_NO_AXIS = np.zeros(3)


def initial_rotation(t_c: np.ndarray, p_n: np.ndarray, xy: np.ndarray) -> np.ndarray | None:
    """Closed-form R from bearings, given the known offset t_c of Eq. (1).

    Each bearing b (unit vector of (x, y, 1)) meets P_C = lambda b with
    |lambda b - t_c| = |X|: lambda = b.t +- sqrt((b.t)^2 - |t|^2 + |X|^2). Then R maps X
    to lambda b - t_c for all points (Procrustes). When the points lie beyond the centre
    of rotation as seen from the camera (a ceiling target) only the + root is in front;
    when they lie on a sphere around it seen from afar (markers on top of the platform)
    both are, and the near one (-) is usually right: both branches are solved and the
    one that reprojects better is kept. A negative discriminant (a grazing ray, noise, or
    a geometry that is off) is clamped to zero: the start is then approximate and
    Gauss-Newton finishes the job.
    """
    # one implementation (visvec._kernels.rotation), compiled with the fast extra
    c = np.ascontiguousarray
    found, R = kernels.closed_form(c(t_c, float), c(p_n, float), c(xy, float))
    return R if found else None


def shift_jacobian(R: np.ndarray, t_c: np.ndarray, X: np.ndarray, axis: np.ndarray):
    """(2N,) derivative of the residuals of :func:`residuals_and_jacobian` with respect
    to a shift s of every point along ``axis``: dp/ds = R axis = e, and
    d(x/z, y/z) = ((e_x - u e_z) / z, (e_y - v e_z) / z): the fourth column of
    visvec._kernels.rotation.residuals_and_jacobian_shift."""
    return residuals_and_jacobian_shift(R, t_c, X, np.zeros((len(X), 2)), axis)[1][:, 3].copy()


def fit_rotation(
    t_c: np.ndarray,
    X: np.ndarray,
    xy: np.ndarray,
    W: np.ndarray,
    R0: np.ndarray | None = None,
    shift: ShiftPrior | None = None,
) -> RotationFit | None:
    """Gauss-Newton for R in Eq. (1) from points X (N, 3) seen at normalised xy (N, 2)
    with weight (inverse covariance) W (2N, 2N), or a scalar for equal independent
    weights (then :func:`_fit_equal_weights`). Starts from R0, or from the closed form.
    None when no start exists (a bearing that cannot reach its point).

    With ``shift`` (full W only), the points are X + s axis and s is estimated with its
    prior as a fourth parameter (maximum a posteriori: the prior is one more residual,
    (s - mean) / sigma); the rotation's covariance is then the marginal one, which
    carries the shift's uncertainty."""
    X0 = X if shift is None else X + shift.mean * shift.axis
    R = R0 if R0 is not None else initial_rotation(t_c, X0, xy)
    if R is None:
        return None
    if isinstance(W, float) or np.ndim(W) == 0:
        return _fit_equal_weights(t_c, X, xy, float(W), R)
    if shift is not None:
        return _fit_with_shift(t_c, X, xy, W, R, shift)
    converged = False
    it = 0
    while it < MAX_ITERATIONS:
        it += 1
        r, J = residuals_and_jacobian(R, t_c, X, xy)
        JtW = J.T @ W
        d = -np.linalg.solve(JtW @ J, JtW @ r)
        R = expmap(d) @ R
        if d @ d < STEP_TOL_RAD**2:
            converged = True
            # the residual after this last small step, to second order in it
            r = r + J @ d
            break
    else:
        r, J = residuals_and_jacobian(R, t_c, X, xy)
    N = J.T @ W @ J
    return RotationFit(R, np.linalg.inv(N), float(r @ W @ r), r, it, converged)


def _fit_with_shift(
    t_c: np.ndarray, X: np.ndarray, xy: np.ndarray, W: np.ndarray, R: np.ndarray, prior
) -> RotationFit:
    """:func:`fit_rotation` with the ShiftPrior ``prior``: Gauss-Newton in (d, s)
    (visvec._kernels.rotation.gn_shift, compiled with the fast extra)."""
    w_s = 1.0 / prior.sigma**2
    # one implementation (visvec._kernels.rotation), compiled with the fast extra; its
    # arguments C-ordered float64 arrays, the one signature the kernel is compiled for
    c = np.ascontiguousarray
    R, s, r, J, N, it, converged = kernels.gn_shift(
        c(R, float), c(t_c, float), c(X, float), c(xy, float), c(W, float),
        c(prior.axis, float), float(prior.mean), w_s, MAX_ITERATIONS, STEP_TOL_RAD**2,
        STEP_TOL_SHIFT,
    )  # fmt: skip
    cov_p = np.linalg.inv(N)
    chi2 = float(r @ W @ r) + (s - prior.mean) ** 2 * w_s
    return RotationFit(R, cov_p[:3, :3], chi2, r, it, converged, s, J, cov_p)


def _jacobian_table() -> np.ndarray:
    """(6, 9) constant T with J^T = T (F (x) G): the rows of
    :func:`residuals_and_jacobian` are bilinear in F = (qx, qy, qz) / z and
    G = (u, v, 1): d(u)/dd = (-qy u, qz + qx u, -qy) / z and
    d(v)/dd = (-(qy v + qz), qx v, qx) / z. Row 2 p + k is parameter p of coordinate
    k (u, v); column 3 i + j multiplies F_i G_j."""
    T = np.zeros((3, 2, 3, 3))
    x, y, z = 0, 1, 2  # F: qx/z, qy/z, qz/z
    u, v, one = 0, 1, 2  # G
    T[0, 0, y, u] = -1.0
    T[1, 0, z, one] = T[1, 0, x, u] = 1.0
    T[2, 0, y, one] = -1.0
    T[0, 1, y, v] = T[0, 1, z, one] = -1.0
    T[1, 1, x, v] = 1.0
    T[2, 1, x, one] = 1.0
    return T.reshape(6, 9)


_JACOBIAN_TABLE = _jacobian_table()


def _fit_equal_weights(
    t_c: np.ndarray, X: np.ndarray, xy: np.ndarray, W: float, R: np.ndarray
) -> RotationFit:
    """:func:`fit_rotation` for equal, independent weights (markers), written for speed:
    the model of Eq. (1) in a few whole-array operations, its Jacobian (that of
    :func:`residuals_and_jacobian`) in one product with a constant table, the 3x3 normal
    matrix inverted in closed form, and the Jacobian kept from one iteration to the next
    while the rotation has moved less than RELINEARISE_RAD from where it was taken (the
    chord form of Gauss-Newton). Its fixed point then solves J0^T r = 0 instead of
    J^T r = 0; with J0 - J of relative size 1e-2 at most and residuals of the noise's
    size, the two differ by about 1 % of the 1-sigma at worst, and by far less while
    tracking (a frame-to-frame step of 1e-3 rad). Residuals come all u, then all v."""
    N = len(X)
    Xh = np.empty((4, N))  # homogeneous points: P = [R | t_c] Xh
    Xh[:3] = X.T
    Xh[3] = 1.0
    M = np.empty((3, 4))
    M[:, 3] = t_c
    xy_t = xy.T
    G = np.empty((3, N))  # (u, v, 1) per point, for the Jacobian
    G[2] = 1.0
    moved = np.inf
    converged = False
    it = 0
    while it < MAX_ITERATIONS:
        it += 1
        M[:, :3] = R
        P = M @ Xh  # P_C of Eq. (1)
        uv = P[:2] / P[2]
        r = (uv - xy_t).ravel()
        if moved > RELINEARISE_RAD:
            F = (P - M[:, 3:]) / P[2]  # q / z with q = R X
            G[:2] = uv
            J = (_JACOBIAN_TABLE @ (F[:, None, :] * G[None, :, :]).reshape(9, N)).reshape(3, -1)
            Ninv = _inv_sym3(J @ J.T)
            K = Ninv @ J  # the step is -K r
            moved = 0.0
        dx, dy, dz = (K @ r).tolist()
        R = expmap_xyz(-dx, -dy, -dz) @ R
        step = math.sqrt(dx * dx + dy * dy + dz * dz)
        moved += step
        if step < STEP_TOL_RAD:
            # r is the residual before this last step, which moves it by J^T d: at the
            # minimum (J r = 0) that changes chi2 only to second order, 1e-3 of sigma^2
            converged = True
            break
    return RotationFit(R, Ninv / W, float(r @ r) * W, r, it, converged)


def _inv_sym3(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite 3x3 matrix by its adjugate (a few float
    operations instead of a LAPACK call, which costs more than the arithmetic here)."""
    (a, b, c), (_, d, e), (_, _, f) = A.tolist()
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    k = 1.0 / (a * A00 + b * A01 + c * A02)
    A00, A01, A02, A11, A12, A22 = A00 * k, A01 * k, A02 * k, A11 * k, A12 * k, A22 * k
    return np.array([[A00, A01, A02], [A01, A11, A12], [A02, A12, A22]])
