"""The triangle's attitude fit's kernels (visvec.estimate.rotation): the closed-form
rotation from three bearings and the Gauss-Newton with the target's height, written as
loops over the three points (the same steps as the numpy functions, tested equal);
compiled by Numba with the ``fast`` extra (visvec._kernels.jit)."""

from __future__ import annotations

import math

import numpy as np

from visvec._kernels.jit import kernel
from visvec.rotations import expmap_xyz


# ------------------------------------- the triangle's attitude (estimate.rotation)
def _closed_form_3(t_c, X, xy):
    """visvec.estimate.rotation.initial_rotation for three points: the closed-form
    rotation from three bearings (each branch of the depths in front, Procrustes by SVD;
    the better reprojecting of two). Returns (found, R)."""
    tt = t_c[0] * t_c[0] + t_c[1] * t_c[1] + t_c[2] * t_c[2]
    b = np.empty((3, 3))
    bt = np.empty(3)
    root = np.empty(3)
    for i in range(3):
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
        V = np.empty((3, 3))
        for k in range(3):
            for j in range(3):
                V[k, j] = lam[k] * b[k, j] - t_c[j]
        H = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                H[i, j] = X[0, i] * V[0, j] + X[1, i] * V[1, j] + X[2, i] * V[2, j]
        U, _, Vt = np.linalg.svd(H)
        d = np.linalg.det(U) * np.linalg.det(Vt)
        s = 1.0 if d == 0.0 else math.copysign(1.0, d)
        R = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                R[i, j] = Vt[0, i] * U[j, 0] + Vt[1, i] * U[j, 1] + s * Vt[2, i] * U[j, 2]
        cost = 0.0
        behind = False
        for k in range(3):
            p0 = R[0, 0] * X[k, 0] + R[0, 1] * X[k, 1] + R[0, 2] * X[k, 2] + t_c[0]
            p1 = R[1, 0] * X[k, 0] + R[1, 1] * X[k, 1] + R[1, 2] * X[k, 2] + t_c[1]
            p2 = R[2, 0] * X[k, 0] + R[2, 1] * X[k, 1] + R[2, 2] * X[k, 2] + t_c[2]
            if p2 <= 0:
                behind = True
            cost += (p0 / p2 - xy[k, 0]) ** 2 + (p1 / p2 - xy[k, 1]) ** 2
        if behind:
            continue
        n_found += 1
        if n_found == 1 or cost < best_cost:
            best, best_cost = R, cost
    return n_found > 0, best


def _gn_shift(R, t_c, X, xy, W, axis, mean, w_s, max_iterations, tol_rad2, tol_shift):
    """visvec.estimate.rotation._gauss_newton_shift, in (d, s): each iteration its
    residuals and Jacobian (residuals_and_jacobian_shift), the normal equations with the
    shift's prior, the step, R <- exp([d]x) R. Returns (R, s, r, J, N, iterations,
    converged), r after the last small step to second order in it."""
    n = X.shape[0]
    s = mean
    r = np.empty(2 * n)
    J = np.empty((2 * n, 4))
    converged = False
    it = 0
    while True:
        e0 = R[0, 0] * axis[0] + R[0, 1] * axis[1] + R[0, 2] * axis[2]
        e1 = R[1, 0] * axis[0] + R[1, 1] * axis[1] + R[1, 2] * axis[2]
        e2 = R[2, 0] * axis[0] + R[2, 1] * axis[1] + R[2, 2] * axis[2]
        for i in range(n):
            x0, x1, x2 = X[i, 0] + s * axis[0], X[i, 1] + s * axis[1], X[i, 2] + s * axis[2]
            qx = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2
            qy = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2
            qz = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2
            iz = 1.0 / (qz + t_c[2])
            u, v = (qx + t_c[0]) * iz, (qy + t_c[1]) * iz
            r[2 * i] = u - xy[i, 0]
            r[2 * i + 1] = v - xy[i, 1]
            J[2 * i, 0] = -qy * u * iz
            J[2 * i, 1] = (qz + qx * u) * iz
            J[2 * i, 2] = -qy * iz
            J[2 * i, 3] = (e0 - u * e2) * iz
            J[2 * i + 1, 0] = -(qy * v + qz) * iz
            J[2 * i + 1, 1] = qx * v * iz
            J[2 * i + 1, 2] = qx * iz
            J[2 * i + 1, 3] = (e1 - v * e2) * iz
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
            r = r + J @ step
            break
    return R, s, r, J, N, it, converged


_expmap = kernel(globals(), "_expmap", expmap_xyz)
gn_shift = kernel(globals(), "gn_shift", _gn_shift)
closed_form_3 = kernel(globals(), "closed_form_3", _closed_form_3)
