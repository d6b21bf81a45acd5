"""Star-field frames from a rotating camera: a random sky, point-spread, smear, noise.

The sky is a random, seeded catalogue with realistic star counts: uniform directions
and magnitudes following N(< m) = 4500 * 3^(m - 6) over the whole sky (about 4500
stars to magnitude 6, so about 40-55 to magnitude 6.2 in a 20-degree field, the count
Fasano et al. (Sensors 2013, Sec. 2.1) assume). A star of magnitude m gives
``flux_m6 * 10^(-0.4 (m - 6))`` grey levels in total over its point-spread per 100 ms of
exposure. The camera turns at a constant rate omega (in C) during a frame, so a star's
image moves during the exposure: the exposure is integrated in sub-steps of at most
0.3 px and a star becomes a streak at high rates. The point-spread is a Gaussian
integrated over each pixel (erf differences). Noise: Poisson shot noise on the signal
and the background (``gain_dn_per_e`` grey levels per electron), Gaussian read noise,
quantisation to 8 bits with saturation at 255.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.rig import Rig
from visvec.rotations import expmap
from visvec.sim.sequence import write_sequence

# Fasano et al. (Sensors 2013), Table 3: rates of the star sensor frame (deg/s)
ORBIT_RATE_DPS = 6.243e-2
PAPER_CASES: dict[int, tuple[float, float, float]] = {
    1: (1.0, -ORBIT_RATE_DPS, 0.0),  # out-of-plane, 1 deg/s
    2: (5.0, -ORBIT_RATE_DPS, 0.0),  # out-of-plane, 5 deg/s
    3: (0.0, -ORBIT_RATE_DPS, -1.0),  # about the boresight, 1 deg/s
    4: (0.0, -ORBIT_RATE_DPS, -5.0),  # about the boresight, 5 deg/s
}
SUBSTEP_PX = 0.3


@dataclass(frozen=True)
class Sky:
    """Star directions ``u_i`` (N, 3) unit vectors in the inertial frame I, and
    magnitudes ``mag`` (N,)."""

    u_i: np.ndarray
    mag: np.ndarray


def make_sky(rng: np.random.Generator, mag_limit: float = 6.2) -> Sky:
    """A random sky to ``mag_limit`` with N(< m) = 4500 * 3^(m - 6) stars."""
    n = int(4500 * 3.0 ** (mag_limit - 6.0))
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    mag = mag_limit + np.log(rng.uniform(size=n)) / np.log(3.0)
    return Sky(v, mag)


@dataclass(frozen=True)
class StarScene:
    """Photometry and noise of simulated star frames.

    exposure_ms : exposure time (the rig's ``[camera] exposure_ms`` when it has one).
    flux_m6 : total grey levels of a magnitude-6 star per 100 ms of exposure.
    psf_sigma_px : Gaussian point-spread sigma (a slightly defocused star tracker).
    background_dn : mean dark + sky level; read_noise_dn : Gaussian read noise sigma.
    gain_dn_per_e : grey levels per photo-electron (sets the shot noise).
    """

    exposure_ms: float = 50.0
    flux_m6: float = 300.0
    psf_sigma_px: float = 1.0
    background_dn: float = 10.0
    read_noise_dn: float = 1.5
    gain_dn_per_e: float = 0.25
    mag_limit: float = 6.2


def _pixel_integrals(centres: np.ndarray, lo: int, n: int, sigma: float) -> np.ndarray:
    """(K, n) fraction of a 1-D Gaussian at each centre falling in pixels lo..lo+n-1
    (pixel p covers [p - 0.5, p + 0.5])."""
    edges = np.arange(lo, lo + n + 1) - 0.5
    from scipy.special import erf

    c = erf((edges[None, :] - centres[:, None]) / (np.sqrt(2.0) * sigma))
    return 0.5 * np.diff(c, axis=1)


def star_image(
    rig: Rig,
    R_ic: np.ndarray,
    w_c: np.ndarray,
    sky: Sky,
    scene: StarScene,
    rng: np.random.Generator,
    extra: Callable[[np.ndarray], None] | None = None,
) -> np.ndarray:
    """One 8-bit frame taken at attitude ``R_ic`` (camera axes in I; mid-exposure) while
    turning at ``w_c`` (rad/s, in C). ``extra`` may add light to the float signal image
    (grey levels) before the noise, for test scenes (a satellite streak, hot pixels)."""
    cam = rig.camera
    h, w = cam.height, cam.width
    T = scene.exposure_ms / 1000.0
    sig = np.zeros((h, w), dtype=np.float64)
    u_c = sky.u_i @ R_ic  # rows: u_C = R_ic^T u_I
    half_fov = np.hypot(w, h) / 2.0 / min(cam.fx, cam.fy) + abs(np.linalg.norm(w_c)) * T
    vis = u_c[:, 2] > np.cos(np.arctan(half_fov) + 0.01)
    smear_px = np.linalg.norm(w_c) * T * min(cam.fx, cam.fy) * (1.0 + half_fov**2)
    k = max(1, int(np.ceil(smear_px / SUBSTEP_PX)))
    ts = (np.arange(k) + 0.5) / k * T - T / 2.0
    # star directions at each sub-step: u_C(t) = exp(-[w]x t) u_C(0)
    rots = np.array([expmap(-w_c * t) for t in ts])  # (k, 3, 3)
    u0 = u_c[vis]
    flux = scene.flux_m6 * (T / 0.1) * 10.0 ** (-0.4 * (sky.mag[vis] - 6.0))
    s = scene.psf_sigma_px
    r = int(np.ceil(4 * s)) + 1
    for j in range(len(u0)):
        uk = rots @ u0[j]  # (k, 3)
        uv = cam.project(uk)  # nan behind the camera or beyond the lens model's field
        if not np.all(np.isfinite(uv)):
            continue
        x0 = int(np.floor(uv[:, 0].min())) - r
        x1 = int(np.ceil(uv[:, 0].max())) + r
        y0 = int(np.floor(uv[:, 1].min())) - r
        y1 = int(np.ceil(uv[:, 1].max())) + r
        if x1 < 0 or y1 < 0 or x0 >= w or y0 >= h:
            continue
        gx = _pixel_integrals(uv[:, 0], x0, x1 - x0 + 1, s)
        gy = _pixel_integrals(uv[:, 1], y0, y1 - y0 + 1, s)
        patch = (gy.T @ gx) * (flux[j] / k)
        ya, xa = max(y0, 0), max(x0, 0)
        yb, xb = min(y1 + 1, h), min(x1 + 1, w)
        sig[ya:yb, xa:xb] += patch[ya - y0 : yb - y0, xa - x0 : xb - x0]
    if extra is not None:
        extra(sig)
    g = scene.gain_dn_per_e
    electrons = rng.poisson((sig + scene.background_dn) / g)
    img = electrons * g + rng.normal(0.0, scene.read_noise_dn, (h, w))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def random_pointing(rng: np.random.Generator) -> np.ndarray:
    """A random camera attitude R_IC (uniform over rotations)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


TRUTH_COLUMNS = ("frame", "file", "time_s", "wx_dps", "wy_dps", "wz_dps")


def simulate_stars(
    rig: Rig,
    out_dir: str | Path,
    n_frames: int,
    rate_dps: tuple[float, float, float],
    *,
    seed: int = 0,
    scene: StarScene | None = None,
    fps: float | None = None,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Render a sequence turning at the constant rate ``rate_dps`` (deg/s, in C) into
    ``out_dir`` with ``truth.csv`` (the rate over the interval ending at each frame).

    Returns the path of truth.csv.
    """
    if scene is None:
        scene = StarScene(exposure_ms=rig.exposure_ms or StarScene.exposure_ms)
    rng = np.random.default_rng(seed)
    sky = make_sky(rng, scene.mag_limit)
    fps = fps or rig.fps
    w_c = np.radians(np.asarray(rate_dps, dtype=float))
    R0 = random_pointing(rng)

    def frame_at(t: float) -> tuple[np.ndarray, list[str]]:
        img = star_image(rig, R0 @ expmap(w_c * t), w_c, sky, scene, rng)
        return img, [f"{x:.9f}" for x in rate_dps]

    return write_sequence(out_dir, TRUTH_COLUMNS, np.arange(n_frames) / fps, frame_at, progress)
