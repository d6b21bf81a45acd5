"""The triangle's attitude fit's kernels (visvec.estimate.rotation): the closed-form
rotation from three bearings and the Gauss-Newton with the target's height, written as
loops over the three points (the same steps as the numpy functions, tested equal);
compiled by Numba with the ``fast`` extra (visvec._kernels.jit)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from visvec._kernels.jit import kernel
from visvec.rotations import expmap_xyz


class ShiftFit(NamedTuple):
    """The attitude fit's Gauss-Newton with the target's height (gn_shift).

    Attributes
    ----------
    R : ndarray, shape (3, 3)
        The rotation found.
    s : float
        The points' shift along the prior's axis (mm).
    r : ndarray, shape (2N,)
        The residuals (normalised image units, u and v interleaved), after the last
        small step to second order in it.
    J : ndarray, shape (2N, 4)
        Their Jacobian in (d, s) at the last iteration.
    N : ndarray, shape (4, 4)
        The normal matrix J^T W J with the shift's prior.
    iterations : int
        The Gauss-Newton steps taken.
    converged : bool
        Whether the last step was below the tolerances.
    """

    R: np.ndarray
    s: float
    r: np.ndarray
    J: np.ndarray
    N: np.ndarray
    iterations: int
    converged: bool


# ------------------------------------- the triangle's attitude (estimate.rotation)
def _closed_form(t_c, X, xy):
    """visvec.estimate.rotation.initial_rotation: the closed-form rotation from N
    bearings (each branch of the depths in front, Procrustes by SVD; the better
    reprojecting of two). Returns (found, R)."""
    n_pts = X.shape[0]
    tt = t_c[0] * t_c[0] + t_c[1] * t_c[1] + t_c[2] * t_c[2]
    b = np.empty((n_pts, 3))
    bt = np.empty(n_pts)
    root = np.empty(n_pts)
    for i in range(n_pts):
        n = math.sqrt(xy[i, 0] * xy[i, 0] + xy[i, 1] * xy[i, 1] + 1.0)
        b[i, 0], b[i, 1], b[i, 2] = xy[i, 0] / n, xy[i, 1] / n, 1.0 / n
        bt[i] = b[i, 0] * t_c[0] + b[i, 1] * t_c[1] + b[i, 2] * t_c[2]
        disc = bt[i] * bt[i] - tt + (X[i, 0] * X[i, 0] + X[i, 1] * X[i, 1] + X[i, 2] * X[i, 2])
        root[i] = math.sqrt(disc) if disc > 0.0 else 0.0
    best = np.eye(3)
    n_found = 0
    best_cost = np.inf
    for sign in (1.0, -1.0):
        lam = bt + sign * root
        if lam.min() <= 0:
            continue
        # Procrustes (Kabsch): R maps each X to lam b - t_c
        H = np.ascontiguousarray(X.T) @ (lam.reshape(n_pts, 1) * b - t_c)
        U, _, Vt = np.linalg.svd(H)
        d = np.linalg.det(U) * np.linalg.det(Vt)
        s = 1.0 if d == 0.0 else math.copysign(1.0, d)
        R = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                R[i, j] = Vt[0, i] * U[j, 0] + Vt[1, i] * U[j, 1] + s * Vt[2, i] * U[j, 2]
        p = X @ R.T + t_c
        behind = p[:, 2].min() <= 0
        cost = np.sum((p[:, 0] / p[:, 2] - xy[:, 0]) ** 2 + (p[:, 1] / p[:, 2] - xy[:, 1]) ** 2)
        if behind:
            continue
        n_found += 1
        if n_found == 1 or cost < best_cost:
            best, best_cost = R, cost
    return n_found > 0, best


def residuals_and_jacobian_shift(R, t_c, X, xy, axis):
    """The residuals (2N,) of the points X (N, 3) seen at normalised xy (N, 2), (u, v)
    interleaved, and their (2N, 4) Jacobian in the update R <- exp([d]x) R (columns d)
    and a shift s of every point along ``axis`` (column s): with q = R X, p = q + t_c,
    (u, v) = (p_x, p_y) / p_z,
    d(u)/dd = (-q_y u, q_z + q_x u, -q_y) / p_z, d(v)/dd = (-(q_y v + q_z), q_x v, q_x) / p_z
    and, e = R axis, d(u, v)/ds = (e_x - u e_z, e_y - v e_z) / p_z."""
    q = X @ R.T
    iz = 1.0 / (q[:, 2] + t_c[2])
    u = (q[:, 0] + t_c[0]) * iz
    v = (q[:, 1] + t_c[1]) * iz
    n = X.shape[0]
    r = np.empty(2 * n)
    r[0::2] = u - xy[:, 0]
    r[1::2] = v - xy[:, 1]
    qx, qy, qz = q[:, 0], q[:, 1], q[:, 2]
    e = R @ axis
    J = np.empty((n, 2, 4))
    J[:, 0, 0] = -qy * u * iz
    J[:, 0, 1] = (qz + qx * u) * iz
    J[:, 0, 2] = -qy * iz
    J[:, 0, 3] = (e[0] - u * e[2]) * iz
    J[:, 1, 0] = -(qy * v + qz) * iz
    J[:, 1, 1] = qx * v * iz
    J[:, 1, 2] = qx * iz
    J[:, 1, 3] = (e[1] - v * e[2]) * iz
    return r, J.reshape(2 * n, 4)


def _gn_shift(R, t_c, X, xy, W, axis, mean, w_s, max_iterations, tol_rad2, tol_shift):
    """visvec.estimate.rotation._fit_with_shift's Gauss-Newton in (d, s): each iteration
    its residuals and Jacobian (residuals_and_jacobian_shift), the normal equations with
    the shift's prior (s - mean)^2 w_s, the step, R <- exp([d]x) R. Returns (R, s, r, J,
    N, iterations, converged) as a ShiftFit."""
    s = mean
    converged = False
    it = 0
    while True:
        r, J = _residuals_and_jacobian_shift(R, t_c, X + s * axis, xy, axis)
        JtW = J.T @ W
        N = JtW @ J
        N[3, 3] += w_s
        if it == max_iterations:
            break
        it += 1
        g = JtW @ r
        g[3] += (s - mean) * w_s
        step = -np.linalg.solve(N, g)
        R = _expmap(step[0], step[1], step[2]) @ R  # Rodrigues: rotations.expmap_xyz
        s += step[3]
        if step[0] ** 2 + step[1] ** 2 + step[2] ** 2 < tol_rad2 and abs(step[3]) < tol_shift:
            converged = True
            # the residual after this last small step, to second order in it
            r = r + J @ step
            break
    return ShiftFit(R, s, r, J, N, it, converged)


_expmap = kernel(globals(), "_expmap", expmap_xyz)
_residuals_and_jacobian_shift = kernel(
    globals(), "_residuals_and_jacobian_shift", residuals_and_jacobian_shift
)
gn_shift = kernel(globals(), "gn_shift", _gn_shift)
closed_form = kernel(globals(), "closed_form", _closed_form)
