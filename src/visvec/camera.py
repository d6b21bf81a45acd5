"""OpenCV pinhole camera with (k1, k2, p1, p2, k3) distortion (SPEC section 1).

``cv2.projectPoints`` is the reference projection; :meth:`CameraModel.distort` is the
same model written in numpy for small point sets (tested against it).

The polynomial is a fit over the field the calibration photos covered. Beyond it a
strong distortion's polynomial can turn back (the image radius r (1 + k1 r^2 + k2 r^4 +
k3 r^6) stops growing with the ray's radius r): past that fold it maps two rays to one
pixel and some pixels to none, which no lens does. The model's field is the disc inside
the fold (:attr:`CameraModel.field_r2`); :meth:`CameraModel.undistort` and
:meth:`CameraModel.project` give nan outside it, never a ray from the wrong branch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

# undistort's Newton steps stop once every point reprojects within this (px)
UNDISTORT_TOL_PX = 1e-9
# and at most this many; a point that then still reprojects more than UNDISTORT_FAIL_PX
# off has no ray in the model's field (nan)
UNDISTORT_STEPS = 4
UNDISTORT_FAIL_PX = 1e-3


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

    @cached_property
    def field_r2(self) -> float:
        """The squared radius (normalised, undistorted) of the model's field: where the
        radial image radius r (1 + k1 r^2 + k2 r^4 + k3 r^6) first stops growing, the
        smallest positive root s = r^2 of its derivative 1 + 3 k1 s + 5 k2 s^2 +
        7 k3 s^3; inf where it never does (tangential terms, a few 1e-3, left out)."""
        k1, k2, _, _, k3 = (float(k) for k in self.dist)
        roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]) if k1 or k2 or k3 else []
        s = [r.real for r in roots if abs(r.imag) <= 1e-9 * abs(r) and r.real > 0]
        return min(s) if s else math.inf

    @property
    def field_radius_px(self) -> float:
        """The model's field as a radius in the image (px from the principal point, at the
        mean focal length); inf without a fold."""
        s = self.field_r2
        if math.isinf(s):
            return math.inf
        k1, k2, _, _, k3 = (float(k) for k in self.dist)
        return math.sqrt(s) * (1.0 + s * (k1 + s * (k2 + s * k3))) * 0.5 * (self.fx + self.fy)

    def in_field(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixels at least ``margin`` px inside the model's field (within a
        tenth of a pixel of the fold :meth:`undistort` may not converge: keep a pixel)."""
        if math.isinf(self.field_r2):
            return np.ones(len(uv), dtype=bool)
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        f = 0.5 * (self.fx + self.fy)
        return np.hypot(x, y) * f <= self.field_radius_px - margin

    @property
    def corner_radius_px(self) -> float:
        """How far the image reaches from the principal point (px, farthest corner)."""
        du = max(self.cx + 0.5, self.width - 0.5 - self.cx)
        dv = max(self.cy + 0.5, self.height - 0.5 - self.cy)
        return float(np.hypot(du, dv))

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
        """Normalised undistorted coordinates (N, 2) to pixels (N, 2): the polynomial as
        it is, also outside the model's field (see :meth:`project`)."""
        x, y = xy_n[:, 0], xy_n[:, 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])

    def project(self, p_c: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) to pixels (N, 2); points behind the camera or outside
        the model's field give nan."""
        p_c = np.asarray(p_c, dtype=float).reshape(-1, 3)
        z = p_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_c[:, :2] / z[:, None]
        uv = self.distort(xy)
        uv[z <= 0] = np.nan
        if not math.isinf(self.field_r2):
            uv[np.einsum("ij,ij->i", xy, xy) >= self.field_r2] = np.nan
        return uv

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) to normalised undistorted coordinates (N, 2); nan for pixels
        outside the model's field (no ray maps there, or only one beyond the fold)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not self.has_distortion:
            out = (uv[:, 0, :] - [self.cx, self.cy]) / [self.fx, self.fy]
            return out
        xy = cv2.undistortPoints(uv, self.K, self.dist).reshape(-1, 2)
        # OpenCV's fixed-point iteration stops early with strong distortion; finish with
        # Newton steps on distort(xy) = uv (analytic 2x2 Jacobian per point), until the
        # points reproject to 1e-9 px (a webcam's k1 = -0.28: two steps; k1 = -0.42 with
        # k2, k3: three)
        target = uv.reshape(-1, 2)
        for step in range(UNDISTORT_STEPS + 1):
            r = self.distort(xy) - target
            if len(r) == 0 or np.abs(r).max() < UNDISTORT_TOL_PX or step == UNDISTORT_STEPS:
                break
            J = self._distort_jacobian(xy)
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            dx = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            dy = (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
            xy = xy - np.column_stack([dx, dy])
        if len(r) and np.abs(r).max() >= UNDISTORT_TOL_PX:
            xy[~(np.abs(r).max(axis=1) < UNDISTORT_FAIL_PX)] = np.nan
        if not math.isinf(self.field_r2):
            xy[~(np.einsum("ij,ij->i", xy, xy) < self.field_r2)] = np.nan
        return xy

    def _distort_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2, 2) d(u, v) / d(x, y) of :meth:`distort`."""
        x, y = xy[:, 0], xy[:, 1]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
        J = np.empty((len(x), 2, 2))
        J[:, 0, 0] = self.fx * (radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x)
        J[:, 0, 1] = self.fx * (2 * x * y * drad + 2 * p1 * x + 2 * p2 * y)
        J[:, 1, 0] = self.fy * (2 * x * y * drad + 2 * p1 * x + 2 * p2 * y)
        J[:, 1, 1] = self.fy * (radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x)
        return J

    def pixels_per_steradian(self, uv: np.ndarray) -> np.ndarray:
        """(N,) image area (px^2) per steradian of the field at pixels ``uv`` (N, 2): a
        small object subtending a solid angle w there covers w times this. Through a
        pinhole a ray at (x, y) of normalised coordinates is (1 + x^2 + y^2)^(3/2) times
        as far out per unit of solid angle as the boresight, and the lens maps a unit of
        normalised area onto det(d(u, v) / d(x, y)) px^2 (fx fy without distortion)."""
        xy = self.undistort(uv)
        if self.has_distortion:
            J = self._distort_jacobian(xy)
            det = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
        else:
            det = np.full(len(xy), self.fx * self.fy)
        return det * (1.0 + np.einsum("ij,ij->i", xy, xy)) ** 1.5

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel positions at least ``margin`` px inside the image."""
        u, v = uv[:, 0], uv[:, 1]
        return (
            (u >= -0.5 + margin)
            & (v >= -0.5 + margin)
            & (u <= self.width - 0.5 - margin)
            & (v <= self.height - 0.5 - margin)
        )
