"""Rendering of LED markers seen by the camera fixed in the lab (STASIS-like frames).

Each LED is a point source blurred by a Gaussian point-spread function and integrated
exactly over each pixel's area (differences of the normal CDF), on a near-black
background (an 11 us exposure: everything but the LEDs stays below a few grey levels),
with shot and read noise, 8-bit saturation and optional stray reflections (dimmer
spots from LED light bouncing off the platform).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.geometry import markers_to_camera
from visvec.rig import Rig


@dataclass(frozen=True)
class SpotScene:
    """Photometry of a marker frame (grey levels 0..255).

    psf_sigma_px : Gaussian point-spread sigma.
    flux : total signal of one LED (grey levels x pixels); a peak of about
        flux / (2 pi psf^2) before saturation.
    flux_spread : relative LED-to-LED brightness variation (uniform +-).
    background, noise_sigma : dark level and read noise.
    shot_gain : grey levels per electron (0 = no shot noise).
    reflections : number of stray spots (a fraction of an LED's flux each).
    hidden : marker ids not drawn (occluded or dead LEDs).
    """

    psf_sigma_px: float = 1.2
    flux: float = 2500.0
    flux_spread: float = 0.2
    background: float = 2.0
    noise_sigma: float = 1.0
    shot_gain: float = 0.1
    reflections: int = 0
    hidden: tuple[int, ...] = ()


def add_spot(img: np.ndarray, u: float, v: float, flux: float, sigma: float) -> None:
    """Add a pixel-integrated Gaussian spot of total ``flux`` centred at (u, v) in place."""
    h, w = img.shape
    r = int(np.ceil(5 * sigma)) + 1
    x0, x1 = max(int(np.floor(u)) - r, 0), min(int(np.floor(u)) + r + 2, w)
    y0, y1 = max(int(np.floor(v)) - r, 0), min(int(np.floor(v)) + r + 2, h)
    if x0 >= x1 or y0 >= y1:
        return
    xs = np.arange(x0, x1 + 1) - 0.5  # pixel edges; pixel centres are integers
    ys = np.arange(y0, y1 + 1) - 0.5
    from scipy.special import ndtr

    fx = np.diff(ndtr((xs - u) / sigma))
    fy = np.diff(ndtr((ys - v) / sigma))
    img[y0:y1, x0:x1] += flux * np.outer(fy, fx)


def render_markers(
    rig: Rig, R_nb: np.ndarray, scene: SpotScene, rng: np.random.Generator | int | None = None
) -> np.ndarray:
    """One 8-bit frame (H, W) of the rig's LEDs at attitude ``R_nb``."""
    rng = np.random.default_rng(rng)
    cam = rig.camera
    img = np.zeros((cam.height, cam.width))
    uv = cam.project(markers_to_camera(rig, R_nb, rig.target.points_b))
    for k, (u, v) in enumerate(uv):
        if k in scene.hidden or not np.isfinite(u):
            continue
        f = scene.flux * (1.0 + scene.flux_spread * rng.uniform(-1.0, 1.0))
        add_spot(img, u, v, f, scene.psf_sigma_px)
    for _ in range(scene.reflections):
        add_spot(
            img,
            rng.uniform(0, cam.width),
            rng.uniform(0, cam.height),
            scene.flux * rng.uniform(0.3, 0.8),
            scene.psf_sigma_px * rng.uniform(1, 2),
        )
    if scene.shot_gain > 0:
        img += rng.standard_normal(img.shape) * np.sqrt(img * scene.shot_gain)
    img += scene.background + rng.standard_normal(img.shape) * scene.noise_sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
