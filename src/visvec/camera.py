"""OpenCV pinhole camera with (k1, k2, p1, p2, k3) distortion (docs/reference.md, Conventions).

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
# and at most this many; a point then still UNDISTORT_RETRY_PX off is solved again from
# its radial solution, and one still UNDISTORT_FAIL_PX off after that has no ray in the
# model's field (nan)
UNDISTORT_STEPS = 4
UNDISTORT_RETRY_PX = 1e-6
UNDISTORT_FAIL_PX = 1e-3
# distort() takes this many points or fewer one by one, in Python's floats
SMALL_N = 4


def _distorted(x, y, k1, k2, p1, p2, k3):
    """OpenCV's distortion polynomial of normalised (x, y): arrays or floats alike."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


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

    @cached_property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    @cached_property
    def _centre_focal(self) -> tuple[np.ndarray, np.ndarray]:
        """[cx, cy] and [fx, fy] as arrays (made once, not on every undistort)."""
        return np.array([self.cx, self.cy]), np.array([self.fx, self.fy])

    @cached_property
    def field_r2(self) -> float:
        """The squared radius (normalised, undistorted) of the model's field: where the
        radial image radius r (1 + k1 r^2 + k2 r^4 + k3 r^6) first stops growing, the
        smallest positive root s = r^2 of its derivative 1 + 3 k1 s + 5 k2 s^2 +
        7 k3 s^3; inf where it never does (tangential terms, a few 1e-3, left out)."""
        k1, k2, _, _, k3 = (float(k) for k in self.dist)
        # terms under 1e-12 change nothing out to s = 100 (84 deg off the boresight) and
        # would only throw np.roots off
        c = [c if abs(c) > 1e-12 else 0.0 for c in (7.0 * k3, 5.0 * k2, 3.0 * k1)]
        roots = np.roots([*c, 1.0]) if any(c) else []
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
        """(N,) bool: pixels at least ``margin`` px inside the model's field, by its
        radial terms (the tangential ones move the fold by a few px: what has a ray is
        what :meth:`undistort` gives one, finite)."""
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

    @cached_property
    def _dist_floats(self) -> tuple[float, ...]:
        return tuple(float(k) for k in self.dist)

    def distort(self, xy_n: np.ndarray) -> np.ndarray:
        """Normalised undistorted coordinates (N, 2) to pixels (N, 2): the polynomial as
        it is, also outside the model's field (see :meth:`project`)."""
        if len(xy_n) <= SMALL_N and getattr(xy_n, "dtype", None) == np.float64:
            # a triangle's vertices: point by point in Python's floats (numpy's start-up
            # on three points costs more than the arithmetic), the same operations
            k = self._dist_floats
            out = [_distorted(x, y, *k) for x, y in xy_n.tolist()]
            uv = np.array(out, dtype=np.float64).reshape(-1, 2)
            uv[:, 0] = self.fx * uv[:, 0] + self.cx
            uv[:, 1] = self.fy * uv[:, 1] + self.cy
            return uv
        xd, yd = _distorted(xy_n[:, 0], xy_n[:, 1], *self.dist)
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
            c, f = self._centre_focal
            return (uv[:, 0, :] - c) / f
        xy = cv2.undistortPoints(uv, self.K, self.dist).reshape(-1, 2)
        # OpenCV's fixed-point iteration stops early with strong distortion; finish with
        # Newton steps on distort(xy) = uv (analytic 2x2 Jacobian per point), until the
        # points reproject to 1e-9 px (a webcam's k1 = -0.28: two steps; k1 = -0.42 with
        # k2, k3: three)
        target = uv.reshape(-1, 2)
        xy, res = self._newton(xy, target)
        # where the fixed point went astray (strong pincushion near the corners: it
        # diverges) or to the polynomial's far branch, start again from the radial
        # solution on the near branch
        again = ~(res < UNDISTORT_RETRY_PX) | ~(np.einsum("ij,ij->i", xy, xy) < self.field_r2)
        if np.any(again):
            idx = np.nonzero(again)[0]
            xy2, res2 = self._newton(self._radial_start(target[idx]), target[idx])
            near = np.einsum("ij,ij->i", xy[idx], xy[idx]) < self.field_r2
            better = ~(res[idx] <= res2) | ~near
            xy[idx[better]], res[idx[better]] = xy2[better], res2[better]
        xy[~(res < UNDISTORT_FAIL_PX)] = np.nan
        if not math.isinf(self.field_r2):
            xy[~(np.einsum("ij,ij->i", xy, xy) < self.field_r2)] = np.nan
        return xy

    def _newton(self, xy: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Up to UNDISTORT_STEPS Newton steps on distort(xy) = target from ``xy``; the
        points and their (N,) remaining reprojection error (px, max of u and v; nan at
        a fold, where the Jacobian is singular). The residual and the 2x2 Jacobian of
        :meth:`distort` (as :meth:`_distort_jacobian`) share their terms here: this runs
        on every edge point of a distorting lens."""
        k1, k2, p1, p2, k3 = (float(k) for k in self.dist)
        fx, fy = self.fx, self.fy
        x, y = xy[:, 0].copy(), xy[:, 1].copy()
        tu, tv = target[:, 0] - self.cx, target[:, 1] - self.cy
        with np.errstate(divide="ignore", invalid="ignore"):
            for step in range(UNDISTORT_STEPS + 1):
                xx, yy, xy_ = x * x, y * y, x * y
                r2 = xx + yy
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                ru = fx * (x * radial + 2.0 * p1 * xy_ + p2 * (r2 + 2.0 * xx)) - tu
                rv = fy * (y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy_) - tv
                worst = np.maximum(np.abs(ru), np.abs(rv))
                if len(x) == 0 or worst.max() < UNDISTORT_TOL_PX or step == UNDISTORT_STEPS:
                    break
                drad2 = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # 2 d radial / d r2
                cross = xy_ * drad2 + 2.0 * (p1 * x + p2 * y)
                a = fx * (radial + xx * drad2 + 2.0 * p1 * y + 6.0 * p2 * x)
                b, c = fx * cross, fy * cross
                d = fy * (radial + yy * drad2 + 6.0 * p1 * y + 2.0 * p2 * x)
                det = a * d - b * c
                x = x - (d * ru - b * rv) / det
                y = y - (a * rv - c * ru) / det
        return np.column_stack([x, y]), worst

    def _radial_start(self, uv: np.ndarray) -> np.ndarray:
        """Normalised points on the near branch whose radial distortion alone gives the
        pixels ``uv`` (N, 2) (tangential terms left to Newton): the radius r of r (1 +
        k1 r^2 + k2 r^4 + k3 r^6) = r_d by bisection on [0, the fold] (within the field
        the image radius grows with r); nan beyond the fold's image radius."""
        xd = np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy])
        rd = np.hypot(xd[:, 0], xd[:, 1])
        k1, k2, _, _, k3 = (float(k) for k in self.dist)

        def image_radius(r: np.ndarray) -> np.ndarray:
            s = r * r
            return r * (1.0 + s * (k1 + s * (k2 + s * k3)))

        if math.isinf(self.field_r2):
            hi = 1.0  # no fold: the image radius grows without bound; double until past
            while hi < 1e6 and image_radius(np.array(hi)) < rd.max(initial=0.0):
                hi *= 2.0
        else:
            hi = math.sqrt(self.field_r2)
        lo, up = np.zeros(len(rd)), np.full(len(rd), hi)
        for _ in range(52):  # to a few 1e-16 of hi
            mid = 0.5 * (lo + up)
            below = image_radius(mid) < rd
            lo, up = np.where(below, mid, lo), np.where(below, up, mid)
        r = 0.5 * (lo + up)
        r[rd > image_radius(np.array(hi))] = np.nan
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(rd > 0, r / rd, 1.0)
        return xd * scale[:, None]

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
