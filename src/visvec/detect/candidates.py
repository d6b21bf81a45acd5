"""Coarse search for the triangle: a bright, triangular region enclosed by the dark board.

The paper ran goodFeaturesToTrack over the whole frame, where the board's own corners,
ceiling lights and clutter win over the triangle's corners. Here the triangle is found
first, as a bright connected component at one of several grey-level thresholds (a cheap
maximally-stable-region search), then corners are looked for on it only.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Candidate:
    """A bright triangular region, in full-resolution pixels.

    corners_px : (3, 2) ndarray, vertices of the enclosing triangle
    contour_px : (K, 2) ndarray, outline of the region
    area_px : float, pixel count of the region
    level : float, threshold (grey level) it was found at
    touches_border : bool
    fill : float, area over the area of the minimum enclosing triangle
    tracked : bool, predicted from the last frame rather than found
    """

    corners_px: np.ndarray
    contour_px: np.ndarray
    area_px: float
    level: float
    touches_border: bool
    fill: float
    tracked: bool = False


# Outline simplifications (px) tried in turn when OpenCV's minimum enclosing triangle
# finds none (opencv/opencv#4992: on some hulls, those with nearly collinear points,
# no candidate side passes its validity test; #11116: it can raise instead)
ENCLOSING_RETRY_EPS_PX = (0.1, 0.5, 1.0)


def enclosing_triangle(points: np.ndarray) -> np.ndarray | None:
    """(3, 1, 2) float32 minimum-area triangle enclosing ``points`` (an outline, (K, 1, 2)),
    or None if none is found.

    cv2.minEnclosingTriangle returns no triangle for some point sets (with an area of
    DBL_MAX; OpenCV 5.0.0 did on a 320x240 frame's triangle region whose hull had three
    nearly collinear points, and the detector took the empty result for a triangle and
    raised). Then the convex hull, simplified by a fraction of a pixel, is tried instead:
    its enclosing triangle is within that fraction of the outline's.
    """
    # (int32 or float32 as it comes: findContours' int32 outline is taken as it is, the
    # same triangle as its float32 copy's, 8 us sooner)
    outline = points if points.dtype in (np.int32, np.float32) else points.astype(np.float32)
    hull = None
    for eps in (None, *ENCLOSING_RETRY_EPS_PX):
        pts = outline
        if eps is not None:
            hull = cv2.convexHull(outline.astype(np.float32)) if hull is None else hull
            pts = cv2.approxPolyDP(hull, eps, True)
            if len(pts) < 3:
                return None
        try:
            area, tri = cv2.minEnclosingTriangle(pts)
        except cv2.error:
            continue
        if tri is not None and tri.size == 6 and np.isfinite(area) and area < 1e300:
            return tri.reshape(3, 1, 2).astype(np.float32)
    return None


def _percentiles(image: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """np.percentile (linear interpolation) of a uint8 image, from its histogram (a
    cumulative count instead of a partial sort)."""
    # cv2.calcHist counts in float32, exact to 2^24 pixels; 2-3x faster than np.bincount.
    # The quantiles from the 256 counts in Python's numbers (bisect_right is
    # np.searchsorted's side="right"): the same values in about 0.8 of the time
    cdf = np.cumsum(cv2.calcHist([image], [0], None, [256], [0, 256]).ravel().astype(np.int64))
    cdf = cdf.tolist()
    n = cdf[-1]
    out = []
    for q in qs:
        pos = q / 100.0 * (n - 1)
        k = int(pos)
        v0 = bisect.bisect_right(cdf, k)
        v1 = bisect.bisect_right(cdf, min(k + 1, n - 1))
        out.append(v0 + (pos - k) * (v1 - v0))
    return np.array(out)


def shrink(image: np.ndarray, scale: int) -> np.ndarray:
    """The image area-averaged over ``scale`` x ``scale`` blocks (the last rows and
    columns that do not fill a block dropped), so that pixel (i, j) of the result covers
    full-resolution pixels [scale i, scale (i + 1)).

    Factors of two are taken one halving at a time: cv2.resize's INTER_AREA has a fast
    path for exactly 2x (15 us for 640x480 -> 160x120 in two halvings against 110 us in
    one 4x step).
    """
    h, w = image.shape[:2]
    out = image[: h - h % scale, : w - w % scale]
    while scale > 1:
        f = 2 if scale % 2 == 0 else scale
        out = cv2.resize(out, (out.shape[1] // f, out.shape[0] // f), interpolation=cv2.INTER_AREA)
        scale //= f
    return out


def _levels(small: np.ndarray, n: int) -> np.ndarray:
    lo, hi = (
        _percentiles(small, (1.0, 99.0))
        if small.dtype == np.uint8
        else np.percentile(small, (1.0, 99.0))
    )
    if hi - lo < 4:
        return np.zeros(0)
    # np.linspace(lo, hi, n + 2)[1:-1], the same values, without its wrapper's cost
    return np.arange(1, n + 1) * ((hi - lo) / (n + 1)) + lo


def iter_candidates(
    image: np.ndarray,
    expected_area_px: float,
    *,
    scale: int = 1,
    levels: np.ndarray | None = None,
    n_levels: int = 12,
    area_tol: float = 0.45,
    area_at: Callable[[tuple[float, float]], float] | None = None,
) -> Iterator[Candidate]:
    """Bright triangular components whose area is near ``expected_area_px``.

    Parameters
    ----------
    image : (H, W) uint8 ndarray
    expected_area_px : float
        Area of the triangle in full-resolution pixels at zero attitude.
    scale : int
        Work on the image shrunk by this factor (area averaging), for speed.
    levels : ndarray, optional
        Thresholds to try in this order (grey levels); by default ``n_levels`` spread
        over the histogram, darkest first: the first one above the board's grey level
        cuts the triangle off from everything else (the dark board encloses it), whether
        the ceiling around the board is brighter or darker than the triangle.
    area_tol : float
        Relative tolerance on the area.
    area_at : callable, optional
        The expected area (full-resolution px) of a region centred at pixel (u, v): the
        triangle's area where it falls in the field (a wide lens shows it larger or
        smaller off the boresight); ``expected_area_px`` everywhere without it.

    Yields
    ------
    Candidate, level by level, the most triangular first within a level; the first
    level with candidates is pooled with the next one (see below).
    """
    small = shrink(image, scale)
    a_exp = expected_area_px / scale**2
    a_lo, a_hi = a_exp * (1 - area_tol), a_exp * (1 + area_tol)
    if levels is None:
        levels = _levels(small, n_levels)
    levels = list(levels)
    k = 0
    while k < len(levels):
        found = _at_level(small, levels[k], scale, a_lo, a_hi, area_at, area_tol)
        if found and k + 1 < len(levels):
            # the first level that cuts the triangle off may sit just above the board's
            # grey, where the outline is ragged (noise and blur on the board side) and
            # its enclosing triangle several px off: the next level, nearer the middle of
            # the step, competes on how triangular its region is
            found += _at_level(small, levels[k + 1], scale, a_lo, a_hi, area_at, area_tol)
            k += 1
        k += 1
        found.sort(key=lambda c: (c.touches_border, -c.fill))
        yield from found


def _at_level(
    small: np.ndarray,
    level: float,
    scale: int,
    a_lo: float,
    a_hi: float,
    area_at: Callable[[tuple[float, float]], float] | None = None,
    area_tol: float = 0.45,
) -> list[Candidate]:
    """Bright regions at one threshold whose area is within [a_lo, a_hi] (small px), or
    with ``area_at`` within ``area_tol`` of the area it expects where the region is, and
    that fill at least 0.8 of their minimum enclosing triangle."""
    h, w = small.shape
    # with area_at, first an area no position in the field makes the triangle's (the
    # lens not consulted), then area_at's own
    lo, hi = (a_lo, a_hi) if area_at is None else (0.5 * a_lo, 2.0 * a_hi)
    _, binary = cv2.threshold(small, float(level), 255, cv2.THRESH_BINARY)
    # outer outlines of the 8-connected bright regions, also those inside another
    # region's hole (the triangle on the board in a bright ceiling): RETR_CCOMP puts
    # every outer outline at the top level, holes under them. findContours is ~6x
    # faster than connectedComponentsWithStats here.
    cnts, hierarchy = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    found = []
    # outer outlines (no parent: not a hole's) of 6 points or more; the rest (most of a
    # level near the board's grey: specks of noise) passed over in one comprehension
    parents = hierarchy[0, :, 3].tolist() if cnts else []
    for cnt in [c for c, p in zip(cnts, parents, strict=True) if p < 0 and len(c) >= 6]:
        area_c = cv2.contourArea(cnt)
        # pixels enclosed by the outline, boundary pixels included (Pick's theorem:
        # the outline's B pixels are the polygon's lattice points on its boundary)
        area_px = area_c + 0.5 * len(cnt) + 1.0
        if not lo <= area_px <= hi:
            continue
        x, y, bw, bh = cv2.boundingRect(cnt)
        if area_at is not None:
            centre = ((x + 0.5 * bw) * scale - 0.5, (y + 0.5 * bh) * scale - 0.5)
            a_exp = area_at(centre) / scale**2
            if abs(area_px / a_exp - 1.0) > area_tol:
                continue
        tri = enclosing_triangle(cnt)
        if tri is None:
            continue
        tri_area = abs(cv2.contourArea(tri))
        fill = area_c / tri_area if tri_area > 0 else 0.0
        if fill < 0.8:
            continue
        touches = bool(x == 0 or y == 0 or x + bw == w or y + bh == h)
        found.append(
            Candidate(
                (tri.reshape(3, 2) + 0.5) * scale - 0.5,
                (cnt.reshape(-1, 2) + 0.5) * scale - 0.5,
                float(area_px) * scale**2,
                float(level),
                touches,
                float(fill),
            )
        )
    return found


@dataclass(frozen=True)
class PartialTriangle:
    """A bright region showing a corner of the triangle (see :func:`partial_triangle`).

    outline_px : (K, 2) ndarray, the region's outline (full-resolution px)
    area_px : float, the region's area (full-resolution px)
    step : float, the smaller grey-level step across the corner's two sides
    inside_level : float, mean grey level just inside the corner
    edge_fraction : float, share of the outline (off the image border) with a step of
        at least ``min_step`` across it: low where the threshold crosses a lighting
        gradient on the board, so that the triangle joins a brighter part of it
    """

    outline_px: np.ndarray
    area_px: float
    step: float
    inside_level: float
    edge_fraction: float


def _across(small: np.ndarray, a: np.ndarray, d: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """Mean grey levels 2 px either side (+n, -n) of the segment a -> a + d, at a quarter,
    half and three quarters of its length."""
    h, w = small.shape
    pts = a + np.array([0.25, 0.5, 0.75])[:, None] * d
    ins = np.rint(pts + 2.0 * n).astype(int)
    out = np.rint(pts - 2.0 * n).astype(int)
    both = np.vstack([ins, out])
    if np.any(both < 0) or np.any(both[:, 0] >= w) or np.any(both[:, 1] >= h):
        return 0.0, 0.0
    return float(small[ins[:, 1], ins[:, 0]].mean()), float(small[out[:, 1], out[:, 0]].mean())


def partial_triangle(
    image: np.ndarray,
    angles_deg: np.ndarray,
    sides_px: np.ndarray,
    *,
    scale: int = 1,
    n_levels: int = 12,
    angle_tol_deg: float = 10.0,
    min_side: float = 0.3,
    min_step: float = 4.0,
) -> PartialTriangle | None:
    """A bright region that shows one of the triangle's corners, or None: evidence that
    the triangle is in view but not whole (a person over it, a light touching it, the
    image edge across it) when no region has its shape.

    A corner of the region's outline (polygon approximation at each threshold of
    :func:`iter_candidates`) matches corner i of the triangle when its angle is within
    ``angle_tol_deg`` of ``angles_deg[i]``, both its sides run at least ``min_side`` of
    the shorter of the triangle's sides at that corner (``sides_px[i]`` is the side
    opposite vertex i), and both sides are edges: the wedge between them brighter than
    their outside by at least ``min_step`` grey levels. Outline segments along the image
    border are not sides (the border cuts regions at any angle), nor are the ragged
    outlines a threshold draws across a lighting gradient (no step across them). The
    board's corners (90 degrees, dark inside) and round lights never match the paper's
    triangle (38 and 71 degrees).
    """
    small = shrink(image, scale)
    h, w = small.shape
    sides = np.asarray(sides_px, float) / scale
    need = np.array([min_side * min(sides[(i + 1) % 3], sides[(i + 2) % 3]) for i in range(3)])
    angles = np.asarray(angles_deg, float)
    # brightest level first: the first to show a corner is then nearest the middle of
    # the triangle's step, where its outline is cleanest (just above the board's grey
    # it is ragged)
    min_len = 2.0 * float(need.min())
    for level in _levels(small, n_levels)[::-1]:
        _, binary = cv2.threshold(small, float(level), 255, cv2.THRESH_BINARY)
        # outer outlines and holes: a triangle joined to the ceiling by a person shows
        # its corners on the outline of the board's hole
        cnts, _ = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
        cnts = [c for c in cnts if len(c) >= min_len]
        polys = [cv2.approxPolyDP(c, 1.0, True).reshape(-1, 2) for c in cnts]
        keep = [k for k, q in enumerate(polys) if len(q) >= 3]
        if not keep:
            continue
        # every outline's polygon at once: vertex j's neighbours within its own polygon
        sizes = np.array([len(polys[k]) for k in keep])
        poly = np.concatenate([polys[k] for k in keep]).astype(float)
        owner = np.repeat(np.arange(len(keep)), sizes)
        first = np.repeat(np.cumsum(sizes) - sizes, sizes)
        j_prev = first + (np.arange(len(poly)) - first - 1) % sizes[owner]
        j_next = first + (np.arange(len(poly)) - first + 1) % sizes[owner]
        prev, nxt = poly[j_prev] - poly, poly[j_next] - poly
        lp, ln = np.hypot(prev[:, 0], prev[:, 1]), np.hypot(nxt[:, 0], nxt[:, 1])
        cos = np.einsum("ij,ij->i", prev, nxt) / np.maximum(lp * ln, 1e-9)
        ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        # a segment with both ends on (within a pixel of) the same image border is
        # the border's cut
        on = np.column_stack(
            [poly[:, 0] <= 1, poly[:, 0] >= w - 2, poly[:, 1] <= 1, poly[:, 1] >= h - 2]
        )
        border_next = np.any(on & on[j_next], axis=1)
        border_prev = border_next[j_prev]
        short = np.minimum(lp, ln)
        match = np.any(
            (np.abs(ang[:, None] - angles[None, :]) <= angle_tol_deg)
            & (short[:, None] >= need[None, :]),
            axis=1,
        )
        match &= ~(border_next | border_prev)
        for k in np.flatnonzero(match):
            a, dp, dn = poly[k], prev[k] / lp[k], nxt[k] / ln[k]
            # each side's normal toward the wedge (the other side's direction)
            n_p = np.array([-dp[1], dp[0]])
            n_p *= np.sign(n_p @ dn)
            n_n = np.array([-dn[1], dn[0]])
            n_n *= np.sign(n_n @ dp)
            in_p, out_p = _across(small, a, prev[k], n_p)
            in_n, out_n = _across(small, a, nxt[k], n_n)
            step = min(in_p - out_p, in_n - out_n)
            if step >= min_step:
                cnt = cnts[keep[owner[k]]]
                mine = owner == owner[k]
                return PartialTriangle(
                    (cnt.reshape(-1, 2) + 0.5) * scale - 0.5,
                    abs(cv2.contourArea(cnt)) * scale**2,
                    step,
                    0.5 * (in_p + in_n),
                    _edge_fraction(
                        small, poly[mine], nxt[mine], ln[mine], border_next[mine], min_step
                    ),
                )
    return None


def _edge_fraction(
    small: np.ndarray,
    poly: np.ndarray,
    nxt: np.ndarray,
    ln: np.ndarray,
    border: np.ndarray,
    min_step: float,
) -> float:
    """Share of the length of a polygon's segments (poly[i] -> poly[i] + nxt[i], those
    not along the image ``border``) with a grey-level step of ``min_step`` or more
    across them."""
    total = stepped = 0.0
    for i in np.flatnonzero(~border & (ln >= 1.0)):
        n = np.array([-nxt[i, 1], nxt[i, 0]]) / ln[i]
        a, b = _across(small, poly[i], nxt[i], n)
        total += ln[i]
        stepped += ln[i] * (abs(a - b) >= min_step)
    return stepped / total if total > 0 else 0.0
