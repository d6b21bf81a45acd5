"""Bright spots (LEDs) on a dark frame: threshold, connected components, weighted
centre-of-mass centroids.

STASIS Eq. (21), after Vyas et al. 2009 (its reference [21]): the centroid of a spot is
the mean of its pixel centres weighted by w(I) = I - T, the grey level above the
threshold T, over the connected pixels above T. Subtracting T keeps the faint rim from
pulling the centroid toward the pixel grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

AUTO_THRESHOLD_SIGMAS = 6.0
AUTO_THRESHOLD_MIN = 20.0


@dataclass(frozen=True)
class Spots:
    """Spots found in one image.

    centroids_px : (N, 2) weighted centre of mass (u, v)
    flux : (N,) sum of grey levels above the threshold
    area_px : (N,) pixel count
    elongation : (N,) ratio of the principal axes of the spot's second moments (1 = round)
    saturated : (N,) bool, the spot has pixels at the top of the scale
    threshold : float
    """

    centroids_px: np.ndarray
    flux: np.ndarray
    area_px: np.ndarray
    elongation: np.ndarray
    saturated: np.ndarray
    threshold: float

    def __len__(self) -> int:
        return len(self.centroids_px)


def auto_threshold(image: np.ndarray) -> float:
    """Background median + 6 robust sigmas (from a sparse pixel grid), at least 20."""
    step = max(1, int(np.sqrt(image.size / 20000)))
    sub = image[::step, ::step]
    if sub.dtype == np.uint8:
        # medians from the histogram: the same values, without sorting
        hist = cv2.calcHist([np.ascontiguousarray(sub)], [0], None, [256], [0, 256]).ravel()
        med = _hist_median(hist)
        # |x - med| doubled is an integer (med is a whole or half level)
        dev2 = np.abs(2 * np.arange(256) - int(round(2 * med)))
        mad = _hist_median(np.bincount(dev2, weights=hist, minlength=511)) / 2 * 1.4826
    else:
        sub = sub.astype(np.float32)
        med = float(np.median(sub))
        mad = float(np.median(np.abs(sub - med))) * 1.4826
    return max(med + AUTO_THRESHOLD_SIGMAS * max(mad, 0.5), AUTO_THRESHOLD_MIN)


def _hist_median(hist: np.ndarray) -> float:
    """Median of integer values given their histogram (the mean of the two middle
    values for an even count, as np.median)."""
    c = np.cumsum(hist)
    n = c[-1]
    lo = int(np.searchsorted(c, (n - 1) // 2 + 1))
    hi = int(np.searchsorted(c, n // 2 + 1))
    return 0.5 * (lo + hi)


# frames of at least this many pixels are labelled at half resolution (_max_pool2)
POOLED_MIN_PX = 100_000


# the four pixels of a 2x2 block, from its top left one
_BLOCK_DX = np.array([0, 1, 0, 1])
_BLOCK_DY = np.array([0, 0, 1, 1])


def _max_pool2(binary: np.ndarray) -> np.ndarray:
    """Non-zero where any pixel of a 2x2 block of the 0/255 mask is (an odd last row or
    column kept as its own): the blocks' mean (cv2.resize INTER_AREA), which is at
    least 64 wherever one pixel is set."""
    h, w = binary.shape
    if h % 2 or w % 2:
        binary = np.pad(binary, ((0, h % 2), (0, w % 2)))
        h, w = binary.shape
    return cv2.resize(binary, (w // 2, h // 2), interpolation=cv2.INTER_AREA)


def _moments(img_vals: np.ndarray, xs: np.ndarray, ys: np.ndarray, lab: np.ndarray, n: int,
             area: np.ndarray, keep: np.ndarray, T: float, top: int) -> list[tuple]:  # fmt: skip
    """Each kept component's spot: weighted centroid (u, v; image px), weight, area,
    elongation and whether it saturates, from its pixels (image coordinates ``xs``,
    ``ys``, values ``img_vals``, component ``lab``; ``area`` its pixel count): weighted
    moments of every component at once (bincount)."""
    v = img_vals.astype(np.float64)
    wgt = v - T
    xs = xs.astype(np.float64)
    ys = ys.astype(np.float64)
    sw = np.bincount(lab, wgt, n)
    inv = 1.0 / np.where(sw > 0, sw, 1.0)
    u = np.bincount(lab, wgt * xs, n) * inv
    vv = np.bincount(lab, wgt * ys, n) * inv
    dx, dy = xs - u[lab], ys - vv[lab]
    cxx = np.bincount(lab, wgt * dx * dx, n) * inv
    cyy = np.bincount(lab, wgt * dy * dy, n) * inv
    cxy = np.bincount(lab, wgt * dx * dy, n) * inv
    sat = np.bincount(lab, v >= top, n) > 0
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = np.sqrt(np.clip(tr * tr / 4 - det, 0.0, None))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 1e-12)
    el = np.sqrt(l1 / l2)
    k = np.nonzero(keep)[0]
    return list(zip(u[k], vv[k], sw[k], area[k].astype(float), el[k], sat[k], strict=True))


def _spots_in(roi: np.ndarray, T: float, top: int, min_area: int, max_area: int) -> list[tuple]:
    """Spots of a whole frame."""
    _, binary = cv2.threshold(roi, T, 255, cv2.THRESH_BINARY)
    binary = binary.astype(np.uint8, copy=False)
    h, w = roi.shape
    if h * w < POOLED_MIN_PX:
        nz = cv2.findNonZero(binary)  # far faster than np.nonzero(labels)
        if nz is None:
            return []
        nz = nz.reshape(-1, 2)
        xs, ys = nz[:, 0], nz[:, 1]
        n, labels = cv2.connectedComponentsWithAlgorithm(binary, 8, cv2.CV_32S, cv2.CCL_GRANA)
        lab = labels[ys, xs]
    else:
        # a whole frame: the components of its 2x2 max-pooled mask (a quarter of the
        # pixels to scan and label; a spot stays one, spots 3 px or more apart stay
        # apart), each full-resolution pixel above T found in its block and labelled
        # by it (benchmarks/lamps.py, speed)
        pooled = _max_pool2(binary)
        nzp = cv2.findNonZero(pooled)
        if nzp is None:
            return []
        n, labels = cv2.connectedComponentsWithAlgorithm(pooled, 8, cv2.CV_32S, cv2.CCL_GRANA)
        nzp = nzp.reshape(-1, 2)
        xs = ((nzp[:, 0:1] << 1) + _BLOCK_DX).ravel()
        ys = ((nzp[:, 1:2] << 1) + _BLOCK_DY).ravel()
        inside = (xs < w) & (ys < h)  # an odd last row or column's padding
        xs, ys = xs[inside], ys[inside]
        on = binary[ys, xs] != 0
        xs, ys = xs[on], ys[on]
        lab = labels[ys >> 1, xs >> 1]
    area = np.bincount(lab, minlength=n)
    keep = (area >= min_area) & (area <= max_area)
    keep[0] = False
    if not keep.any():
        return []
    return _moments(roi[ys, xs], xs, ys, lab, n, area, keep, T, top)


def _spots_in_windows(image: np.ndarray, regions: list[tuple[int, int, int, int]], T: float,
                      top: int, min_area: int, max_area: int) -> list[tuple]:  # fmt: skip
    """Spots of several windows (x0, y0, x1, y1; clipped, non-empty) at once: the
    windows side by side on one canvas, a column of zeros between two, thresholded and
    labelled in one pass (one call per frame instead of one per window: a tracked
    markers frame has a window per LED). A spot touching its window's edge is left out
    (it may be cut)."""
    widths = [x1 - x0 for x0, _, x1, _ in regions]
    heights = [y1 - y0 for _, y0, _, y1 in regions]
    ox = np.cumsum([0] + [wd + 1 for wd in widths])  # each window's column on the canvas
    canvas = np.zeros((max(heights), int(ox[-1])), image.dtype)
    for (x0, y0, x1, y1), o in zip(regions, ox[:-1].tolist(), strict=False):
        canvas[: y1 - y0, o : o + x1 - x0] = image[y0:y1, x0:x1]
    _, binary = cv2.threshold(canvas, T, 255, cv2.THRESH_BINARY)
    binary = binary.astype(np.uint8, copy=False)
    nz = cv2.findNonZero(binary)
    if nz is None:
        return []
    nz = nz.reshape(-1, 2)
    cx, cy = nz[:, 0], nz[:, 1]
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(
        binary, 8, cv2.CV_32S, cv2.CCL_GRANA
    )
    lab = labels[cy, cx]
    bx, by, bw, bh, area = stats.T
    win = np.searchsorted(ox, bx, side="right") - 1  # each component's window
    win = np.clip(win, 0, len(regions) - 1)
    wx = ox[win]
    wd = np.array(widths)[win]
    ht = np.array(heights)[win]
    keep = (area >= min_area) & (area <= max_area)
    keep &= (bx > wx) & (by > 0) & (bx + bw < wx + wd) & (by + bh < ht)
    keep[0] = False
    if not keep.any():
        return []
    k = win[lab]
    x0s = np.array([r[0] for r in regions])
    y0s = np.array([r[1] for r in regions])
    xs = cx - ox[k] + x0s[k]
    ys = cy + y0s[k]
    return _moments(canvas[cy, cx], xs, ys, lab, n, area, keep, T, top)


def find_spots(
    image: np.ndarray,
    threshold: float = 0.0,
    min_area: int = 3,
    max_area: int = 400,
    windows: list[tuple[int, int, int, int]] | None = None,
) -> Spots:
    """Spots of ``min_area``..``max_area`` pixels above ``threshold`` (0 = automatic).

    Parameters
    ----------
    image : (H, W) uint8 or uint16 ndarray
    windows : list of (x0, y0, x1, y1), optional
        Search only these windows (tracking: around the predicted markers); spots that
        touch a window's edge are left out (they may be cut).
    """
    T = float(threshold) if threshold > 0 else auto_threshold(image)
    top = 255 if image.dtype == np.uint8 else 65535
    h, w = image.shape
    if windows is None:
        out = _spots_in(image, T, top, min_area, max_area)
    else:
        regions = []
        for x0, y0, x1, y1 in windows:
            x0, y0 = max(int(x0), 0), max(int(y0), 0)
            x1, y1 = min(int(x1), w), min(int(y1), h)
            if x1 - x0 >= 3 and y1 - y0 >= 3:
                regions.append((x0, y0, x1, y1))
        out = _spots_in_windows(image, regions, T, top, min_area, max_area) if regions else []
    if not out:
        z = np.zeros(0)
        return Spots(np.zeros((0, 2)), z, z, z, np.zeros(0, bool), T)
    a = np.array(out, dtype=float)
    # the same spot found in two overlapping windows counts once: a spot within 0.5 px
    # of one kept before it is dropped (the pairs' distances at once; the loop only
    # over the spots that have such a pair)
    keep = np.ones(len(a), bool)
    close = np.triu(np.hypot(a[:, None, 0] - a[None, :, 0], a[:, None, 1] - a[None, :, 1]) < 0.5, 1)
    for i in np.flatnonzero(close.any(axis=1)):
        if keep[i]:
            keep[close[i]] = False
    a = a[keep]
    return Spots(a[:, :2], a[:, 2], a[:, 3], a[:, 4], a[:, 5].astype(bool), T)
