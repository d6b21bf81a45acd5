"""The triangle's edges fitted to the pixels themselves (a photometric refinement).

The edge-line fit (visvec.detect.edges) turns profiles across each edge into edge points
and fits lines through them; each step throws a little information away (the profiles'
bilinear sampling, their spacing, levels measured apart from the step, one
Gauss-Newton step of the step's position). Here the lines it found are refined by
fitting a model of the blurred edges to every pixel near them, by Gauss-Newton
(maximum likelihood under white Gaussian pixel noise, whose Fisher information is the
Cramér-Rao bound of benchmarks/triangle_crb.py):

    I(x) = L(x) + C(x) Phi(d_e(x) / w_e),

x a pixel's ideal (undistorted) coordinates, e the one edge the pixel is near,
d_e(x) = n_e . (x - c_e) - o_e its signed distance to that edge's line (inward
positive), w_e the edge's blur width, Phi the standard normal CDF (a Gaussian blur of a
straight step; the pixel's box response is taken as part of the Gaussian,
w^2 = sigma_blur^2 + 1/12), and L, C the board level and the triangle's contrast, each a
plane across the image (a lighting gradient). Pixels within reach of two edges (the
vertices' neighbourhoods, where a blurred corner is no longer a product of steps) are
left out. The parameters: each line's rotation about its centre and its offset, the
three widths, the six level coefficients; the lines give the vertices, whose covariance
follows from the fit's (the residuals' variance times (J^T J)^-1), so that the lines'
errors through the shared levels are correlated as they are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from visvec.camera import CameraModel
from visvec.detect.edges import _vertices

GN_STEPS = 2
# pixels within this many blur widths + REACH_PX of an edge are fitted to it
REACH_WIDTHS = 3.0
REACH_PX = 2.0
# and when they lie this many blur widths inside the other two edges (where those add
# under 0.14 % of the contrast)
CLEAR_WIDTHS = 3.0
N_PARAMS = 15  # 3 lines x (rotation, offset), 3 widths, 6 level coefficients
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class PhotometricFit:
    """Vertices (3, 2) ideal px (vertex i opposite line i), their covariance (6, 6), the
    edges' blur widths (3,), the residual RMS (grey levels) and the pixels used."""

    xy: np.ndarray
    cov: np.ndarray
    width: np.ndarray
    rms: float
    n_pixels: int
    ok: bool = True


class _IdealGrid:
    """Ideal (undistorted, f * normalised) coordinates of every pixel centre of a camera,
    computed once."""

    _cache: dict[tuple, np.ndarray] = {}

    @classmethod
    def of(cls, camera: CameraModel) -> np.ndarray:
        key = (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
               tuple(float(k) for k in camera.dist))  # fmt: skip
        grid = cls._cache.get(key)
        if grid is None:
            u, v = np.meshgrid(np.arange(camera.width, dtype=float),
                               np.arange(camera.height, dtype=float))  # fmt: skip
            xy = camera.undistort(np.column_stack([u.ravel(), v.ravel()])) * camera.fx
            grid = xy.reshape(camera.height, camera.width, 2)
            if len(cls._cache) > 4:
                cls._cache.clear()
            cls._cache[key] = grid
        return grid


def _intersections(n: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, list | None]:
    """Vertices (3, 2) of the lines n_i . (x - c_i) = 0 (vertex i on lines i+1, i+2),
    and per vertex the inverse of its lines' 2x2 normal matrix (edges._vertices)."""
    return _vertices(n, np.einsum("ij,ij->i", n, c))


