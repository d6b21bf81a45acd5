"""Simulation of the lamps rig: the ceiling seen from the moving mock-up, the mock-up's
path (pushed by hand around the table perimeter, as in the LuVeX experiments of Keldysh
preprint 2011-24, Fig. 7) and its IMU (one gyro, a two-axis accelerometer; Sec. 3).

Frames: each lamp is a small disc (its image a Gaussian of the disc's and the lens's
spread, integrated over each pixel) drawn at several instants across the exposure, so
that a moving mock-up smears it; a dim ceiling with a lighting gradient, shot and read
noise, 8-bit saturation and optional spurious bright spots (reflections, other lights).

IMU: the body-frame specific force and rate along the path, with constant biases, white
noise (the paper's accelerometer: sigma 0.002 m/s^2) and occasional faults (spikes far
beyond the paper's 0.5 m/s^2 and 50 deg/s limits).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.estimate.planar import lamps_to_camera
from visvec.rig import Rig
from visvec.sim.markers import add_spot
from visvec.sim.sequence import write_sequence

TRUTH_COLUMNS = ("frame", "file", "time_s", "x_mm", "y_mm", "heading_deg")
IMU_COLUMNS = ("time_s", "gz_dps", "ax_mps2", "ay_mps2")
IMU_TRUTH_COLUMNS = ("frame", "time_s", "x_mm", "y_mm", "heading_deg")


@dataclass(frozen=True)
class LampScene:
    """Photometry of a lamp frame (grey levels 0..255).

    lamp_diameter_mm : the lamps' size; psf_sigma_px : lens blur.
    flux : total signal of one lamp (grey levels x pixels), flux_spread its relative
        lamp-to-lamp variation; ceiling, gradient : the ceiling's grey level and its
        change across the frame; noise_sigma, shot_gain : read noise, grey levels per
        electron; exposure_ms : exposure (motion smear); spurious : extra bright spots
        per frame, as a fraction of the lamps in view; hidden : lamp indices not lit.
    """

    lamp_diameter_mm: float = 20.0
    psf_sigma_px: float = 0.8
    flux: float = 1500.0
    flux_spread: float = 0.15
    ceiling: float = 18.0
    gradient: float = 8.0
    noise_sigma: float = 1.5
    shot_gain: float = 0.1
    exposure_ms: float = 10.0
    spurious: float = 0.0
    hidden: tuple[int, ...] = ()


@dataclass(frozen=True)
class PerimeterPath:
    """A mock-up pushed by hand around a table: a rounded rectangle (x = a tanh(k cos th)
    / tanh(k), y likewise with sin; semi-axes a_mm, b_mm, centred at centre_mm) at a
    speed that surges and slows with the pushes, the heading turning with the path and
    swaying.

    ``at(t)`` gives (x_mm, y_mm, heading_rad); ``rest`` gives a still mock-up;
    ``rest_s`` keeps it still at the start (for the IMU's bias calibration at rest).
    """

    a_mm: float = 1600.0
    b_mm: float = 900.0
    centre_mm: tuple[float, float] = (0.0, 0.0)
    squareness: float = 2.0
    lap_s: float = 90.0
    surge: float = 0.35  # speed variation of the pushes (relative)
    push_s: float = 6.0
    sway_deg: float = 8.0
    sway_s: float = 11.0
    heading0_deg: float = 20.0
    rest: bool = False
    rest_s: float = 0.0  # still for this long, then eased into the motion over 4 s
    ease_s: float = 4.0

    def at(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if self.rest_s > 0:
            u = np.clip(t - self.rest_s, 0.0, None)
            t = np.where(u < self.ease_s, u * u / (2 * self.ease_s), u - self.ease_s / 2)
        if self.rest:
            z = np.zeros_like(t)
            return np.stack(
                [z + self.centre_mm[0], z + self.centre_mm[1], z + np.radians(self.heading0_deg)],
                axis=-1,
            )
        w = 2 * np.pi / self.lap_s
        th = w * t + self.surge * (self.push_s / self.lap_s) * np.sin(2 * np.pi * t / self.push_s)
        c, s = np.cos(th), np.sin(th)
        k = self.squareness
        x = self.centre_mm[0] + self.a_mm * np.tanh(k * c) / np.tanh(k)
        y = self.centre_mm[1] + self.b_mm * np.tanh(k * s) / np.tanh(k)
        psi = (
            np.radians(self.heading0_deg)
            + th
            + np.radians(self.sway_deg) * np.sin(2 * np.pi * t / self.sway_s)
        )
        return np.stack([x, y, psi], axis=-1)

    def derivatives(self, t: np.ndarray, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """Velocity (mm/s, rad/s) and acceleration (mm/s^2) by central differences."""
        p0, pm, pp = self.at(t), self.at(t - h), self.at(t + h)
        return (pp - pm) / (2 * h), (pp - 2 * p0 + pm) / h**2


def render_lamps(
    rig: Rig,
    path: Callable[[np.ndarray], np.ndarray],
    t: float,
    scene: LampScene,
    rng: np.random.Generator,
) -> np.ndarray:
    """One 8-bit frame of the ceiling lamps from the mock-up at time ``t`` (the middle
    of the exposure), smeared by the motion during the exposure."""
    cam = rig.camera
    lamps = rig.target.lamps.xyz_mm
    h, w = cam.height, cam.width
    img = np.zeros((h, w))
    n_sub = 9
    exp_s = scene.exposure_ms / 1000.0
    times = t + (np.arange(n_sub) + 0.5 - n_sub / 2) / n_sub * exp_s
    poses = path(times)
    flux = scene.flux * (1.0 + scene.flux_spread * rng.uniform(-1.0, 1.0, len(lamps)))
    lit = np.ones(len(lamps), bool)
    lit[list(scene.hidden)] = False
    p_mid = lamps_to_camera(rig, path(np.array([t]))[0], lamps)
    in_view = lit & (p_mid[:, 2] > 0)
    uv_mid = cam.project(p_mid[in_view])
    view = np.zeros(len(lamps), bool)
    view[np.nonzero(in_view)[0]] = cam.in_image(uv_mid, -20.0)
    for pose in poses:
        p = lamps_to_camera(rig, pose, lamps[view])
        uv = cam.project(p)
        sig_disc = scene.lamp_diameter_mm / 4.0 * cam.fx / p[:, 2]  # a disc's rms radius
        sig = np.sqrt(sig_disc**2 + scene.psf_sigma_px**2)
        for (u, v), f, s in zip(uv, flux[view], sig, strict=True):
            if np.isfinite(u):  # nan: beyond the lens model's field
                add_spot(img, u, v, f / n_sub, s)
    n_in = int(np.sum(cam.in_image(cam.project(p_mid[in_view]), 0.0)))
    n_spur = rng.poisson(scene.spurious * n_in) if scene.spurious > 0 else 0
    for _ in range(n_spur):
        add_spot(
            img, rng.uniform(5, w - 5), rng.uniform(5, h - 5),
            scene.flux * rng.uniform(0.5, 1.0), scene.psf_sigma_px * rng.uniform(1.0, 2.5),
        )  # fmt: skip
    if scene.shot_gain > 0:
        img += rng.standard_normal(img.shape) * np.sqrt(img * scene.shot_gain)
    ramp = np.linspace(-0.5, 0.5, w)[None, :] + np.linspace(-0.3, 0.3, h)[:, None]
    img += scene.ceiling + scene.gradient * ramp
    img += rng.standard_normal(img.shape) * scene.noise_sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def lamps_in_view(
    rig: Rig, pose: np.ndarray, margin_px: float = 5.0, hidden: tuple[int, ...] = ()
) -> int:
    """How many lit lamps of the map the camera sees at ``pose`` (at least ``margin_px``
    inside the image, as the lamp pipeline uses them)."""
    lit = np.ones(len(rig.target.lamps), bool)
    lit[list(hidden)] = False
    p = lamps_to_camera(rig, pose, rig.target.lamps.xyz_mm[lit])
    front = p[:, 2] > 0
    return int(np.sum(rig.camera.in_image(rig.camera.project(p[front]), margin_px)))


def simulate_lamps(
    rig: Rig,
    out_dir: str | Path,
    n_frames: int,
    *,
    path: PerimeterPath | None = None,
    scene: LampScene | None = None,
    seed: int = 0,
    fps: float | None = None,
    t0: float = 0.0,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Render ``n_frames`` frames along ``path`` into ``out_dir`` with truth.csv (the
    pose at the middle of each exposure). Returns the path of truth.csv."""
    path = path or PerimeterPath()
    scene = scene or LampScene(exposure_ms=rig.exposure_ms or LampScene.exposure_ms)
    rng = np.random.default_rng(seed)
    fps = fps or rig.fps

    def frame_at(t: float) -> tuple[np.ndarray, list[str]]:
        x, y, psi = path.at(t)
        img = render_lamps(rig, path.at, t, scene, rng)
        return img, [f"{x:.4f}", f"{y:.4f}", f"{_wrap_deg(psi):.6f}"]

    times = t0 + np.arange(n_frames) / fps
    return write_sequence(out_dir, TRUTH_COLUMNS, times, frame_at, progress)


@dataclass(frozen=True)
class ImuModel:
    """A planar IMU (LuVeX Sec. 3.2): rate_hz samples of gz (deg/s) and ax, ay (m/s^2,
    body axes), with constant biases, white noise and faults (a fraction of samples
    replaced by spikes of fault_size times the paper's limits)."""

    rate_hz: float = 100.0
    gyro_bias_dps: float = 0.3
    accel_bias_mps2: tuple[float, float] = (0.004, -0.003)
    gyro_noise_dps: float = 0.05
    accel_noise_mps2: float = 0.002
    fault_fraction: float = 0.002
    fault_size: float = 3.0


def simulate_imu(
    path: PerimeterPath,
    duration_s: float,
    out_dir: str | Path,
    *,
    model: ImuModel | None = None,
    seed: int = 0,
    t0: float = 0.0,
) -> tuple[Path, Path]:
    """Write imu.csv (time_s,gz_dps,ax_mps2,ay_mps2) and imu_truth.csv (the true pose
    at every sample, ``frame`` = the sample's index, as in the rows of `visvec fuse`)
    for ``duration_s`` of ``path``. Returns both paths."""
    model = model or ImuModel()
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(int(round(duration_s * model.rate_hz)) + 1) / model.rate_hz
    pose = path.at(t)
    vel, acc = path.derivatives(t)
    psi = pose[:, 2]
    c, s = np.cos(psi), np.sin(psi)
    # specific force in B: a_B = Rz(psi)^T a_N (a level table: gravity is along n3)
    ax = (c * acc[:, 0] + s * acc[:, 1]) / 1000.0
    ay = (-s * acc[:, 0] + c * acc[:, 1]) / 1000.0
    gz = np.degrees(vel[:, 2])
    n = len(t)
    gz = gz + model.gyro_bias_dps + rng.standard_normal(n) * model.gyro_noise_dps
    ax = ax + model.accel_bias_mps2[0] + rng.standard_normal(n) * model.accel_noise_mps2
    ay = ay + model.accel_bias_mps2[1] + rng.standard_normal(n) * model.accel_noise_mps2
    faults = rng.random(n) < model.fault_fraction
    faults[: int(2 * model.rate_hz)] = False  # keep the first seconds clean
    sign = rng.choice([-1.0, 1.0], size=n)
    gz[faults] = sign[faults] * 50.0 * model.fault_size
    ax[faults] = -sign[faults] * 0.5 * model.fault_size
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    imu, truth = out / "imu.csv", out / "imu_truth.csv"
    with open(imu, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(IMU_COLUMNS)
        for row in zip(t, gz, ax, ay, strict=True):
            wr.writerow([f"{row[0]:.4f}", *(f"{v:.6f}" for v in row[1:])])
    with open(truth, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(IMU_TRUTH_COLUMNS)
        for i, (ti, (x, y, p)) in enumerate(zip(t, pose, strict=True)):
            wr.writerow([i, f"{ti:.4f}", f"{x:.4f}", f"{y:.4f}", f"{_wrap_deg(p):.6f}"])
    return imu, truth


def _wrap_deg(a_rad: float) -> float:
    return float((np.degrees(a_rad) + 180.0) % 360.0 - 180.0)
