"""The rolling shutter's geometry: where a point seen at one image row would be at the
centre row's exposure while the platform turns (:func:`unroll`), and its linearisation
(:func:`shutter_matrix`, :func:`shutter_shift`). Detection (detect/) undoes the shutter;
estimation (estimate/shear.py) fits the readout time from it; both import it from here.
Readout times are in milliseconds, as in the rig file (``[camera] readout_ms``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.camera import CameraModel


@dataclass(frozen=True)
class RollingShutter:
    """A rolling shutter as the detector undoes it.

    Attributes
    ----------
    readout_ms : float
        From the first row's exposure to the last's (negative: the last row read first).
    lever : (3,) ndarray or None
        The camera's position in the body over the target's depth, camera axes (see
        :func:`unroll`); None for a camera on the axis of rotation.
    """

    readout_ms: float
    lever: np.ndarray | None = None


def row_times(rows: np.ndarray, camera: CameraModel, readout_ms: float) -> np.ndarray:
    """Seconds from the centre row's exposure to each row's."""
    return (np.asarray(rows, float) - camera.cy) / camera.height * (readout_ms / 1000.0)


def unroll(
    xy: np.ndarray,
    rows: np.ndarray,
    camera: CameraModel,
    omega_c: np.ndarray,
    readout_ms: float,
    lever: np.ndarray | None = None,
) -> np.ndarray:
    """Normalised points (N, 2) seen at image rows ``rows`` by a rolling shutter, taken to
    the centre row's exposure.

    The camera rides on the platform, which turns about the lab origin at omega_c
    (camera axes): a lab point seen at time t after the centre row is, to first order,
    P(t) = P(0) - t omega_c x (P(0) + b), b = R_BC^T t_B the camera's position in B in
    camera axes (its lever arm: turning about the origin also moves the camera). With
    P = Z d, d = (x, y, 1): d0 = d + t omega_c x (d + ``lever``), ``lever`` = b / Z for
    the target's depth Z (None: a camera on the axis), t = (v - cy) / H * readout.
    """
    t = row_times(rows, camera, readout_ms)
    d = np.column_stack([xy, np.ones(len(xy))])
    arm = d if lever is None else d + lever
    d0 = d + t[:, None] * np.cross(np.asarray(omega_c, float), arm)
    return d0[:, :2] / d0[:, 2:3]


def shutter_matrix(
    xy: np.ndarray,
    rows: np.ndarray,
    camera: CameraModel,
    readout_ms: float,
    lever: np.ndarray | None = None,
) -> np.ndarray:
    """(6, 3) A: three normalised vertices xy (3, 2) seen at image ``rows`` by a rolling
    shutter of ``readout_ms`` move by A omega (x1, y1, x2, ...) when taken to the centre
    row's exposure (:func:`unroll` linearised at omega = 0; omega in rad/s, camera
    axes): the vertices as seen are those of the centre row less A omega.

    With e = d + lever = (ex, ey, ez) and t = (v - cy) / H * readout,
    A = t [[-x ey, ez + x ex, -ey], [-ez - y ey, y ex, ex]] (for a camera on the axis,
    e = (x, y, 1): t [[-x y, 1 + x^2, -y], [-1 - y^2, x y, x]]). (A vertex is an
    intersection of fitted lines whose points have their own rows; its own row's shift
    is the first-order value.)
    """
    t = row_times(rows, camera, readout_ms)
    x, y = xy[:, 0], xy[:, 1]
    lx, ly, lz = (0.0, 0.0, 0.0) if lever is None else np.asarray(lever, float)
    ex, ey, ez = x + lx, y + ly, 1.0 + lz
    A = np.zeros((6, 3))
    A[0::2] = np.column_stack([-x * ey, ez + x * ex, -ey]) * t[:, None]
    A[1::2] = np.column_stack([-ez - y * ey, y * ex, ex]) * t[:, None]
    return A


def shutter_shift(
    xy: np.ndarray,
    rows: np.ndarray,
    camera: CameraModel,
    readout_ms: float,
    omega_c: np.ndarray,
    lever: np.ndarray | None = None,
) -> np.ndarray:
    """(6,) A omega of :func:`shutter_matrix` for one rate, written for speed: with
    c = omega x e (e = d + lever), the projection's linearisation gives
    t (c_x - x c_z, c_y - y c_z) per vertex."""
    t = row_times(rows, camera, readout_ms)
    x, y = xy[:, 0], xy[:, 1]
    lx, ly, lz = (0.0, 0.0, 0.0) if lever is None else lever
    ex, ey, ez = x + lx, y + ly, 1.0 + lz
    wx, wy, wz = omega_c
    # omega x e written out (np.cross takes 20 us on three rows)
    cx, cy, cz = wy * ez - wz * ey, wz * ex - wx * ez, wx * ey - wy * ex
    out = np.empty(2 * len(xy))
    out[0::2] = (cx - x * cz) * t
    out[1::2] = (cy - y * cz) * t
    return out
