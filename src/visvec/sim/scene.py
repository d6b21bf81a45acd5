"""What a simulated ceiling looks like, apart from the rig itself."""

from __future__ import annotations

from dataclasses import dataclass, field

from visvec.sim.webcam import WebcamChain


@dataclass(frozen=True)
class Light:
    """A round ceiling light in a simulated frame.

    Attributes
    ----------
    x_mm, y_mm : float
        Its centre on the ceiling plane (mm, lab axes n1, n2).
    radius_mm : float
        Its radius (mm).
    level : float
        Its grey level (0..255).
    """

    x_mm: float
    y_mm: float
    radius_mm: float = 120.0
    level: float = 255.0


@dataclass(frozen=True)
class Occluder:
    """Something between camera and ceiling (a person leaning over): a disc.

    Attributes
    ----------
    x_mm, y_mm : float
        Its centre (mm, lab axes n1, n2).
    z_mm : float
        Its height in N (mm).
    radius_mm : float
        Its radius (mm).
    level : float
        Its grey level (0..255).
    """

    x_mm: float
    y_mm: float
    z_mm: float = 1300.0
    radius_mm: float = 250.0
    level: float = 120.0


@dataclass(frozen=True)
class Scene:
    """Photometry and clutter of a simulated frame (grey levels 0..255).

    Attributes
    ----------
    board_mm : (along n1, along n2) size of the black board, centred on the triangle.
    board_level, contrast : board grey level, and the triangle's step above it.
    ceiling_level : grey level of the ceiling around the board.
    gradient_per_m : relative change of illumination per metre along ``gradient_dir``.
    noise_sigma : Gaussian read noise (grey levels).
    shot_gain : grey levels per photo-electron; > 0 adds shot noise (0 = none).
    blur_sigma_px : Gaussian defocus blur.
    exposure : multiplies every radiance before clipping (over-exposure > 1).
    show_triangle : False renders the board without a triangle.
    tone_gamma : the camera's tone curve, grey = 255 (E / 255)^(1 / tone_gamma) for the
        linear exposure E (1: linear; about 2.2 for most webcams). The grey levels above
        (board, contrast, ceiling, lights, occluder) are those of the output; the optics
        (coverage, gradient, blur, exposure) act on the linear E.
    webcam : a webcam's image chain (visvec.sim.webcam.WebcamChain: Bayer mosaic,
        sensor noise, vignetting, gain, chromatic aberration, hot pixels, sRGB, JPEG)
        in place of noise_sigma, shot_gain and tone_gamma; None: the plain render.
    """

    board_mm: tuple[float, float] = (1219.2, 914.4)
    board_level: float = 70.0
    contrast: float = 28.0
    ceiling_level: float = 150.0
    gradient_per_m: float = 0.15
    gradient_dir: tuple[float, float] = (0.6, 0.8)
    noise_sigma: float = 2.0
    shot_gain: float = 0.0
    blur_sigma_px: float = 0.6
    exposure: float = 1.0
    show_triangle: bool = True
    lights: tuple[Light, ...] = field(default_factory=tuple)
    occluder: Occluder | None = None
    supersample: int = 8
    tone_gamma: float = 1.0
    webcam: WebcamChain | None = None
