"""Stars in a frame, and whether the frame is a usable star field at all.

After Fasano et al. (Sensors 2013), Sec. 3.1: the background is removed with a global
mu + 3 sigma threshold and the connected stars of at least 3 pixels are kept. Beyond the
paper: a smooth background (median of a 4x shrunk image, blurred) is subtracted first so
that a sky glow or vignetting does not bias the threshold, sigma is the robust (MAD)
spread of the residual, and centroids are weighted centres of mass with weights = signal
above the threshold (as for the LED markers).

A frame is a usable star field when its bright pixels are mostly compact, point-like
spots on a dark background: few pixels above the threshold (at most 3 %), at least
70 % of them in compact spots, a few spots with a clear peak (the 90th-percentile peak at
least 15 sigma above the threshold) and at least 5 spots. A photo of a tree against the
sky or of a roof fails these; a real sky, even with a comet, passes (tested on real
frames in tests/test_stars.py).

Pixel convention: (0, 0) is the centre of the top-left pixel (SPEC). Tools that put
(0, 0) at the pixel's corner (tetra3, cedar-solve) report coordinates 0.5 px larger.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

THRESHOLD_SIGMAS = 3.0  # Fasano et al.: mu + 3 sigma
MIN_AREA_PX = 3  # Fasano et al.: stars under 3 pixels are dropped
MAX_AREA_PX = 150
MAX_BRIGHT_FRACTION = 0.03
MIN_COMPACT_FRACTION = 0.7
MIN_PEAK_SNR_P90 = 15.0
MIN_STARS = 5


@dataclass(frozen=True)
class StarField:
    """Stars of one frame.

    centroids_px : (N, 2) (u, v); flux : (N,) signal above threshold; area_px : (N,);
    peak_snr : (N,) peak above the threshold in units of the noise sigma;
    usable : whether the frame is a star field; reason : why not ("" when usable);
    noise_sigma, bright_fraction, compact_fraction : the statistics behind the verdict.
    """

    centroids_px: np.ndarray
    flux: np.ndarray
    area_px: np.ndarray
    peak_snr: np.ndarray
    usable: bool
    reason: str
    noise_sigma: float
    bright_fraction: float
    compact_fraction: float

    def __len__(self) -> int:
        return len(self.centroids_px)


def background(img: np.ndarray) -> np.ndarray:
    """Smooth background: median of the 4x shrunk image, blurred, enlarged back."""
    h, w = img.shape
    f = 4 if min(h, w) >= 64 else 1
    small = cv2.resize(img, (w // f, h // f), interpolation=cv2.INTER_AREA)
    bg = cv2.blur(cv2.medianBlur(small, 5), (7, 7))
    return cv2.resize(bg, (w, h), interpolation=cv2.INTER_LINEAR)


def find_stars(image: np.ndarray) -> StarField:
    """Stars in a grey (H, W) image of any integer or float type (colour is converted)."""
    img = image
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    img = img.astype(np.float32)
    r = img - background(img)
    med = float(np.median(r))
    sigma = 1.4826 * float(np.median(np.abs(r - med)))
    sigma = max(sigma, 1e-3 * max(float(img.max()), 1.0), 1e-6)
    T = med + THRESHOLD_SIGMAS * sigma
    binary = (r > T).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    cents, flux, area, snr = [], [], [], []
    bright_total = 0
    compact_total = 0
    for k in range(1, n):
        x, y, bw, bh, a = stats[k]
        if a < MIN_AREA_PX:
            continue
        bright_total += a
        if a > MAX_AREA_PX or max(bw, bh) > 3 * min(bw, bh) + 2 or a / (bw * bh) < 0.4:
            continue  # extended or straggly: not a star
        compact_total += a
        m = labels[y : y + bh, x : x + bw] == k
        wgt = (r[y : y + bh, x : x + bw] - T) * m
        s = float(wgt.sum())
        ys, xs = np.mgrid[y : y + bh, x : x + bw]
        cents.append(((wgt * xs).sum() / s, (wgt * ys).sum() / s))
        flux.append(s)
        area.append(a)
        snr.append(float(wgt.max()) / sigma)
    frac = float(binary.mean())
    compact = compact_total / bright_total if bright_total else 0.0
    snr_a = np.array(snr)
    p90 = float(np.percentile(snr_a, 90)) if len(snr_a) else 0.0
    reason = ""
    if len(snr_a) < MIN_STARS:
        reason = "too_few_stars"
    elif frac > MAX_BRIGHT_FRACTION:
        reason = "not_a_star_field"  # too much of the frame is bright
    elif compact < MIN_COMPACT_FRACTION:
        reason = "not_a_star_field"  # bright areas are extended, not point-like
    elif p90 < MIN_PEAK_SNR_P90:
        reason = "not_a_star_field"  # no clearly peaked point sources
    return StarField(
        np.array(cents).reshape(-1, 2),
        np.array(flux),
        np.array(area),
        snr_a,
        reason == "",
        reason,
        sigma,
        frac,
        compact,
    )
