"""Planar pose (x, y, heading) of a mock-up from identified ceiling lamps.

The table is level, so the body's attitude is a rotation by the heading psi about n3:
R_NB = Rz(psi), and the body origin is at p = (x, y, 0) in N. A lamp P_N appears at
P_C = R_BC^T (Rz(psi)^T (P_N - p) - t_B) (docs/reference.md, Conventions, with the body
origin moved to p). The LuVeX paper (Keldysh preprint 2011-24, Sec. 2) takes the position from the
identified triangles' agreement; here, beyond it, every matched lamp enters one
Gauss-Newton least-squares fit of the three parameters in pixels, with an analytic
Jacobian and the covariance sigma^2 (J^T J)^-1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from visvec.data import Status
from visvec.rig import Rig

MAX_ITERATIONS = 15
STEP_TOL = 1e-7  # mm and rad
# three identified lamps fix the pose with three degrees of freedom to spare
MIN_LAMPS = 3
OUTLIER_SIGMAS = 5.0
OUTLIER_FLOOR_PX = 1.5  # residuals under this are never outliers (model error of a real map)


@dataclass(frozen=True)
class PlanarSolution:
    """Pose ``pose`` = (x_mm, y_mm, heading_rad) with covariance ``cov`` (mm, rad);
    ``inliers`` marks the lamps kept in the fit."""

    status: Status
    pose: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    cov: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    rms_px: float = float("nan")
    n_points: int = 0
    inliers: np.ndarray | None = None
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def lamps_to_camera(rig: Rig, pose: np.ndarray, lamps_n: np.ndarray) -> np.ndarray:
    """Lamp positions (K, 3) in N seen from the camera at ``pose`` (x, y, heading rad)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = lamps_n - np.array([pose[0], pose[1], 0.0])
    p_b = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
    return (p_b - rig.t_b) @ rig.R_bc


def project_lamps(rig: Rig, pose: np.ndarray, lamps_n: np.ndarray) -> np.ndarray:
    """Normalised (undistorted) image coordinates of lamps; nan behind the camera."""
    p = lamps_to_camera(rig, pose, lamps_n)
    z = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
    return p[:, :2] / z[:, None]


# -e3 x P = S P: the heading's derivative of P_B = Rz(psi)^T (P_N - (x, y, 0))
_E3_CROSS = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def _residual_jacobian(rig: Rig, pose: np.ndarray, lamps_n: np.ndarray, xy_n: np.ndarray):
    """Residuals (2K,: projected minus seen, normalised) and their Jacobian (2K, 3) in
    (x, y, heading). P_B = Rz(psi)^T (P_N - (x, y, 0)), P_C = R_CB (P_B - t_B);
    dP_C/dx = -R_CB Rz^T e1, dP_C/dy = -R_CB Rz^T e2, dP_C/dpsi = R_CB (-e3 x P_B);
    through the projection u = X/Z: du = (dX - u dZ) / Z. As K x 3 products, a few
    numpy calls for all lamps."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R_cb = rig.R_bc.T
    p_b = (lamps_n - (pose[0], pose[1], 0.0)) @ Rz  # rows Rz^T (P_N - p)
    p_c = (p_b - rig.t_b) @ R_cb.T
    iz = 1.0 / p_c[:, 2]
    uv = p_c[:, :2] * iz[:, None]
    r = uv - xy_n
    # dP_C / d(x, y, psi), K x 3 (parameters) x 3 (camera axes)
    M = R_cb @ Rz.T
    d = np.empty((len(lamps_n), 3, 3))
    d[:, 0] = -M[:, 0]
    d[:, 1] = -M[:, 1]
    d[:, 2] = p_b @ (R_cb @ _E3_CROSS).T
    # (K, 2, 3): d(u, v)/d(x, y, psi)
    J = (d[:, :, :2] - d[:, :, 2:3] * uv[:, None, :]).transpose(0, 2, 1) * iz[:, None, None]
    return r.reshape(-1), J.reshape(-1, 3)


def _gauss_newton_step(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The least-squares step -(J^T J)^-1 J^T r through the 3x3 normal equations (a
    fifth of lstsq's time); lstsq where they are singular."""
    try:
        return np.linalg.solve(J.T @ J, -(J.T @ r))
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(J, -r, rcond=None)[0]


def solve_planar(
    xy_n: np.ndarray,
    lamps_n: np.ndarray,
    rig: Rig,
    sigma_px: float,
    pose0: np.ndarray,
    min_lamps: int = MIN_LAMPS,
) -> PlanarSolution:
    """Least-squares pose from lamps ``lamps_n`` (K, 3, mm in N) seen at ``xy_n`` (K, 2,
    undistorted normalised), starting from ``pose0`` (x, y, heading rad).

    Lamps whose residual exceeds 5 robust sigmas (and 1.5 px) are dropped once and the
    fit repeated (at least ``min_lamps`` must stay: two fix the pose, with one degree of
    freedom to check it, their distance); the covariance is sigma^2 (J^T J)^-1 with
    sigma the larger of the rig's centroid noise and the fit's own residual scatter.
    """
    f = float(rig.camera.fx)
    keep = np.ones(len(xy_n), bool)
    pose = np.asarray(pose0, dtype=float).copy()
    for rnd in range(2):
        if keep.sum() < min_lamps:
            return PlanarSolution(
                Status.REJECTED, n_points=int(keep.sum()), warnings=("too_few_lamps",)
            )
        P, xy = lamps_n[keep], xy_n[keep]
        converged = False
        for _ in range(MAX_ITERATIONS):
            r, J = _residual_jacobian(rig, pose, P, xy)
            if not np.all(np.isfinite(r)):
                return PlanarSolution(Status.NOT_CONVERGED, warnings=("lamp_behind_camera",))
            step = _gauss_newton_step(J, r)
            pose += step
            if abs(step[0]) + abs(step[1]) < STEP_TOL and abs(step[2]) < STEP_TOL:
                converged = True
                break
        if not converged:
            return PlanarSolution(
                Status.NOT_CONVERGED, n_points=len(P), warnings=("not_converged",)
            )
        r_all, J_all = _residual_jacobian(rig, pose, lamps_n, xy_n)
        e = np.hypot(*r_all.reshape(-1, 2).T) * f
        scale = np.median(e[keep]) / np.sqrt(np.log(4.0))  # Rayleigh median -> sigma
        bad = e > max(OUTLIER_SIGMAS * max(scale, sigma_px), OUTLIER_FLOOR_PX)
        if rnd == 1 or not np.any(bad & keep):
            break
        keep &= ~bad
    # the last round's residuals and Jacobian are at the final pose: the kept lamps' rows
    r = r_all.reshape(-1, 2)[keep].reshape(-1)
    J = J_all.reshape(-1, 2, 3)[keep].reshape(-1, 3)
    n = int(keep.sum())
    rms_px = float(np.sqrt(np.mean(r**2)) * f)
    dof = max(2 * n - 3, 1)
    chi2 = float(np.sum((r * f / sigma_px) ** 2))
    cov = np.linalg.inv(J.T @ J) * (sigma_px / f) ** 2 * max(1.0, chi2 / dof)
    pose[2] = (pose[2] + np.pi) % (2 * np.pi) - np.pi
    warnings = ("outlier_lamps",) if n < len(xy_n) else ()
    return PlanarSolution(Status.OK, pose, cov, rms_px, n, keep, warnings)