def _vertex_gain(n: np.ndarray, c: np.ndarray, V: np.ndarray, invs: list) -> np.ndarray:
    """(6, 6) d(vertices)/d(lines): line i turned by a small angle about c_i, or moved
    by an offset along n_i, moves vertex v on it (v on lines j, k) by A_v^-1 times the
    change of those lines' equations n . x = n . c at v: the offset adds 1 to its
    row's right side; the turn d(theta) (n -> n + d(theta) n_perp) takes
    n_perp . (v - c_i) d(theta) from it."""
    G = np.zeros((6, 6))
    for v in range(3):
        inv = invs[v]
        for row, ln in enumerate(((v + 1) % 3, (v + 2) % 3)):
            nx, ny = n[ln]
            s = (V[v, 0] - c[ln, 0]) * -ny + (V[v, 1] - c[ln, 1]) * nx
            for q in range(2):
                G[2 * v + q, 2 * ln] -= inv[q][row] * s
                G[2 * v + q, 2 * ln + 1] += inv[q][row]
    return G


def _meet(n1, o1, n2, o2) -> tuple[float, float]:
    """The point where the lines n1 . x = o1 and n2 . x = o2 meet (Cramer's rule)."""
    det = n1[0] * n2[1] - n1[1] * n2[0]
    return ((o1 * n2[1] - o2 * n1[1]) / det, (n1[0] * o2 - n2[0] * o1) / det)


