"""The "paper" estimator, as published (kept for comparison).

Virginia Tech Visual Vector Sensor (Sec. IV.E-G): the rotation angle from the
centroid-to-acute-vertex vector against the camera axes (Eq. 1); the centroid's offset
from the calibrated zero-tilt centroid (Eqs. 2-3), rotated by the rotation angle into
the triangle-aligned e frame (Eq. 4); the offsets turned into lengths with the pixel /
length ratio at the target and into tilt angles about n1 and n2 with the distance to the
target (Eqs. 5-6, right triangles). Small-angle geometry; the camera's lever arm and the
lens distortion are ignored, as in the paper. Distances come from the rig file.
The uncertainty adds the method's model error on each frame (its difference from the
full camera model on the same vertices) to the propagated vertex noise, and a frame the
full model refuses (no attitude explains the vertices) is refused here too.
"""

from __future__ import annotations

import numpy as np

from visvec.data import AttitudeSolution, Detection, Status
from visvec.estimate.triangle_full import solve_full
from visvec.geometry import project_target
from visvec.rig import Rig
from visvec.rotations import euler_rates_from_body, matrix_to_euler, rot_x, rot_y, rot_z


def zero_tilt_centroid(rig: Rig) -> np.ndarray:
    """(2,) calibrated zero-tilt centroid, or the rig's prediction without calibration."""
    if rig.zero_tilt.centroid_px is not None:
        return rig.zero_tilt.centroid_px
    return project_target(rig, np.eye(3)).mean(axis=0)


def paper_attitude(points_px: np.ndarray, rig: Rig, z0: np.ndarray) -> np.ndarray:
    """R_nb from the three vertices (3, 2) in pixels by the paper's equations."""
    cam = rig.camera
    c = points_px.mean(axis=0)
    # Eq. (1): rotation angle from the centroid -> acute vertex vector (camera axes
    # taken into the body frame through the mount rotation)
    d = points_px[0] - c
    v_b = rig.R_bc @ np.array([d[0] / cam.fx, d[1] / cam.fy, 0.0])
    theta = np.arctan2(-v_b[1], v_b[0])
    # Eqs. (2)-(3): centroid relative to the zero-tilt centroid
    z = c - z0
    s_b = rig.R_bc @ np.array([z[0] / cam.fx, z[1] / cam.fy, 0.0])
    # Eq. (4): rotate by the rotation angle into the triangle-aligned e frame
    e = rot_z(theta)[:2, :2] @ s_b[:2]
    # Eqs. (5)-(6): pixel/length ratio at the target, then the right triangle with the
    # distance L from the centre of rotation to the target
    L = float(rig.target.vertices_mm[:, 2].mean())
    h = float(rig.t_b[2])
    lateral = e * (L - h)
    tilt_n1 = np.arctan2(lateral[1], L)
    tilt_n2 = np.arctan2(-lateral[0], L)
    return rot_x(tilt_n1) @ rot_y(tilt_n2) @ rot_z(theta)


def solve_paper(det: Detection, rig: Rig, R_nb_guess: np.ndarray | None = None) -> AttitudeSolution:
    """The paper's attitude with a covariance propagated from the vertex covariance.

    Parameters
    ----------
    det : Detection
        The triangle's vertices (normalised image coordinates) and their covariance.
    rig : Rig
        The triangle rig.
    R_nb_guess : ndarray, shape (3, 3), optional
        Unused by the paper's closed form (kept for the estimators' common signature).

    Returns
    -------
    AttitudeSolution
        R_NB (3, 3) and its covariance (rad^2, body axes), or a status that says why
        there is none.
    """
    del R_nb_guess
    z0 = zero_tilt_centroid(rig)
    pts = det.points_px
    R_nb = paper_attitude(pts, rig, z0)
    e0 = np.array(matrix_to_euler(R_nb))
    # numerical propagation of the vertex covariance (pixels ~ fx * normalised)
    cov_n = det.cov_n if det.consider_n is None else det.cov_n + det.consider_n
    cov_px = cov_n * rig.camera.fx**2
    J = np.zeros((3, 6))
    h = 1e-3
    for k in range(6):
        dp = np.zeros(6)
        dp[k] = h
        ep = np.array(matrix_to_euler(paper_attitude(pts + dp.reshape(3, 2), rig, z0)))
        em = np.array(matrix_to_euler(paper_attitude(pts - dp.reshape(3, 2), rig, z0)))
        diff = ep - em
        diff[0] = (diff[0] + np.pi) % (2 * np.pi) - np.pi
        J[:, k] = diff / (2 * h)
    cov_e = J @ cov_px @ J.T
    # The published method is small-angle and ignores the lever arm and the lens, so its
    # error is mostly model error, not noise. Its size on this frame is measured against
    # the full camera model on the same vertices and added to the covariance, so that the
    # reported sigma covers it (the paper gives no uncertainty at all).
    full = solve_full(det, rig)
    warnings: tuple[str, ...] = ()
    if full.status is Status.OK:
        d = np.array(matrix_to_euler(full.R_nb)) - e0
        d[0] = (d[0] + np.pi) % (2 * np.pi) - np.pi
        cov_e = cov_e + np.diag(d**2)
    else:
        warnings = ("model_error_unknown",)
    E = np.linalg.inv(euler_rates_from_body(*e0))
    cov_b = E @ cov_e @ E.T
    rms = full.rms_px if full.status is Status.OK else float("nan")
    status = full.status if full.status is not Status.OK else Status.OK
    return AttitudeSolution(
        status,
        R_nb=R_nb,
        cov_b=cov_b,
        rms_px=rms,
        n_points=3,
        iterations=0,
        warnings=warnings + full.warnings,
    )
