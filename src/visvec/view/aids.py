"""Set-up aids for a person aiming and focusing a camera: what the image's grey levels
do, how sharp the target's edges are, and how close the target comes to the border.

All of it is computed from a frame the sensor has already finished with, in the live
view's own thread, at most as often as the page shows a frame."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# the image's histogram, in this many bins of 256 grey levels
HIST_BINS = 64
# the sharpness is measured on this share of the region's strongest gradients: the
# target's edges, not the flat inside or the background
EDGE_SHARE = 0.02
# a region around the target this many pixels wider than its points on every side
REGION_PAD_PX = 12


@dataclass(frozen=True)
class Aids:
    """What the page shows beside the frame.

    histogram : HIST_BINS counts of the grey levels (shares of the pixels)
    clipped : share of the pixels at the top of the scale (255)
    dark : share of the pixels at 0
    sharpness : the target's edge sharpness, the strongest grey-level gradients over the
        region's contrast (1/px: about 1 / the edge's blur width; higher is sharper);
        nan without a target
    margin_px : the target's nearest point to the image border (px; negative: out of
        view); nan without a target
    points : how many of the target's points were found
    """

    histogram: list[float]
    clipped: float
    dark: float
    sharpness: float
    margin_px: float
    points: int

    def as_dict(self) -> dict[str, object]:
        def f(x: float) -> float | None:
            return None if not np.isfinite(x) else round(float(x), 4)

        return {
            "histogram": [round(h, 5) for h in self.histogram],
            "clipped": round(self.clipped, 6),
            "dark": round(self.dark, 6),
            "sharpness": f(self.sharpness),
            "margin_px": f(self.margin_px),
            "points": self.points,
        }


def target_points(det: object | None) -> np.ndarray:
    """(N, 2) pixel points of a detection: a triangle's vertices, the identified spots
    of markers or lamps, the stars of a star field; empty without one."""
    if det is None:
        return np.empty((0, 2))
    pts = getattr(det, "points_px", None)
    if pts is not None:
        pts = np.asarray(pts, float).reshape(-1, 2)
        return pts[np.all(np.isfinite(pts), axis=1)]
    spots = getattr(det, "spots", None)
    if spots is not None:
        ids = np.asarray(getattr(det, "ids", np.zeros(0)))
        c = np.asarray(spots.centroids_px, float).reshape(-1, 2)
        return c[ids >= 0] if len(ids) == len(c) else c
    stars = getattr(det, "stars", None)
    if stars is not None:
        return np.asarray(stars.centroids_px, float).reshape(-1, 2)
    return np.empty((0, 2))


def edge_sharpness(image: np.ndarray, pts: np.ndarray) -> float:
    """The strongest gradients (the top EDGE_SHARE) in the region around ``pts`` over
    the region's contrast (its 99th less its 1st percentile grey level): a sharp step
    of any contrast reads about 1 / the blur's width in px."""
    if len(pts) == 0:
        return float("nan")
    h, w = image.shape[:2]
    lo = np.floor(pts.min(axis=0) - REGION_PAD_PX).astype(int)
    hi = np.ceil(pts.max(axis=0) + REGION_PAD_PX).astype(int)
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return float("nan")
    roi = image[y0:y1, x0:x1].astype(np.float32)
    gx = cv2.Sobel(roi, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(roi, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    g = np.sqrt(gx * gx + gy * gy).ravel()
    lo_g, hi_g = np.percentile(roi, (1.0, 99.0))
    contrast = float(hi_g - lo_g)
    if contrast < 2.0:
        return float("nan")
    k = max(1, int(EDGE_SHARE * g.size))
    top = np.partition(g, g.size - k)[g.size - k :]
    return float(np.mean(top) / contrast)


def border_margin(pts: np.ndarray, width: int, height: int) -> float:
    """The nearest point's distance to the image border (px)."""
    if len(pts) == 0:
        return float("nan")
    u, v = pts[:, 0], pts[:, 1]
    return float(np.min(np.minimum.reduce([u, v, width - 1 - u, height - 1 - v])))


def aids(image: np.ndarray, det: object | None) -> Aids:
    """The set-up aids of one grey frame and its detection."""
    hist = cv2.calcHist([image], [0], None, [HIST_BINS], [0, 256]).ravel()
    n = max(float(image.size), 1.0)
    pts = target_points(det)
    h, w = image.shape[:2]
    return Aids(
        histogram=(hist / n).tolist(),
        clipped=float(np.count_nonzero(image >= 255)) / n,
        dark=float(np.count_nonzero(image == 0)) / n,
        sharpness=edge_sharpness(image, pts),
        margin_px=border_margin(pts, w, h),
        points=len(pts),
    )