def _band(image, n, c, reach, clear, camera):
    """The pixels fitted to each edge: within its reach, and clear inside the other two
    edges. The band of each edge is drawn as a quadrilateral in the image (its corners
    taken through the lens, 1.5 px wider against the curvature a distortion gives it),
    then checked exactly on the pixels' ideal coordinates. Returns per edge the
    pixels' ideal coordinates (m_e, 2) and grey levels (m_e,), or None."""
    nn = n.tolist()
    o = np.einsum("ij,ij->i", n, c).tolist()
    quads = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        for sgn, other in ((-1.0, j), (-1.0, k), (1.0, k), (1.0, j)):
            oi = o[i] + sgn * (reach[i] + 1.5)
            quads.append(_meet(nn[i], oi, nn[other], o[other] + clear[other]))
    q_px = camera.distort(np.array(quads) / camera.fx)
    if not np.all(np.isfinite(q_px)):
        return None
    lo = np.maximum(np.floor(q_px.min(axis=0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(q_px.max(axis=0)).astype(int) + 1,
                    [camera.width - 1, camera.height - 1])  # fmt: skip
    if np.any(hi <= lo):
        return None
    # the three bands drawn on one mask; the exact check below gives each pixel to the
    # edge it is near (near a vertex, where two bands overlap, to neither)
    mask = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.uint8)
    for i in range(3):
        poly = np.rint((q_px[4 * i : 4 * i + 4] - lo) * 16).astype(np.int32)
        cv2.fillPoly(mask, [poly], i + 1, cv2.LINE_8, 4)
    pts = cv2.findNonZero(mask)
    if pts is None:
        return None
    pts = pts.reshape(-1, 2)
    # flat indices into the frame (one take is cheaper than a gather by row and column)
    flat = (pts[:, 1] + lo[1]) * camera.width + (pts[:, 0] + lo[0])
    x = np.take(_IdealGrid.of(camera).reshape(-1, 2), flat, axis=0)
    grey = np.take(image.reshape(-1), flat)
    d = x @ n.T - np.array(o)  # (P, 3)
    out = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        # a pixel is the nearest edge's: within its reach and clear of the other two
        keep = (np.abs(d[:, i]) < reach[i]) & (d[:, j] > clear[j]) & (d[:, k] > clear[k])
        out.append((x[keep], grey[keep].astype(float)))
    return out


def refine(image: np.ndarray, normals: np.ndarray, offsets: np.ndarray, width: np.ndarray,
           camera: CameraModel) -> PhotometricFit:  # fmt: skip
    """Refine the edge lines n_i . x = offset_i (ideal px, normals into the triangle)
    on the pixels of ``image``; ``width`` (3,) the blur widths to start from."""
    n = np.asarray(normals, float).copy()
    # each line's centre: the middle between its two vertices
    V, _ = _intersections(n, n * np.asarray(offsets, float)[:, None])
    c = 0.5 * (V[[1, 2, 0]] + V[[2, 0, 1]])
    w = np.maximum(np.asarray(width, float), 0.3)
    bands = _band(image, n, c, REACH_WIDTHS * w + REACH_PX, CLEAR_WIDTHS * w, camera)
    counts = [0, 0, 0] if bands is None else [len(b[1]) for b in bands]
    m = sum(counts)
    if m < 3 * N_PARAMS or min(counts) < 10:
        return PhotometricFit(V, np.full((6, 6), np.nan), w, math.nan, m, ok=False)
    centroid = V.mean(axis=0)
    scale = max(float(np.abs(V - centroid).max()), 1.0)
    # per edge, its pixels' Jacobian (m_e, 9): rotation about c (d(d)/d(theta) =
    # n_perp . (x - c)), offset, width, then the six level coefficients, whose first
    # three (the board's plane: 1, x, y) never change
    jac = []
    for x, _ in bands:
        Je = np.empty((len(x), 9), order="F")
        Je[:, 3] = 1.0
        Je[:, 4:6] = (x - centroid) / scale
        jac.append(Je)
    idx = [[2 * i, 2 * i + 1, 6 + i, 9, 10, 11, 12, 13, 14] for i in range(3)]
    level = None
    for _ in range(GN_STEPS):
        H = np.zeros((N_PARAMS, N_PARAMS))
        b = np.zeros(N_PARAMS)
        rss = 0.0
        steps = []
        for i, ((x, _), Je) in enumerate(zip(bands, jac, strict=True)):
            nx, ny = n[i]
            rx, ry = x[:, 0] - c[i, 0], x[:, 1] - c[i, 1]
            u = (rx * nx + ry * ny) / w[i]
            T = ndtr(u)
            Je[:, 6:9] = Je[:, 3:6] * T[:, None]
            steps.append((u, rx * -ny + ry * nx))
        if level is None:
            # the levels from the starting lines, by linear least squares
            A = np.concatenate([Je[:, 3:9] for Je in jac])
            level = np.linalg.solve(A.T @ A, A.T @ np.concatenate([y for _, y in bands]))
        for i, ((_, y), Je) in enumerate(zip(bands, jac, strict=True)):
            u, perp = steps[i]
            C = Je[:, 3:6] @ level[3:]
            r = y - Je[:, 3:9] @ level
            rss += float(r @ r)
            g = C * np.exp(-0.5 * u * u) / (_SQRT_2PI * w[i])  # dI / d(distance)
            Je[:, 0] = g * perp
            Je[:, 1] = -g
            Je[:, 2] = -g * u
            H[np.ix_(idx[i], idx[i])] += Je.T @ Je
            b[idx[i]] += Je.T @ r
        try:
            step = np.linalg.solve(H, b)
        except np.linalg.LinAlgError:
            return PhotometricFit(V, np.full((6, 6), np.nan), w, math.nan, m, ok=False)
        for i in range(3):
            th, oo = step[2 * i], step[2 * i + 1]
            cs, sn = math.cos(th), math.sin(th)
            n[i] = [cs * n[i, 0] - sn * n[i, 1], sn * n[i, 0] + cs * n[i, 1]]
            c[i] = c[i] + oo * n[i]
        w = np.maximum(w + step[6:9], 0.2)
        level = level + step[9:15]
        # the residuals after the step, as Gauss-Newton predicts them (the last step is
        # a small one: no pass of its own is needed to measure them)
        rss -= float(step @ b)
    s2 = max(rss, 0.0) / max(m - N_PARAMS, 1)
    try:
        cov_p = s2 * np.linalg.inv(H)[:6, :6]
    except np.linalg.LinAlgError:
        return PhotometricFit(V, np.full((6, 6), np.nan), w, math.nan, m, ok=False)
    V, invs = _intersections(n, c)
    if invs is None:
        return PhotometricFit(V, np.full((6, 6), np.nan), w, math.nan, m, ok=False)
    G = _vertex_gain(n, c, V, invs)
    return PhotometricFit(V, G @ cov_p @ G.T, w, math.sqrt(s2), m)
