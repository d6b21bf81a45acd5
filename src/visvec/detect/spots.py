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
    sub = image[::step, ::step].astype(np.float32)
    med = float(np.median(sub))
    mad = float(np.median(np.abs(sub - med))) * 1.4826
    return max(med + AUTO_THRESHOLD_SIGMAS * max(mad, 0.5), AUTO_THRESHOLD_MIN)


def _measure(patch: np.ndarray, mask: np.ndarray, T: float, x0: int, y0: int, top: int):
    w = (patch.astype(np.float64) - T) * mask
    s = w.sum()
    ys, xs = np.mgrid[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]]
    u = (w * xs).sum() / s
    v = (w * ys).sum() / s
    cxx = (w * (xs - u) ** 2).sum() / s
    cyy = (w * (ys - v) ** 2).sum() / s
    cxy = (w * (xs - u) * (ys - v)).sum() / s
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 + disc, max(tr / 2 - disc, 1e-12)
    sat = bool(np.any(patch[mask > 0] >= top))
    return u, v, s, float(np.sqrt(l1 / l2)), sat


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
    regions = windows or [(0, 0, w, h)]
    out = []
    for x0, y0, x1, y1 in regions:
        x0, y0 = max(int(x0), 0), max(int(y0), 0)
        x1, y1 = min(int(x1), w), min(int(y1), h)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        roi = image[y0:y1, x0:x1]
        _, binary = cv2.threshold(roi, T, 255, cv2.THRESH_BINARY)
        if not binary.any():
            continue
        n, labels, stats, _ = cv2.connectedComponentsWithStats(binary.astype(np.uint8), 8)
        for k in range(1, n):
            bx, by, bw, bh, area = stats[k]
            if area < min_area or area > max_area:
                continue
            if windows is not None and (
                bx == 0 or by == 0 or bx + bw == x1 - x0 or by + bh == y1 - y0
            ):
                continue
            mask = (labels[by : by + bh, bx : bx + bw] == k).astype(np.float64)
            u, v, s, el, sat = _measure(
                roi[by : by + bh, bx : bx + bw], mask, T, x0 + bx, y0 + by, top
            )
            out.append((u, v, s, area, el, sat))
    if not out:
        z = np.zeros(0)
        return Spots(np.zeros((0, 2)), z, z, z, np.zeros(0, bool), T)
    a = np.array(out, dtype=float)
    # the same spot found in two overlapping windows counts once
    keep = np.ones(len(a), bool)
    for i in range(len(a)):
        if keep[i]:
            d = np.hypot(a[i + 1 :, 0] - a[i, 0], a[i + 1 :, 1] - a[i, 1])
            keep[i + 1 :][d < 0.5] = False
    a = a[keep]
    return Spots(a[:, :2], a[:, 2], a[:, 3], a[:, 4], a[:, 5].astype(bool), T)
