"""OpenCV pinhole camera with (k1, k2, p1, p2, k3) distortion (SPEC section 1).

``cv2.projectPoints`` is the reference projection; :meth:`CameraModel.distort` is the
same model written in numpy for small point sets (tested against it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels.
    dist : (5,) ndarray
        k1, k2, p1, p2, k3.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def scaled(self, factor: float) -> CameraModel:
        """The same lens on a sensor resampled by ``factor`` (pixel centres kept)."""
        return CameraModel(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            dist=self.dist.copy(),
        )

    def distort(self, xy_n: np.ndarray) -> np.ndarray:
        """Normalised undistorted coordinates (N, 2) to pixels (N, 2)."""
        x, y = xy_n[:, 0], xy_n[:, 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])

    def project(self, p_c: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) to pixels (N, 2); points behind the camera give nan."""
        p_c = np.asarray(p_c, dtype=float).reshape(-1, 3)
        z = p_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_c[:, :2] / z[:, None]
        uv = self.distort(xy)
        uv[z <= 0] = np.nan
        return uv

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) to normalised undistorted coordinates (N, 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not self.has_distortion:
            out = (uv[:, 0, :] - [self.cx, self.cy]) / [self.fx, self.fy]
            return out
        out = cv2.undistortPointsIter(uv, self.K, self.dist, None, None, _UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel positions at least ``margin`` px inside the image."""
        u, v = uv[:, 0], uv[:, 1]
        return (
            (u >= -0.5 + margin)
            & (v >= -0.5 + margin)
            & (u <= self.width - 0.5 - margin)
            & (v <= self.height - 0.5 - margin)
        )
