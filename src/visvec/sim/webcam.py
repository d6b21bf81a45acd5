"""What a webcam does to the light between the lens and the frame visvec reads.

visvec's renderer gives the exposure E at every pixel (linear, grey levels 0-255 for a
white that just fills the sensor). A webcam does not deliver E: it delivers a Bayer
mosaic's three colour channels, each with its own sensitivity and the shot noise of its
photo-electrons, darkened toward the corners (vignetting), scaled by a gain that
breathes from frame to frame (auto exposure, mains flicker), with a few hot pixels,
the red and blue images a little larger and smaller than the green (lateral chromatic
aberration), demosaiced, white-balanced, passed through a tone curve (sRGB) and
compressed as Motion-JPEG. `through_webcam` applies that chain, in that order, and
returns the grey frame visvec reads (OpenCV's BGR-to-grey of the decoded colour image).

Every step has a default a usual USB webcam would have and can be set or switched off
(`WebcamChain`; `visvec simulate --webcam`, `--webcam-set KEY=VALUE`).

The noise model is the usual one of image sensors (EMVA Standard 1288, Release 4.0,
2021, Sec. 2: photo-electrons Poisson with mean the signal, plus a read noise, then a
system gain); the sRGB transfer function is IEC 61966-2-1's; demosaicing is OpenCV's
bilinear (cv2.COLOR_Bayer*2BGR), as cheap webcams' own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import cv2
import numpy as np

# the Bayer pattern's channel at each (row % 2, col % 2): RGGB, as most webcam sensors
_RGGB = ((0, 1), (1, 2))  # (R, G), (G, B) as channel indices 0 R, 1 G, 2 B


@dataclass(frozen=True)
class WebcamChain:
    """The steps from exposure to frame, each with a webcam's usual value; 0 (or False)
    switches a step off.

    Attributes
    ----------
    vignetting : float
        Relative darkening at the image's corners (E falls as 1 - v (r / r_corner)^2).
    gain_sigma : float
        1-sigma of the frame's gain, relative (auto exposure breathing, mains flicker).
    electrons_at_white : float
        Photo-electrons of a pixel at E = 255 (green): the shot noise's scale.
    read_noise_e : float
        Read noise, electrons (1-sigma).
    sensitivity_r, sensitivity_b : float
        The red and blue pixels' response to grey light, relative to green's (white
        balance takes them back, with their noise).
    bayer : bool
        A Bayer (RGGB) mosaic, demosaiced bilinearly; off: every pixel sees all three.
    chromatic_aberration : float
        Lateral chromatic aberration: the red image scaled by 1 + ca about the centre,
        the blue by 1 - ca (at 640x480, 0.0008 moves a corner's red by 0.32 px).
    hot_pixels : float
        Share of pixels stuck high (the same pixels every frame of a camera).
    srgb : bool
        The sRGB tone curve (IEC 61966-2-1) from linear to 8-bit; off: linear.
    jpeg_quality : int
        Motion-JPEG quality (1-100); 0: none.
    seed : int
        The camera's own fixed pattern (its hot pixels).
    """

    vignetting: float = 0.25
    gain_sigma: float = 0.01
    electrons_at_white: float = 6000.0
    read_noise_e: float = 6.0
    sensitivity_r: float = 0.55
    sensitivity_b: float = 0.75
    bayer: bool = True
    chromatic_aberration: float = 0.0008
    hot_pixels: float = 1e-4
    srgb: bool = True
    jpeg_quality: int = 85
    seed: int = 1

    def with_settings(self, settings: dict[str, str]) -> WebcamChain:
        """The chain with ``settings`` (KEY: VALUE text, as `--webcam-set KEY=VALUE`)
        applied; off, no, false and 0 switch a step off.

        Raises
        ------
        ValueError
            An unknown key, or a value that is not one the step takes (naming both).
        """
        kinds = {f.name: f.type for f in fields(self)}
        out = {}
        for key, text in settings.items():
            if key not in kinds:
                raise ValueError(f"webcam setting {key!r}: expected one of {sorted(kinds)}")
            t = text.strip().lower()
            off = t in ("off", "no", "false", "0")
            kind = kinds[key]
            try:
                if kind == "bool":
                    if not off and t not in ("on", "yes", "true", "1"):
                        raise ValueError
                    v: object = not off
                elif kind == "int":
                    v = 0 if off else int(t)
                else:
                    v = 0.0 if off else float(t)
                    if not math.isfinite(v):
                        raise ValueError
            except ValueError:
                raise ValueError(f"webcam setting {key}={text!r}: expected a {kind} "
                                 "(or off)") from None  # fmt: skip
            out[key] = v
        chain = replace(self, **out)
        chain.check()
        return chain

    def check(self) -> None:
        """Refuse values no camera has (ValueError naming the setting)."""
        bad = [
            ("vignetting", not 0.0 <= self.vignetting < 1.0, "in [0, 1)"),
            ("gain_sigma", not 0.0 <= self.gain_sigma < 0.5, "in [0, 0.5)"),
            ("electrons_at_white", self.electrons_at_white < 0.0, ">= 0 (0: no shot noise)"),
            ("read_noise_e", self.read_noise_e < 0.0, ">= 0"),
            ("sensitivity_r", not 0.05 <= self.sensitivity_r <= 2.0, "in [0.05, 2]"),
            ("sensitivity_b", not 0.05 <= self.sensitivity_b <= 2.0, "in [0.05, 2]"),
            ("chromatic_aberration", abs(self.chromatic_aberration) > 0.01, "within 0.01"),
            ("hot_pixels", not 0.0 <= self.hot_pixels <= 0.01, "in [0, 0.01]"),
            ("jpeg_quality", not 0 <= self.jpeg_quality <= 100, "in 0..100 (0: none)"),
        ]  # fmt: skip
        for name, wrong, want in bad:
            if wrong:
                raise ValueError(f"webcam setting {name} = {getattr(self, name)!r}: "
                                 f"expected {want}")  # fmt: skip


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's transfer function: linear [0, 1] to encoded [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(v: float) -> float:
    """The inverse: an encoded level [0, 1] to linear [0, 1]."""
    v = min(max(v, 0.0), 1.0)
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def _radial_scale(img: np.ndarray, s: float) -> np.ndarray:
    """The image magnified by ``s`` about its centre (bilinear)."""
    h, w = img.shape
    M = np.array([[s, 0.0, (1.0 - s) * (w - 1) / 2.0], [0.0, s, (1.0 - s) * (h - 1) / 2.0]])
    return cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def through_webcam(E: np.ndarray, chain: WebcamChain, rng: np.random.Generator) -> np.ndarray:
    """The 8-bit grey frame a webcam makes of the exposure ``E`` (H, W; linear, 255 a
    white that fills a green pixel), the chain's steps in the module doc's order."""
    E = np.asarray(E, np.float64)
    h, w = E.shape
    yy, xx = np.mgrid[0:h, 0:w]
    if chain.vignetting:
        r2 = ((xx - (w - 1) / 2.0) ** 2 + (yy - (h - 1) / 2.0) ** 2) / (
            ((w - 1) / 2.0) ** 2 + ((h - 1) / 2.0) ** 2
        )
        E = E * (1.0 - chain.vignetting * r2)
    gain = 1.0 + chain.gain_sigma * rng.standard_normal() if chain.gain_sigma else 1.0
    sens = (chain.sensitivity_r, 1.0, chain.sensitivity_b)
    planes = []
    for c in range(3):
        Ec = E
        if chain.chromatic_aberration and c != 1:
            Ec = _radial_scale(E, 1.0 + (chain.chromatic_aberration if c == 0
                                         else -chain.chromatic_aberration))  # fmt: skip
        planes.append(Ec * sens[c])
    if chain.bayer:
        chan = np.empty((h, w), np.int64)
        for dy in (0, 1):
            for dx in (0, 1):
                chan[dy::2, dx::2] = _RGGB[dy][dx]
        raw = np.choose(chan, planes)
        resp = np.choose(chan, sens)
    else:
        raw = np.stack(planes, axis=-1)
        resp = np.array(sens)
    # photo-electrons (Poisson, as a Gaussian of its variance) and read noise, then the
    # system gain back to grey levels; the sensor clips at full well
    fw = chain.electrons_at_white
    if fw > 0:
        e = raw / 255.0 * fw
        e = e + rng.standard_normal(e.shape) * np.sqrt(np.maximum(e, 0.0))
        if chain.read_noise_e:
            e = e + rng.standard_normal(e.shape) * chain.read_noise_e
        raw = e / fw * 255.0
    raw = np.clip(raw * gain, 0.0, 255.0 * np.max(resp))
    if chain.hot_pixels:
        fixed = np.random.default_rng(chain.seed)
        n = max(1, int(round(chain.hot_pixels * h * w)))
        ys, xs = fixed.integers(0, h, n), fixed.integers(0, w, n)
        raw[ys, xs] = 255.0 * np.max(resp)
    if chain.bayer:
        raw16 = np.clip(np.rint(raw / (255.0 * max(sens)) * 65535.0), 0, 65535).astype(np.uint16)
        # an RGGB mosaic: OpenCV names it by its second row (BayerBG), in RGB order
        rgb = cv2.cvtColor(raw16, cv2.COLOR_BayerBG2RGB).astype(np.float64) / 65535.0
        rgb *= 255.0 * max(sens)
    else:
        rgb = raw
    # white balance: each channel back by its sensitivity
    rgb = rgb / np.array(sens)
    lin = np.clip(rgb / 255.0, 0.0, 1.0)
    enc = srgb_encode(lin) if chain.srgb else lin
    bgr = np.clip(np.rint(enc[..., ::-1] * 255.0), 0, 255).astype(np.uint8)
    if chain.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(chain.jpeg_quality)])
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
