"""Star displacements between two frames by region matching.

Fasano et al. (Sensors 2013), Sec. 2.1, Eqs. (1)-(2): for each star of the first
(background-removed) image, the integer shift minimising the sum of squared differences
between a window around the star and the second image (cv2.matchTemplate, TM_SQDIFF),
then the centroid of the second image in a window of the star's shape plus a 2 px
margin placed at that shift.

Beyond the paper: the search is centred on a predicted position (from the last rate
when tracking, else from a first rate fitted to the brightest stars searched over the
whole range), so that most stars need a window a few pixels wide rather than the full
range; and a match must carry the star's light (flux ratio within a factor of 2) to
count.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from visvec.detect.stars import Residual, StarField

MARGIN_PX = 2  # Fasano et al.: the star's window plus a 2 px margin
FLUX_RATIO_MAX = 2.0


@dataclass(frozen=True)
class Matches:
    """Matched stars: ``uv1`` (N, 2) centroids in the first frame, ``uv2`` (N, 2) in
    the second, ``index`` (N,) the star's index in the first frame's StarField,
    ``flux2`` (N,) signal of the star in the second frame,
    ``bbox2`` (N, 4) the star's box (x, y, w, h) moved to where it matched,
    ``spread1``, ``spread2`` (N,) each centroid's variance per unit pixel-noise variance
    (see :func:`window_centroid`)."""

    uv1: np.ndarray
    uv2: np.ndarray
    index: np.ndarray
    flux2: np.ndarray
    bbox2: np.ndarray
    spread1: np.ndarray
    spread2: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


def signal(res: Residual) -> np.ndarray:
    """The image above the threshold (zero elsewhere), float32: the paper's
    background-removed image."""
    return res.sig


def window_centroid(sig: np.ndarray, x0: int, y0: int, x1: int, y1: int, spread: bool = True):
    """(u, v, flux, spread) of the signal in the window [x0, x1) x [y0, y1), or None if
    the window leaves the image or holds no signal; spread (see :func:`lit_spread`) is
    NaN when not asked for."""
    h, w = sig.shape
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return None
    win = sig[y0:y1, x0:x1]
    m = cv2.moments(win)
    s = m["m00"]
    if s <= 0:
        return None
    cu, cv = m["m10"] / s, m["m01"] / s  # in the window
    sp = lit_spread(win, cu, cv, s) if spread else np.nan
    return cu + x0, cv + y0, s, sp


def lit_spread(win: np.ndarray, cu: float, cv: float, flux: float) -> float:
    """sum((x - u)^2 + (y - v)^2) / flux^2 over the lit pixels of a window whose centroid
    is (cu, cv) in window coordinates: the centroid's variance (px^2, both axes
    together) per unit pixel-noise variance, from d u / d w_i = (x_i - u) / flux for the
    centre of mass u = sum(w_i x_i) / sum(w_i). Pixels below the threshold are clipped
    to zero, so only lit pixels pass noise on."""
    b = cv2.moments((win > 0).view(np.uint8), binaryImage=True)
    n = b["m00"]
    du, dv = b["m10"] / n - cu, b["m01"] / n - cv  # lit pixels' centre vs centroid
    return (b["mu20"] + b["mu02"] + n * (du * du + dv * dv)) / (flux * flux)


def centred_centroid(sig: np.ndarray, x0: int, y0: int, w: int, h: int):
    """:func:`window_centroid` of a w x h window moved once to be centred on the
    centroid found in it: a window left off-centre cuts more of the star on one side
    and pulls the centroid toward its own centre (a bias that builds up when windows
    are carried from frame to frame). Returns (u, v, flux, spread, x0, y0) or None."""
    c = window_centroid(sig, x0, y0, x0 + w, y0 + h, spread=False)
    if c is None:
        return None
    nx = int(round(c[0] - (w - 1) / 2.0))
    ny = int(round(c[1] - (h - 1) / 2.0))
    if (nx, ny) != (x0, y0):
        c2 = window_centroid(sig, nx, ny, nx + w, ny + h)
        if c2 is not None:
            return (*c2, nx, ny)
    sp = lit_spread(sig[y0 : y0 + h, x0 : x0 + w], c[0] - x0, c[1] - y0, c[2])
    return (*c[:3], sp, x0, y0)


def match_stars(
    first: StarField,
    sig1: np.ndarray,
    sig2: np.ndarray,
    shift_px: np.ndarray,
    radius_px: np.ndarray,
    which: np.ndarray | None = None,
) -> Matches:
    """Match stars of the first frame into the second.

    Parameters
    ----------
    first : StarField of the first frame (its ``bbox_px`` give the windows).
    sig1, sig2 : :func:`signal` images of the two frames.
    shift_px : (N, 2) predicted displacement (u, v) of each star (zeros when unknown).
    radius_px : (N,) int half-width of the search around the prediction.
    which : indices of the stars to match (all by default).
    """
    idx = np.arange(len(first)) if which is None else np.asarray(which, dtype=int)
    m = MARGIN_PX
    h, w = sig2.shape
    uv1, uv2, keep, fl2, box2, sp1, sp2 = [], [], [], [], [], [], []
    for i in idx:
        x, y, bw, bh = (int(a) for a in first.bbox_px[i])
        tx0, ty0, tx1, ty1 = x - m, y - m, x + bw + m, y + bh + m
        if first.windowed is not None and first.windowed[i]:  # measured in this window
            c1 = (*first.centroids_px[i], first.flux[i], first.spread[i], tx0, ty0)
        else:
            c1 = centred_centroid(sig1, tx0, ty0, tx1 - tx0, ty1 - ty0)
        if c1 is None:
            continue
        r = int(radius_px[i])
        dx, dy = (int(round(a)) for a in shift_px[i])
        sx0, sy0 = tx0 + dx - r, ty0 + dy - r
        sx1, sy1 = tx1 + dx + r, ty1 + dy + r
        if sx0 < 0 or sy0 < 0 or sx1 > w or sy1 > h:
            continue  # the search would leave the image: the star may be leaving it
        tmpl = sig1[ty0:ty1, tx0:tx1]
        ssd = cv2.matchTemplate(sig2[sy0:sy1, sx0:sx1], tmpl, cv2.TM_SQDIFF)
        _, _, (bx, by), _ = cv2.minMaxLoc(ssd)
        ox, oy = sx0 + bx, sy0 + by  # the template's top-left corner in frame 2
        c2 = centred_centroid(sig2, ox, oy, tx1 - tx0, ty1 - ty0)
        if c2 is None:
            continue
        ratio = c2[2] / c1[2]
        if not 1.0 / FLUX_RATIO_MAX <= ratio <= FLUX_RATIO_MAX:
            continue  # the window holds another star, part of one, or noise
        uv1.append(c1[:2])  # fmt: skip
        uv2.append(c2[:2])
        keep.append(i)
        fl2.append(c2[2])
        sp1.append(c1[3])
        sp2.append(c2[3])
        box2.append((c2[4] + m, c2[5] + m, bw, bh))
    return Matches(
        np.array(uv1).reshape(-1, 2),
        np.array(uv2).reshape(-1, 2),
        np.array(keep, dtype=int),
        np.array(fl2),
        np.array(box2, dtype=int).reshape(-1, 4),
        np.array(sp1),
        np.array(sp2),
    )
