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
frames in tests/detect/test_stars.py).

Pixel convention: (0, 0) is the centre of the top-left pixel (docs/reference.md,
Conventions). Tools that put (0, 0) at the pixel's corner (tetra3, cedar-solve) report
coordinates 0.5 px larger.
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
STREAK_GAP_PX = 3
LINE_WIDTH_PX = 6


@dataclass(frozen=True)
class StarField:
    """Stars of one frame.

    centroids_px : (N, 2) (u, v); flux : (N,) signal above threshold; area_px : (N,);
    peak_snr : (N,) peak above the threshold in units of the noise sigma;
    usable : whether the frame is a star field; reason : why not ("" when usable);
    noise_sigma, bright_fraction, compact_fraction : the statistics behind the verdict.
    threshold : the mu + 3 sigma threshold of the background-removed image.
    signal : (H, W) float32 grey levels above the threshold, zero below (the paper's
        background-removed image, which the rate pipeline matches stars on).
    bbox_px : (N, 4) int x, y, width, height of each star's pixels.
    windowed : (N,) bool, True where the centroid and flux are already those of the
        star's window (its box plus the flow margin, centred on it): the rate
        pipeline's tracked stars.
    spread : (N,) for windowed stars, the centroid's variance per unit pixel-noise
        variance (px^2; see visvec.detect.flow.window_centroid).
    saturated_fraction : fraction of pixels at the image's top grey level.
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
    threshold: float = 0.0
    signal: np.ndarray | None = None
    bbox_px: np.ndarray | None = None
    windowed: np.ndarray | None = None
    spread: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.centroids_px)


def background(img: np.ndarray) -> np.ndarray:
    """Smooth background (float32): median of the 4x shrunk image, blurred, enlarged
    back. All in floating point: a background rounded to whole grey levels would make
    the residual whole numbers and quantise its MAD (sigma exactly 1.48 or 2.97)."""
    h, w = img.shape
    f = 4 if min(h, w) >= 64 else 1
    small = cv2.resize(img.astype(np.float32), (w // f, h // f), interpolation=cv2.INTER_AREA)
    bg = cv2.blur(cv2.medianBlur(small, 5), (7, 7))
    return cv2.resize(bg, (w, h), interpolation=cv2.INTER_LINEAR)


STATS_SAMPLES = 10_000


def _robust_stats(sub: np.ndarray) -> tuple[float, float]:
    """Median and MAD sigma of a sample of residual pixels (about STATS_SAMPLES on a
    regular grid: sigma to about 1 %, at a fraction of the cost of all pixels)."""
    med = float(np.median(sub))
    return med, 1.4826 * float(np.median(np.abs(sub - med)))


@dataclass(frozen=True)
class Residual:
    """A frame with its background removed and thresholded (Fasano et al., Sec. 2.1):
    ``sig`` (float32) is the grey level above the mu + 3 sigma ``threshold``, zero
    below it; ``sigma`` is the noise."""

    sig: np.ndarray
    sigma: float
    threshold: float


def residual(image: np.ndarray, bg: np.ndarray | None = None) -> Residual:
    """Background-removed image of a grey (or colour) frame of any integer/float type;
    ``bg`` is a background to reuse (from :func:`background` of a recent frame), else
    the frame's own is computed. The noise and the threshold are always the frame's:
    from a grid of pixels first, then one pass over the frame subtracts background and
    threshold together and clips at zero."""
    img = image
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if bg is None:
        bg = background(img)
    step = max(1, int(np.sqrt(img.size / STATS_SAMPLES)))
    med, sigma = _robust_stats(img[::step, ::step].astype(np.float32) - bg[::step, ::step])
    sigma = max(sigma, 1e-3 * max(float(img.max()), 1.0), 1e-6)
    T = med + THRESHOLD_SIGMAS * sigma
    if img.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
        img = img.astype(np.float32)
    r = cv2.subtract(img, bg + np.float32(T), dtype=cv2.CV_32F)
    cv2.threshold(r, 0.0, 0.0, cv2.THRESH_TOZERO, dst=r)  # signal above the threshold
    return Residual(r, sigma, T)


@dataclass(frozen=True)
class _Segments:
    cents: np.ndarray
    flux: np.ndarray
    area: np.ndarray
    snr: np.ndarray
    boxes: np.ndarray
    bright_px: int
    compact_px: int
    above_px: int


def segment(res: Residual, streak_px: float = 0.0) -> _Segments:
    """Stars of a background-removed frame (see :func:`segment_edges` for its edges)."""
    return _segment(res.sig, res.sigma, streak_px, 0, 0)


def segment_edges(
    res: Residual, bands: int | tuple[int, int, int, int], streak_px: float = 0.0
) -> _Segments:
    """Stars within the bands along the image's edges, where new stars enter a turning
    camera's view: ``bands`` is one width in px or (top, bottom, left, right).

    The four bands are packed into one small image (the side bands transposed, a blank
    row between bands) so that one labelling pass serves them all. The side bands run
    the full height, so a star in a corner lies whole in a side band even where it
    straddles the end of the top or bottom band; one found whole in both is kept once.
    Stars cut by a band's inner edge are left out (they are inside the frame, tracked
    or found by the next full search)."""
    sig = res.sig
    h, w = sig.shape
    if isinstance(bands, int | np.integer):
        bands = (int(bands),) * 4
    bt, bb, bl, br = (int(np.clip(b, 1, d // 3)) for b, d in zip(bands, (h, h, w, w), strict=True))
    parts = [  # (pixels, x0, y0, transposed, cut side: 1 = far end of rows, 0 = row 0)
        (sig[:bt, :], 0, 0, False, 1),
        (sig[h - bb :, :], 0, h - bb, False, 0),
        (sig[:, :bl].T, 0, 0, True, 1),
        (sig[:, w - br :].T, w - br, 0, True, 0),
    ]
    canvas = np.zeros((bt + bb + bl + br + 3, max(w, h)), np.float32)
    rows = []
    y = 0
    for p, *_ in parts:
        canvas[y : y + p.shape[0], : p.shape[1]] = p
        rows.append(y)
        y += p.shape[0] + 1
    seg = _segment(canvas, res.sigma, streak_px, 0, 0)
    keep = []
    cents, boxes = seg.cents.copy(), seg.boxes.copy()
    for k, (c, bx) in enumerate(zip(seg.cents, seg.boxes, strict=True)):
        i = max(j for j in range(4) if rows[j] <= bx[1])
        p, x0, y0, transposed, far = parts[i]
        ly = bx[1] - rows[i]
        inner = ly + bx[3] >= p.shape[0] if far else ly == 0
        if transposed:
            # canvas (x, y) in the band is (v, u - x0) of the frame
            cents[k] = (c[1] - rows[i] + x0, c[0])
            boxes[k] = (ly + x0, bx[0], bx[3], bx[2])
            top, bottom = bx[0], bx[0] + bx[2]
            inner |= bottom < bt or top > h - bb  # kept whole by the top or bottom band
        else:
            cents[k] = (c[0], c[1] - rows[i] + y0)
            boxes[k] = (bx[0], ly + y0, bx[2], bx[3])
        if not inner:
            keep.append(k)
    keep_a = np.array(keep, dtype=int)
    return _Segments(
        cents[keep_a], seg.flux[keep_a], seg.area[keep_a], seg.snr[keep_a],
        boxes[keep_a], seg.bright_px, seg.compact_px, seg.above_px,
    )  # fmt: skip


def _segment(r: np.ndarray, sigma: float, streak_px: float, x_off: int, y_off: int) -> _Segments:
    """Stars of a signal image ``r`` (zero below the threshold); coordinates offset."""
    binary = (r > 0).view(np.uint8)
    # Grana's block-based labelling is about 3x faster than OpenCV's default here, on a
    # frame sprinkled with single noise pixels above the threshold
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(
        binary, 8, cv2.CV_32S, cv2.CCL_GRANA
    )
    cents, flux, area, snr, boxes = [], [], [], [], []
    big = np.nonzero(stats[1:, 4] >= MIN_AREA_PX)[0] + 1  # Fasano et al.: >= 3 px
    if streak_px > 0:
        # a satellite or meteor trail is a long thin line: neither a star nor the clutter
        # of a non-sky scene, so it does not count against the star-field verdict
        length = np.maximum(stats[big, 2], stats[big, 3])
        line = (length > streak_px + 8) & (stats[big, 4] <= LINE_WIDTH_PX * length)
        big = big[~line]
    bright_total = int(stats[big, 4].sum())
    compact_total = 0
    max_area = MAX_AREA_PX * (1.0 + streak_px / 4.0)
    groups = _streak_groups(stats, big) if streak_px > 0 else [[k] for k in big]
    for g in groups:
        x0, y0 = stats[g, 0].min(), stats[g, 1].min()
        x1, y1 = (stats[g, 0] + stats[g, 2]).max(), (stats[g, 1] + stats[g, 3]).max()
        x, y, bw, bh, a = x0, y0, x1 - x0, y1 - y0, int(stats[g, 4].sum())
        if a > max_area:
            continue
        if streak_px <= 0:
            if max(bw, bh) > 3 * min(bw, bh) + 2 or a / (bw * bh) < 0.4:
                continue  # extended or straggly: not a star
        elif max(bw, bh) > streak_px + 8 or min(bw, bh) > 12 and a / (bw * bh) < 0.25:
            continue  # longer than a star's streak can be, or a straggly blob
        lab = labels[y : y + bh, x : x + bw]
        m = lab == g[0] if len(g) == 1 else np.isin(lab, g)
        wgt = r[y : y + bh, x : x + bw] * m
        s = float(wgt.sum())
        cents.append(
            (
                float(wgt.sum(axis=0) @ np.arange(x, x + bw)) / s + x_off,
                float(wgt.sum(axis=1) @ np.arange(y, y + bh)) / s + y_off,
            )
        )
        flux.append(s)
        area.append(a)
        snr.append(float(wgt.max()) / sigma)
        boxes.append((x + x_off, y + y_off, bw, bh))
        compact_total += int(stats[g, 4][stats[g, 4] >= MIN_AREA_PX].sum())
    return _Segments(
        np.array(cents).reshape(-1, 2),
        np.array(flux),
        np.array(area, dtype=int),
        np.array(snr),
        np.array(boxes, dtype=int).reshape(-1, 4),
        bright_total,
        compact_total,
        int(cv2.countNonZero(binary)),
    )


def find_stars(image: np.ndarray, streak_px: float = 0.0) -> StarField:
    """Stars in a grey (H, W) image of any integer or float type (colour is converted).

    ``streak_px``: the longest streak a star may make during the exposure (the camera's
    fastest expected rate times the exposure); spots up to that much longer than a round
    star are kept as stars, longer ones (a satellite, a meteor) are not.
    """
    return stars_of(residual(image), streak_px)


def stars_of(res: Residual, streak_px: float = 0.0) -> StarField:
    """The stars of a background-removed frame, with the star-field verdict."""
    seg = segment(res, streak_px)
    frac = seg.above_px / res.sig.size
    compact = seg.compact_px / seg.bright_px if seg.bright_px else 0.0
    snr_a = seg.snr
    p90 = float(np.percentile(snr_a, 90)) if len(snr_a) else 0.0
    reason = ""
    if len(snr_a) < MIN_STARS:
        reason = "too_few_stars"
    elif frac > MAX_BRIGHT_FRACTION:
        reason = "not_a_star_field"  # too much of the frame is bright
    elif compact < MIN_COMPACT_FRACTION:
        reason = "not_a_star_field"  # bright areas are extended, not point-like
    elif p90 < MIN_PEAK_SNR_P90 / (1.0 + streak_px / 4.0):
        reason = "not_a_star_field"  # no clearly peaked point sources
    return StarField(
        seg.cents,
        seg.flux,
        seg.area,
        snr_a,
        reason == "",
        reason,
        res.sigma,
        frac,
        compact,
        threshold=res.threshold,
        signal=res.sig,
        bbox_px=seg.boxes,
    )


def _streak_groups(stats: np.ndarray, big: np.ndarray) -> list[list[int]]:
    """Labels grouped into streaks: a faint streak breaks into pieces on the threshold,
    each with a wrong centroid, so pieces (of 2 px or more) whose boxes come within
    STREAK_GAP_PX of a star's box are joined to it (union-find on box overlap)."""
    cand = np.nonzero(stats[1:, 4] >= 2)[0] + 1
    if len(cand) == 0:
        return []
    g = STREAK_GAP_PX
    x0 = stats[cand, 0] - g
    y0 = stats[cand, 1] - g
    x1 = stats[cand, 0] + stats[cand, 2] + g
    y1 = stats[cand, 1] + stats[cand, 3] + g
    near = (
        (x0[:, None] < x1[None, :])
        & (x0[None, :] < x1[:, None])
        & (y0[:, None] < y1[None, :])
        & (y0[None, :] < y1[:, None])
    )
    parent = np.arange(len(cand))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(near, 1)), strict=True):
        a, b = find(i), find(j)
        if a != b:
            parent[b] = a
    roots: dict[int, list[int]] = {}
    for i in range(len(cand)):
        roots.setdefault(find(i), []).append(int(cand[i]))
    is_big = set(big.tolist())
    # a group counts only if it holds a piece of at least MIN_AREA_PX (the paper's rule)
    return [grp for grp in roots.values() if any(k in is_big for k in grp)]
