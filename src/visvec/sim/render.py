"""Physically based rendering of the triangle scene seen by the platform camera.

Each pixel's ray is traced through the rig's camera model (distortion included) to
the ceiling plane, shaded, and pixels on a boundary are super-sampled for partial
coverage; then defocus blur, shot and read noise and 8-bit quantisation are applied.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import cv2
import numpy as np

from visvec.camera import CameraModel
from visvec.rig import Rig
from visvec.rotations import expmap
from visvec.shutter import row_times
from visvec.sim.scene import Scene
from visvec.sim.webcam import srgb_decode, through_webcam

# labels of what a ray hits
_CEILING, _BOARD, _TRIANGLE, _LIGHT, _OCCLUDER = 0, 1, 2, 3, 4


@lru_cache(maxsize=4)
def _ray_grid(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float, dist: tuple[float, ...]
) -> np.ndarray:
    """(H + 2, W + 2, 2) normalised undistorted coordinates of pixel centres -1..W."""
    cam = CameraModel(width, height, fx, fy, cx, cy, np.array(dist))
    u, v = np.meshgrid(
        np.arange(-1, width + 1, dtype=float), np.arange(-1, height + 1, dtype=float)
    )
    xy = cam.undistort(np.column_stack([u.ravel(), v.ravel()]))
    return xy.reshape(height + 2, width + 2, 2)


def _rays_at(grid: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of the ray grid at sub-pixel positions (N,) -> (N, 2)."""
    gu, gv = u + 1.0, v + 1.0
    i0 = np.clip(np.floor(gv).astype(int), 0, grid.shape[0] - 2)
    j0 = np.clip(np.floor(gu).astype(int), 0, grid.shape[1] - 2)
    a, b = (gu - j0)[:, None], (gv - i0)[:, None]
    return (
        (1 - a) * (1 - b) * grid[i0, j0]
        + a * (1 - b) * grid[i0, j0 + 1]
        + (1 - a) * b * grid[i0 + 1, j0]
        + a * b * grid[i0 + 1, j0 + 1]
    )


