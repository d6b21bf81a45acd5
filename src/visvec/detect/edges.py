"""Sub-pixel triangle vertices from straight-line fits to its three edges.

Corners of a blurred, noisy, low-contrast triangle are poorly located by corner
detectors (the acute corner rounds off and cornerSubPix is pulled inward). Edges are
long: each is sampled by many intensity profiles across it, each profile gives a
sub-pixel edge point, and a robust total-least-squares line through the points is fitted
in undistorted coordinates (the edges are straight there, whatever the lens). Vertices
are the intersections of the lines, with a covariance from the fit residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import erf

from visvec.camera import CameraModel

# Variance inflation of the edge-point residuals for correlated neighbouring profiles
# (profiles 1 px apart, bilinear sampling); calibrated by simulation so that vertex
# errors divided by their predicted sigma have unit RMS.
EDGE_VARIANCE_INFLATION = 2.5


@dataclass(frozen=True)
class EdgeFit:
    """Lines fitted to the three edges; line i joins vertex i+1 and i+2 (opposite vertex i).

    normals : (3, 2) unit normals (ideal-pixel units, pointing into the triangle)
    offsets : (3,) n . x = offset
    centres : (3, 2) centroid of each edge's inlier points
    spreads : (3,) sum of squared along-line coordinates of the inliers about the centre
    counts : (3,) inlier counts
    sigmas : (3,) robust residual standard deviation (px)
    outlier_fraction : (3,)
    contrast : (3,) median triangle-minus-board grey-level step on each edge
    mid_level : (3,) mean of the board and triangle grey levels along each edge
    end_gaps_px : (3, 2) length of edge with no usable profile next to each end
        (vertex i+1, vertex i+2) beyond the planned corner clearance
    """

    normals: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray
    spreads: np.ndarray
    counts: np.ndarray
    sigmas: np.ndarray
    outlier_fraction: np.ndarray
    contrast: np.ndarray
    mid_level: np.ndarray
    end_gaps_px: np.ndarray

    def vertex_gaps(self) -> np.ndarray:
        """(3,) for each vertex, the longer unsupported stretch of its two edges (px)."""
        g = self.end_gaps_px
        return np.array([max(g[(v + 1) % 3, 1], g[(v + 2) % 3, 0]) for v in range(3)])


def _profiles(
    img: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    n_in: np.ndarray,
    half: float,
    step: float,
    trim_a: float,
    trim_b: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Intensity profiles across segment a-b, leaving out ``trim_a`` px at a and
    ``trim_b`` px at b; returns (bases (M, 2), values (M, S))."""
    length = float(np.linalg.norm(b - a))
    ta, tb = min(trim_a / length, 0.4), 1.0 - min(trim_b / length, 0.4)
    m = max(4, int(length * (tb - ta)))
    t = np.linspace(ta, tb, m)
    bases = a[None, :] + t[:, None] * (b - a)[None, :]
    offs = np.arange(-half, half + 1e-9, step)
    pts = bases[:, None, :] + offs[None, :, None] * n_in[None, None, :]
    mx = pts[..., 0].astype(np.float32)
    my = pts[..., 1].astype(np.float32)
    vals = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return bases, vals


