"""Where lab points appear in a platform-mounted camera (docs/reference.md, Conventions)."""

from __future__ import annotations

import numpy as np

from visvec.rig import Rig


def lab_to_camera(rig: Rig, R_nb: np.ndarray, p_n: np.ndarray) -> np.ndarray:
    """Lab points (N, 3) in the camera frame: P_C = R_BC^T (R_NB^T P_N - t_B)."""
    return (p_n @ R_nb - rig.t_b) @ rig.R_bc


def project_target(rig: Rig, R_nb: np.ndarray) -> np.ndarray:
    """(3, 2) pixel positions of the triangle's vertices at attitude ``R_nb``."""
    return rig.camera.project(lab_to_camera(rig, R_nb, rig.target.vertices_mm))


def camera_offset_c(rig: Rig) -> np.ndarray:
    """(3,) constant translation t_c in P_C = R_CN P_N + t_c, with t_c = -R_BC^T t_B.

    Because the camera rides on the platform and the platform turns about the lab
    origin, the camera-frame translation does not depend on the attitude: only
    R_CN = R_BC^T R_NB^T is unknown.
    """
    return -rig.R_bc.T @ rig.t_b


def markers_to_camera(rig: Rig, R_nb: np.ndarray, m_b: np.ndarray) -> np.ndarray:
    """Body points (N, 3) seen by a camera fixed in the lab:
    P_C = R_NC^T (R_NB M_B - t_N)."""
    return (m_b @ R_nb.T - rig.t_n) @ rig.R_nc


def lab_camera_offset_c(rig: Rig) -> np.ndarray:
    """(3,) t_c in P_C = R_CB M_B + t_c for a camera fixed in the lab: t_c = -R_NC^T t_N."""
    return -rig.R_nc.T @ rig.t_n