class _Shader:
    """Traces normalised camera rays into the lab and returns (label, radiance)."""

    def __init__(self, rig: Rig, scene: Scene, R_nb: np.ndarray):
        self.scene = scene
        self.R_nc = R_nb @ rig.R_bc
        self.c_n = R_nb @ rig.t_b
        v = rig.target.vertices_mm
        self.z_ceiling = float(v[:, 2].mean())
        self.tri = v[:, :2]
        self.centre = v[:, :2].mean(axis=0)
        # inward edge normals of the triangle in the ceiling plane
        a, b = self.tri[1] - self.tri[0], self.tri[2] - self.tri[0]
        orient = np.sign(a[0] * b[1] - a[1] * b[0])
        self.edges = []
        for i in range(3):
            a, b = self.tri[i], self.tri[(i + 1) % 3]
            t = (b - a) / np.linalg.norm(b - a)
            n = orient * np.array([-t[1], t[0]])
            self.edges.append((n, float(n @ a)))

    def __call__(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sc = self.scene
        d = np.column_stack([xy, np.ones(len(xy))]) @ self.R_nc.T
        dz = d[:, 2]
        up = dz > 1e-9
        s = np.where(up, (self.z_ceiling - self.c_n[2]) / np.where(up, dz, 1.0), np.nan)
        X = self.c_n[0] + s * d[:, 0]
        Y = self.c_n[1] + s * d[:, 1]
        g = sc.gradient_dir
        illum = (
            1.0
            + sc.gradient_per_m
            * ((X - self.centre[0]) * g[0] + (Y - self.centre[1]) * g[1])
            / 1000.0
        )
        label = np.full(len(xy), _CEILING, dtype=np.int8)
        rad = sc.ceiling_level * illum
        bx, by = sc.board_mm[0] / 2, sc.board_mm[1] / 2
        on_board = (np.abs(X - self.centre[0]) <= bx) & (np.abs(Y - self.centre[1]) <= by)
        label[on_board] = _BOARD
        rad = np.where(on_board, sc.board_level * illum, rad)
        if sc.show_triangle:
            inside = np.ones(len(xy), dtype=bool)
            for n, c in self.edges:
                inside &= (n[0] * X + n[1] * Y) >= c
            label[inside] = _TRIANGLE
            rad = np.where(inside, (sc.board_level + sc.contrast) * illum, rad)
        for lamp in sc.lights:
            lit = (X - lamp.x_mm) ** 2 + (Y - lamp.y_mm) ** 2 <= lamp.radius_mm**2
            label[lit] = _LIGHT
            rad = np.where(lit, lamp.level, rad)
        if sc.occluder is not None:
            o = sc.occluder
            so = (o.z_mm - self.c_n[2]) / np.where(up, dz, 1.0)
            Xo = self.c_n[0] + so * d[:, 0]
            Yo = self.c_n[1] + so * d[:, 1]
            rr = (Xo - o.x_mm) ** 2 + (Yo - o.y_mm) ** 2
            hit = up & (so > 0) & (rr <= o.radius_mm**2)
            label[hit] = _OCCLUDER
            # soft shading like a head or shoulder: brighter toward its middle
            rad = np.where(hit, o.level * (1.1 - 0.3 * rr / o.radius_mm**2), rad)
        label[~up] = _CEILING
        rad = np.where(up, rad, 0.0)
        return label, rad


# rows per band of a rolling-shutter frame rendered at one attitude
ROLLING_BAND_ROWS = 4
# motion blur: sub-frames close enough that the image moves at most this between two
# (px), and at most this many
MOTION_STEP_PX = 0.25
MAX_MOTION_SUBFRAMES = 25

# the plastic constant's reciprocals: the R2 sequence's two strides (Roberts 2018), whose
# multiples fill the unit square evenly
_R2 = (0.7548776662466927, 0.5698402909980532)


def subpixel_offsets(
    rows: np.ndarray, cols: np.ndarray, width: int, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """(M, n^2) offsets (u, v) in [-0.5, 0.5) from pixel centres of the sub-pixel rays that
    give pixels (``rows``, ``cols``) their partial coverage.

    A regular n x n grid snaps an edge along a pixel row or column to the nearest of its
    n sub-rows in every pixel of the edge alike: the whole edge drawn up to 1 / (2n) px
    off (0.06 px at n = 8), a bias of the truth, not noise. A 320x240 triangle whose base
    ran along a row read 1.8 sigma off in roll on clean frames, 4.3 sigma when
    over-exposed (the contrast, and with it the sensor's precision, 2.3x higher).
    Instead each pixel takes the n-rooks lattice u = (i + (j + 1/2) / n) / n,
    v = (j + (i + 1/2) / n) / n (n^2 distinct sub-rows and sub-columns: Chiu, Shirley and
    Wang's multi-jittered pattern) shifted modulo the pixel by its own offset (a
    Cranley-Patterson rotation), the R2 sequence over the pixel's index: each sub-ray is
    uniform over its pixel, so a pixel's coverage is unbiased, and along an edge the
    pixels' small errors (under 1 / n^2 of the step for a row or column edge) cancel.
    Deterministic: the same scene renders to the same image.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    lu = ((i + (j + 0.5) / n) / n).ravel()
    lv = ((j + (i + 0.5) / n) / n).ravel()
    k = rows.astype(np.float64) * width + cols
    su = (k * _R2[0]) % 1.0
    sv = (k * _R2[1]) % 1.0
    ou = (lu[None, :] + su[:, None]) % 1.0 - 0.5
    ov = (lv[None, :] + sv[:, None]) % 1.0 - 0.5
    return ou, ov


def render_clean(
    rig: Rig,
    R_nb: np.ndarray,
    scene: Scene,
    readout_ms: float = 0.0,
    omega_b: np.ndarray | None = None,
    exposure_ms: float = 0.0,
) -> np.ndarray:
    """Noise-free radiance image (H, W) float64 of the scene at attitude ``R_nb``.

    Motion blur: with ``exposure_ms`` > 0 (each row's exposure, ms, as the rig's
    [camera] exposure_ms) and a body rate ``omega_b``, each row collects light over its
    exposure, centred on its own time: the mean of sub-frames at attitudes
    R_nb expm([omega_b] tau) over tau in [-exposure / 2, exposure / 2], as many that the
    image moves at most MOTION_STEP_PX between two of them.

    Pixels whose 3x3 neighbourhood holds more than one surface are averaged over
    ``scene.supersample``^2 sub-pixel rays (box pixel response).

    Rolling shutter: with ``readout_ms`` != 0 (negative: the last row read first) and a
    body rate ``omega_b`` (rad/s), row v is exposed (v - cy) / H * readout after the
    centre row, at attitude R_nb expm([omega_b] t) (R_nb is the centre row's); bands of
    ROLLING_BAND_ROWS rows share one attitude (at 20 deg/s and 25 ms the attitude moves
    0.004 deg in a band).
    """
    cam = rig.camera
    exposure_s = exposure_ms / 1000.0
    if exposure_s > 0 and omega_b is not None and np.any(omega_b):
        w = np.asarray(omega_b, float)
        # the image moves fastest at the corners: f (1 + (r/f)^2) per rad across the
        # boresight, r per rad about it (camera axes)
        w_c = np.abs(rig.R_bc.T @ w) if rig.mount.on == "platform" else np.abs(w)
        f = max(cam.fx, cam.fy)
        r = float(np.hypot(max(cam.cx, cam.width - cam.cx), max(cam.cy, cam.height - cam.cy)))
        travel_px = exposure_s * (float(np.hypot(w_c[0], w_c[1])) * (f + r * r / f) + w_c[2] * r)
        n = int(np.clip(np.ceil(travel_px / MOTION_STEP_PX), 1, MAX_MOTION_SUBFRAMES))
        taus = ((np.arange(n) + 0.5) / n - 0.5) * exposure_s
        return np.mean(
            [render_clean(rig, R_nb @ expmap(w * tau), scene, readout_ms, w) for tau in taus],
            axis=0,
        )
    grid = _ray_grid(
        cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, tuple(float(k) for k in cam.dist)
    )
    rolling = readout_ms != 0 and omega_b is not None and np.any(omega_b)
    bands = range(0, cam.height, ROLLING_BAND_ROWS) if rolling else [0]  # first row of each band
    band_h = ROLLING_BAND_ROWS if rolling else cam.height
    shaders = []
    for r0 in bands:
        R = R_nb
        if rolling:
            row = r0 + 0.5 * (min(band_h, cam.height - r0) - 1)  # the band's middle row
            t = float(row_times(np.array([row]), cam, readout_ms)[0])
            R = R_nb @ expmap(np.asarray(omega_b, float) * t)
        shaders.append(_Shader(rig, scene, R))
    centres = grid[1:-1, 1:-1]
    img = np.empty((cam.height, cam.width))
    label = np.empty((cam.height, cam.width), np.int8)
    for r0, shade in zip(bands, shaders, strict=True):
        rows = slice(r0, r0 + band_h)
        lab, rad = shade(centres[rows].reshape(-1, 2))
        label[rows] = lab.reshape(-1, cam.width)
        img[rows] = rad.reshape(-1, cam.width)
    lab8 = label.astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    mixed = cv2.dilate(lab8, k) != cv2.erode(lab8, k)
    rows, cols = np.nonzero(mixed)
    n = max(1, int(scene.supersample))
    if len(rows) and n > 1:
        ou, ov = subpixel_offsets(rows, cols, cam.width, n)
        band_of = rows // band_h
        for b in np.unique(band_of):
            sel = band_of == b
            su = (cols[sel][:, None] + ou[sel]).ravel()
            sv = (rows[sel][:, None] + ov[sel]).ravel()
            _, srad = shaders[b](_rays_at(grid, su, sv))
            img[rows[sel], cols[sel]] = srad.reshape(-1, n * n).mean(axis=1)
    return img


def _linear_scene(scene: Scene) -> Scene:
    """The scene with its output grey levels taken back through the tone curve to the
    linear exposures that give them (the webcam chain's sRGB curve, where it has one)."""
    web = scene.webcam

    def lin(v: float) -> float:
        if web is not None:
            return 255.0 * srgb_decode(max(v, 0.0) / 255.0) if web.srgb else v
        return 255.0 * (max(v, 0.0) / 255.0) ** scene.tone_gamma

    board = lin(scene.board_level)
    return replace(
        scene,
        board_level=board,
        contrast=lin(scene.board_level + scene.contrast) - board,
        ceiling_level=lin(scene.ceiling_level),
        lights=tuple(replace(li, level=lin(li.level)) for li in scene.lights),
        occluder=None
        if scene.occluder is None
        else replace(scene.occluder, level=lin(scene.occluder.level)),
    )


def render_frame(
    rig: Rig,
    R_nb: np.ndarray,
    scene: Scene,
    rng: np.random.Generator | int | None = None,
    readout_ms: float = 0.0,
    omega_b: np.ndarray | None = None,
    exposure_ms: float = 0.0,
) -> np.ndarray:
    """One 8-bit grey frame (H, W) of the scene at attitude ``R_nb``.

    Parameters
    ----------
    rig : Rig
        Camera model, mount and target (the *true* geometry of the simulated lab).
    R_nb : (3, 3) ndarray
        True attitude.
    scene : Scene
        Photometry, clutter and noise.
    rng : numpy Generator or seed
        Source of the noise.
    readout_ms, omega_b : float, (3,) ndarray
        A rolling shutter's readout time (ms) and the platform's body rate (rad/s): see
        :func:`render_clean` (R_nb is then the attitude when the centre row is exposed).
    exposure_ms : float
        Each row's exposure time (ms, as the rig's [camera] exposure_ms): motion blur
        while the platform turns.

    Returns
    -------
    ndarray of uint8, shape (H, W)
        The grey frame (the rig's camera's size), through the scene's blur, noise and,
        with ``scene.webcam``, a webcam's image chain.

    Examples
    --------
    >>> from visvec.api import Scene, load_rig, render_frame
    >>> rig = load_rig("configs/triangle.toml")  # doctest: +SKIP
    >>> render_frame(rig, np.eye(3), Scene(), rng=1).shape  # doctest: +SKIP
    (480, 640)
    """
    rng = np.random.default_rng(rng)
    g = scene.tone_gamma
    linear = scene if g == 1.0 and scene.webcam is None else _linear_scene(scene)
    img = render_clean(rig, R_nb, linear, readout_ms, omega_b, exposure_ms) * scene.exposure
    if scene.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), scene.blur_sigma_px)
    if scene.webcam is not None:
        # a webcam's own chain: its noise, tone curve and compression (visvec.sim.webcam)
        return through_webcam(img, scene.webcam, rng)
    if g != 1.0:
        # the tone curve, after the sensor clips (noise is output-referred here)
        img = 255.0 * (np.clip(img, 0.0, 255.0) / 255.0) ** (1.0 / g)
    if scene.shot_gain > 0:
        # shot noise: variance = signal * gain (grey levels^2)
        img = img + rng.standard_normal(img.shape) * np.sqrt(np.maximum(img, 0.0) * scene.shot_gain)
    if scene.noise_sigma > 0:
        img = img + rng.standard_normal(img.shape) * scene.noise_sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