def _edge_positions(
    vals: np.ndarray, half: float, step: float, ends: int, width: float | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """Sub-pixel step position of each profile (offset along the inward normal), and the
    local step height.

    Area (first-moment) estimator: for a step from level lo to hi, blurred by any
    symmetric kernel narrower than the profile, the integral of the normalised profile
    (I - lo) / (hi - lo) from -half to +half equals half - e. Levels lo and hi are fitted
    as straight lines along the edge to follow the lighting gradient.
    """
    m = vals.shape[0]
    t = np.linspace(-1.0, 1.0, m)
    lo_raw = vals[:, :ends].mean(axis=1)
    hi_raw = vals[:, -ends:].mean(axis=1)
    # straight-line fits against t (t is centred, so intercept and slope decouple)
    tt = t @ t
    lo = lo_raw.mean() + t * ((t @ lo_raw) / tt)
    hi = hi_raw.mean() + t * ((t @ hi_raw) / tt)
    step_h = hi - lo
    safe = np.where(np.abs(step_h) > 1e-6, step_h, 1e-6)
    f = (vals - lo[:, None]) / safe[:, None]
    integral = step * (f.sum(axis=1) - 0.5 * (f[:, 0] + f[:, -1]))
    e = half - integral
    if width is not None:
        # Matched refinement: least-squares fit of an erf step of the measured blur
        # width to each normalised profile, two Gauss-Newton steps from the area
        # estimate. Weights the samples by the edge slope instead of uniformly, which
        # cuts the noise by about 1.5x for a sharp edge (the flat tails add no noise).
        x = np.arange(-half, half + 1e-9, step)[None, :]
        s2 = np.sqrt(2.0) * width
        for _ in range(2):
            u = (x - e[:, None]) / s2
            r = f - 0.5 * (1.0 + erf(u))
            g = np.exp(-u * u) / (np.sqrt(np.pi) * s2)
            e = e - np.clip((r * g).sum(axis=1) / np.maximum((g * g).sum(axis=1), 1e-12), -0.5, 0.5)
    return e, hi_raw - lo_raw, float(lo.mean() + hi.mean()) / 2


def _edge_width(vals: np.ndarray, e: np.ndarray, half: float, step: float) -> float:
    """RMS width (px) of the edge's blur: second moment of the mean profile derivative."""
    offs = np.arange(-half, half + 1e-9, step)
    g = np.diff(vals, axis=1).mean(axis=0)
    x = 0.5 * (offs[1:] + offs[:-1]) - float(np.median(e))
    g = np.clip(g, 0.0, None)
    if g.sum() <= 0:
        return half
    return float(np.sqrt((g * x * x).sum() / g.sum()))


def _tls(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre, unit direction and unit normal of the total-least-squares line through p."""
    c = p.mean(axis=0)
    q = p - c
    sxx, syy, sxy = q[:, 0] @ q[:, 0], q[:, 1] @ q[:, 1], q[:, 0] @ q[:, 1]
    # direction: principal axis of the 2x2 scatter matrix, angle 0.5 atan2(2 sxy, sxx - syy)
    a = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    d = np.array([np.cos(a), np.sin(a)])
    return c, d, np.array([-d[1], d[0]])


def _robust_line(p: np.ndarray, floor: float) -> tuple[np.ndarray, ...]:
    """Total-least-squares line through (N, 2) points with iterative outlier rejection
    (3.5 robust sigmas, sigma from the median absolute residual).

    Returns normal, offset, centre, spread, inlier mask, sigma.
    """
    keep = np.ones(len(p), dtype=bool)
    c, d, n = _tls(p)
    for _ in range(3):
        r = (p - c) @ n
        sigma = max(1.4826 * np.median(np.abs(r[keep])), floor)
        new = np.abs(r) <= max(3.5 * sigma, 0.25)
        if np.array_equal(new, keep) or new.sum() < 5:
            break
        keep = new
        c, d, n = _tls(p[keep])
    q = p[keep] - c
    r = q @ n
    # EDGE_VARIANCE_INFLATION: neighbouring profiles share pixels through the bilinear
    # sampling, so the points are not independent (measured in tests/test_edges.py).
    sigma = max(float(np.sqrt(r @ r / max(len(r) - 2, 1) * EDGE_VARIANCE_INFLATION)), floor)
    tcoord = q @ d
    return n, float(n @ c), c, float(tcoord @ tcoord), keep, sigma


def _side_lengths(p: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p[[1, 2, 0]] - p[[2, 0, 1]], axis=1)


def _corner_angles(p: np.ndarray) -> np.ndarray:
    a, b, c = _side_lengths(p)  # opposite vertices 0, 1, 2
    cos0 = (b * b + c * c - a * a) / (2 * b * c)
    cos1 = (a * a + c * c - b * b) / (2 * a * c)
    return np.arccos(
        np.clip(
            [
                cos0,
                cos1,
                -np.cos(np.arccos(np.clip(cos0, -1, 1)) + np.arccos(np.clip(cos1, -1, 1))),
            ],
            -1,
            1,
        )
    )


def fit_edges(
    image: np.ndarray,
    corners_px: np.ndarray,
    camera: CameraModel,
    *,
    sigma_floor: float = 0.02,
    half: float = 4.0,
    step: float = 0.5,
    trim: float = 0.06,
) -> EdgeFit:
    """Fit the three edges of the triangle whose coarse corners are ``corners_px`` (3, 2).

    Two passes: profiles across the chords of the coarse corners, then across the lines
    of the first pass (centred, so that the profiles are symmetric about the edge).
    Lines are in ideal (undistorted) pixels: f * (normalised coordinates), f = fx.
    """
    lo = np.floor(corners_px.min(axis=0) - half - 3).astype(int)
    hi = np.ceil(corners_px.max(axis=0) + half + 3).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [image.shape[1] - 1, image.shape[0] - 1])
    roi = image[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1].astype(np.float32)
    off = lo.astype(float)
    f = camera.fx
    ends = max(2, int(1.0 / step))
    corners = corners_px.astype(float)
    fit = None
    width = half / 3.0
    for npass in range(2):
        if npass == 1:
            # second pass: profiles centred on the first lines and only as long as the
            # blur needs: the tails carry noise but no edge information
            half = step * np.ceil(float(np.clip(3.0 * width + 0.75, 1.5, half)) / step)
        normals, offsets, centres = np.zeros((3, 2)), np.zeros(3), np.zeros((3, 2))
        spreads, counts, sigmas = np.zeros(3), np.zeros(3), np.zeros(3)
        outl, contrast, mid = np.zeros(3), np.zeros(3), np.zeros(3)
        gaps = np.zeros((3, 2))
        inside = corners.mean(axis=0)
        # near a vertex of angle alpha the other edge is d sin(alpha) away: keep the
        # profiles (and the blur around them) clear of it
        trims = np.maximum(
            trim * _side_lengths(corners).min(),
            (half + 2.0 * width + 0.5) / np.sin(np.clip(_corner_angles(corners), 0.2, None)),
        )
        widths = np.zeros(3)
        for i in range(3):
            a, b = corners[(i + 1) % 3], corners[(i + 2) % 3]
            d = (b - a) / max(np.linalg.norm(b - a), 1e-9)
            n_in = np.array([-d[1], d[0]])
            if n_in @ (inside - a) < 0:
                n_in = -n_in
            bases, vals = _profiles(
                roi, a - off, b - off, n_in, half, step, trims[(i + 1) % 3], trims[(i + 2) % 3]
            )
            e, h, mid[i] = _edge_positions(vals, half, step, ends, width if npass == 1 else None)
            widths[i] = _edge_width(vals, e, half, step)
            pts_px = bases + off + e[:, None] * n_in[None, :]
            good = (np.abs(e) < half - 1.0) & (h > 0.4 * max(np.median(h), 1e-6))
            ideal = camera.undistort(pts_px) * f
            n, o, c, s, keep, sig = _robust_line(
                ideal[good] if good.sum() >= 5 else ideal, sigma_floor
            )
            centre_ideal = camera.undistort(inside[None, :])[0] * f
            if n @ centre_ideal < o:
                n, o = -n, -o
            normals[i], offsets[i], centres[i] = n, o, c
            spreads[i], counts[i], sigmas[i] = s, keep.sum(), sig
            outl[i] = 1.0 - keep.sum() / len(e)
            # how far the inlier edge points stop short of the two ends of the edge
            idx = np.nonzero(good)[0][keep] if good.sum() >= 5 else np.nonzero(keep)[0]
            along = (bases[idx] + off - a) @ d
            length = float(np.linalg.norm(b - a))
            gaps[i] = (
                (along.min() - trims[(i + 1) % 3], length - trims[(i + 2) % 3] - along.max())
                if len(idx)
                else (length,) * 2
            )
            contrast[i] = float(np.median(h))
        fit = EdgeFit(normals, offsets, centres, spreads, counts, sigmas, outl, contrast, mid, gaps)
        width = float(np.median(widths))
        corners = camera.distort(intersect(fit)[0] / f)
    return fit


def intersect(fit: EdgeFit) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (3, 2) in ideal pixels and their (6, 6) covariance.

    Vertex i lies on lines j = i+1 and k = i+2. Each line is perturbed by an offset
    error (variance sigma^2 / count) and a rotation about its centre (variance
    sigma^2 / spread); at a point x on the line these move it along its normal by
    eps_o + eps_a * s(x), s = along-line distance from the centre. Stacking the six line
    errors, vertex displacements are linear in them: cov = J diag(var) J^T.
    """
    V = np.zeros((3, 2))
    J = np.zeros((6, 6))
    var = np.zeros(6)
    for j in range(3):
        var[2 * j] = fit.sigmas[j] ** 2 / fit.counts[j]
        var[2 * j + 1] = fit.sigmas[j] ** 2 / max(fit.spreads[j], 1e-12)
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        A = np.vstack([fit.normals[j], fit.normals[k]])
        x = np.linalg.solve(A, np.array([fit.offsets[j], fit.offsets[k]]))
        V[i] = x
        Ainv = np.linalg.inv(A)
        for row, ln in enumerate((j, k)):
            t = np.array([-fit.normals[ln][1], fit.normals[ln][0]])
            s = float((x - fit.centres[ln]) @ t)
            J[2 * i : 2 * i + 2, 2 * ln] += Ainv[:, row]
            J[2 * i : 2 * i + 2, 2 * ln + 1] += Ainv[:, row] * s
    return V, J @ np.diag(var) @ J.T
