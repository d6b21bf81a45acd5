"""An undeclared rolling shutter's evidence, frame by frame (visvec.estimate.shear),
as kernels compiled by Numba with the ``fast`` extra (visvec._kernels.jit); the same
steps as the numpy functions, tested equal."""

from __future__ import annotations

import math

import numpy as np

from visvec._kernels.jit import kernel


# ------------------------- an undeclared rolling shutter's evidence (estimate.shear)
def _readout_frame(J, W, r, xy, rows, omega, lever, cy, height, ifx, ify, ka, info, rhs):
    """One frame of visvec.estimate.shear.ReadoutEvidence.add: its design (-shutter_shift
    of a 1 s readout beside shear.model_error_design, written out for three vertices;
    tests/estimate/test_triangle.py checks it against the two) and what the free fit's weight
    P = W - W J C0 J^T W leaves of it, added to ``info`` and ``rhs`` in place. Returns
    (False, 0) when J^T W J is singular (nothing added), else (True, the frame's
    chi-square term)."""
    JW = J.T @ W
    try:
        C0 = np.linalg.inv(JW @ J)
    except Exception:  # noqa: BLE001 - numpy's LinAlgError, as add catches it
        return False, 0.0
    P = W - JW.T @ C0 @ JW
    n_par = info.shape[0]
    D = np.zeros((6, n_par))
    vx = xy[0, 0] - (xy[0, 0] + xy[1, 0] + xy[2, 0]) / 3.0
    vy = xy[0, 1] - (xy[0, 1] + xy[1, 1] + xy[2, 1]) / 3.0
    norm = math.hypot(vx, vy)
    c, s = vx / norm, vy / norm
    wx, wy, wz = omega[0], omega[1], omega[2]
    for i in range(3):
        x, y = xy[i, 0], xy[i, 1]
        t = (rows[i] - cy) / height
        ex, ey, ez = x + lever[0], y + lever[1], 1.0 + lever[2]
        ox, oy, oz = wy * ez - wz * ey, wz * ex - wx * ez, wx * ey - wy * ex
        D[2 * i, 0] = -(ox - x * oz) * t
        D[2 * i + 1, 0] = -(oy - y * oz) * t
        D[2 * i, 1 + 2 * i], D[2 * i, 2 + 2 * i] = c, -s
        D[2 * i + 1, 1 + 2 * i], D[2 * i + 1, 2 + 2 * i] = s, c
        D[2 * i, 7] = ifx
        D[2 * i + 1, 8], D[2 * i + 1, 9] = ify, y
    PD = P @ D
    a, b = -(PD.T @ r), D.T @ PD
    info += b
    rhs += a + b[:, 0] * ka
    return True, (r @ P) @ r + 2.0 * ka * a[0] + ka * ka * b[0, 0]


def _readout_solve(info, prior_info, rhs, chi2, dof):
    """visvec.estimate.shear.ReadoutEvidence._posterior: (covariance, estimate, the
    chi-square per degree of freedom they leave)."""
    A = info + prior_info
    if A[0, 0] <= 0:
        A[0, 0] = 1.0  # its row and rhs are 0: k = 0, and readout_ms() says NaN
    cov = np.linalg.inv(A)
    theta = cov @ rhs
    left = dof - np.sum(cov * info)
    return cov, theta, (chi2 - theta @ rhs) / max(left, 1.0)


readout_frame = kernel(globals(), "readout_frame", _readout_frame)
readout_solve = kernel(globals(), "readout_solve", _readout_solve)
