"""PnP baselines on the same marker detections: OpenCV's solvePnP estimates six pose
parameters (rotation and translation of the pattern) and the translation is thrown
away, as the systems the STASIS paper compares against do (its Sec. 3.5)."""

from __future__ import annotations

import cv2
import numpy as np

from visvec.data import AttitudeSolution, Status
from visvec.rig import Rig

PNP_FLAGS = {
    "pnp-iterative": cv2.SOLVEPNP_ITERATIVE,
    "pnp-p3p": cv2.SOLVEPNP_P3P,
    "pnp-ap3p": cv2.SOLVEPNP_AP3P,
    "pnp-ippe": cv2.SOLVEPNP_IPPE,
    "pnp-sqpnp": cv2.SOLVEPNP_SQPNP,
}


def _spread_four(X: np.ndarray) -> np.ndarray:
    """Indices of 4 well-spread points (P3P and AP3P take exactly four)."""
    c = X.mean(axis=0)
    i0 = int(np.argmax(np.linalg.norm(X - c, axis=1)))
    chosen = [i0]
    for _ in range(3):
        d = np.min(np.linalg.norm(X[:, None] - X[chosen][None], axis=2), axis=1)
        chosen.append(int(np.argmax(d)))
    return np.array(chosen)


def _onto_plane(X: np.ndarray) -> np.ndarray:
    """The points projected onto their least-squares plane. IPPE solves for a planar
    target and OpenCV refuses points off a plane; a calibrated layout of coplanar
    boards carries each LED's small estimated offset out of it (hundredths of a mm),
    which IPPE, by its model, cannot use."""
    c = X.mean(axis=0)
    n = np.linalg.svd(X - c)[2][2]
    return X - np.outer((X - c) @ n, n)


def solve_pnp(
    uv_px: np.ndarray, ids: np.ndarray, rig: Rig, method: str, sigma_px: float
) -> AttitudeSolution:
    """R_NB from solvePnP with the given method; the rotation covariance comes from the
    six-parameter Jacobian at the solution (what a 6-DoF solver can know)."""
    X = rig.target.points_b[ids].astype(np.float64)
    uv = uv_px.astype(np.float64)
    if method in ("pnp-p3p", "pnp-ap3p"):
        sel = _spread_four(X)
        X4, uv4 = X[sel], uv[sel]
    elif method == "pnp-ippe":
        X4, uv4 = _onto_plane(X), uv
    else:
        X4, uv4 = X, uv
    if len(X4) < 4:
        return AttitudeSolution(Status.REJECTED, n_points=len(X), warnings=("too_few_markers",))
    try:
        ok, rvec, tvec = cv2.solvePnP(
            X4, uv4, rig.camera.K, rig.camera.dist, flags=PNP_FLAGS[method]
        )
    except cv2.error:
        ok = False
    if not ok:
        return AttitudeSolution(Status.NOT_CONVERGED, n_points=len(X), warnings=("pnp_failed",))
    R_cb, _ = cv2.Rodrigues(rvec)
    R_nb = rig.R_nc @ R_cb
    proj, jac = cv2.projectPoints(X, rvec, tvec, rig.camera.K, rig.camera.dist)
    r = (proj.reshape(-1, 2) - uv).ravel()
    # jac columns: d/d(rvec, tvec, f, c, dist); the rotation block is in rvec terms,
    # near the solution a left increment of R_CB to first order
    J6 = jac[:, :6]
    cov6 = np.linalg.pinv(J6.T @ J6) * sigma_px**2
    # rvec perturbation -> camera-axis rotation increment (first order, exact enough)
    Jr = _rvec_to_left(rvec.ravel())
    cov_d = Jr @ cov6[:3, :3] @ Jr.T
    cov_b = R_cb.T @ cov_d @ R_cb
    return AttitudeSolution(
        Status.OK, R_nb=R_nb, cov_b=cov_b, rms_px=float(np.sqrt(np.mean(r**2))), n_points=len(X)
    )


def _rvec_to_left(rvec: np.ndarray) -> np.ndarray:
    """(3, 3) d(left increment)/d(rvec): numerical, from exp(d) R(rvec) = R(rvec + drvec)."""
    R0, _ = cv2.Rodrigues(rvec)
    J = np.zeros((3, 3))
    h = 1e-7
    for k in range(3):
        dr = np.zeros(3)
        dr[k] = h
        R1, _ = cv2.Rodrigues(rvec + dr)
        D = R1 @ R0.T
        J[:, k] = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / (2 * h)
    return J
