"""`visvec simulate`: frames of the rig's target at known attitudes, with truth.csv."""

from __future__ import annotations

import csv
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from visvec.imageio import write_image
from visvec.output import ATTITUDE_COLUMNS
from visvec.rig import Rig
from visvec.rotations import (
    euler_to_matrix,
    logmap,
    matrix_to_euler,
    matrix_to_quat,
    rot_x,
    rot_y,
    rot_z,
)
from visvec.sim.markers import SpotScene, render_markers
from visvec.sim.render import render_frame
from visvec.sim.scene import Light, Occluder, Scene

TRUTH_COLUMNS = ("frame", "file", "time_s", *ATTITUDE_COLUMNS[3:10])


def random_attitudes(
    n: int,
    max_tilt_deg: float,
    rng: np.random.Generator,
    motion: str = "random",
    turn_rad: float = 0.8 * 2.0 * np.pi,
    wobble_cycles: tuple[float, float] = (1.3, 0.9),
) -> np.ndarray:
    """(n, 3) yaw, pitch, roll in radians.

    ``random``: yaw uniform over the circle, pitch and roll uniform within +-max_tilt.
    ``sweep``: a smooth motion like a recording (a steady yaw turn by ``turn_rad`` over
    the sequence, pitch and roll wobbling by ``wobble_cycles`` over it).
    ``swing``: the same with the yaw swinging out and back once over the sequence (a
    slew and its return), its peak rate that of the sweep: amplitude turn_rad / 2 pi.
    ``level``: pitch = roll = 0 at yaws spread over the circle (for zero-tilt
    calibration).
    """
    m = np.radians(max_tilt_deg)
    if motion == "random":
        return np.column_stack(
            [rng.uniform(-np.pi, np.pi, n), rng.uniform(-m, m, n), rng.uniform(-m, m, n)]
        )
    if motion == "level":
        yaw = np.linspace(-np.pi, np.pi, n, endpoint=False) + rng.uniform(0, 2 * np.pi / n)
        return np.column_stack([(yaw + np.pi) % (2 * np.pi) - np.pi, np.zeros(n), np.zeros(n)])
    if motion in ("sweep", "swing"):
        return smooth_path(max_tilt_deg, rng, motion, turn_rad, wobble_cycles)(
            np.linspace(0.0, 1.0, n)
        )
    raise ValueError(f"motion = {motion!r}: expected 'random', 'sweep', 'swing' or 'level'")


def smooth_path(
    max_tilt_deg: float,
    rng: np.random.Generator,
    motion: str,
    turn_rad: float = 0.8 * 2.0 * np.pi,
    wobble_cycles: tuple[float, float] = (1.3, 0.9),
):
    """A ``sweep`` or ``swing`` (see `random_attitudes`) as a function of the
    sequence's fraction u in [0, 1] -> (len(u), 3) yaw, pitch, roll in radians."""
    m = np.radians(max_tilt_deg)
    ph = rng.uniform(0, 2 * np.pi, 2)
    yaw0 = rng.uniform(-np.pi, np.pi)

    def at(u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, float)
        turn = turn_rad * u if motion == "sweep" else turn_rad / (2 * np.pi) * np.sin(2 * np.pi * u)
        yaw = (yaw0 + turn + np.pi) % (2 * np.pi) - np.pi
        return np.column_stack(
            [
                yaw,
                0.8 * m * np.sin(2 * np.pi * wobble_cycles[0] * u + ph[0]),
                0.8 * m * np.sin(2 * np.pi * wobble_cycles[1] * u + ph[1]),
            ]
        )

    return at


IMU_RATE_HZ = 100.0
IMU_BIAS_DPS = (0.2, -0.15, 0.1)
IMU_NOISE_DPS = 0.05
IMU_TRUTH_COLUMNS = ("frame", "time_s", "yaw_deg", "pitch_deg", "roll_deg", "qw", "qx", "qy",
                     "qz")  # fmt: skip


def write_gyro(out_dir: str | Path, path, span_s: float, seed: int) -> tuple[Path, Path]:
    """A 3-D gyro on the platform over a sweep's or swing's ``span_s`` seconds:
    ``imu.csv`` (time_s, gx_dps, gy_dps, gz_dps at 100 Hz: the body rate, a constant
    bias and white noise) and ``imu_truth.csv`` (the attitude at every sample; frame =
    the sample's index, as `visvec fuse` numbers its rows). ``path`` is `smooth_path`'s
    function of the sequence's fraction."""
    out = Path(out_dir)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, span_s + 1e-9, 1.0 / IMU_RATE_HZ)
    h = 1e-4
    R = lambda u: np.array([euler_to_matrix(*e) for e in path(u)])  # noqa: E731
    Ra, Rb, Rm = R((t - h) / span_s), R((t + h) / span_s), R(t / span_s)
    w = np.array([logmap(a.T @ b) / (2 * h) for a, b in zip(Ra, Rb, strict=True)])
    g = np.degrees(w) + np.array(IMU_BIAS_DPS) + rng.normal(0.0, IMU_NOISE_DPS, w.shape)
    imu, truth = out / "imu.csv", out / "imu_truth.csv"
    with open(imu, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(["time_s", "gx_dps", "gy_dps", "gz_dps"])
        for ti, gi in zip(t, g, strict=True):
            wr.writerow([f"{ti:.4f}", *(f"{x:.6f}" for x in gi)])
    with open(truth, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(IMU_TRUTH_COLUMNS)
        for k, (ti, Ri) in enumerate(zip(t, Rm, strict=True)):
            e = np.degrees(matrix_to_euler(Ri))
            wr.writerow([k, f"{ti:.4f}", *(f"{x:.9f}" for x in e),
                         *(f"{x:.12f}" for x in matrix_to_quat(Ri))])  # fmt: skip
    return imu, truth


def body_rates(R: np.ndarray, dt: float) -> np.ndarray:
    """(n, 3) body rates (rad/s) of a smooth sequence of attitudes R (n, 3, 3) sampled
    every ``dt`` s: central differences, omega_k = log(R_{k-1}^T R_{k+1}) / (2 dt)
    (second order in dt), one-sided at the ends; zeros for a single frame."""
    n = len(R)
    out = np.zeros((n, 3))
    for k in range(n):
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        if b > a:
            out[k] = logmap(R[a].T @ R[b]) / ((b - a) * dt)
    return out


def true_rig(
    rig: Rig,
    target_offset_mm: tuple[float, float] = (0.0, 0.0),
    camera_askew_deg: tuple[float, float] = (0.0, 0.0),
    height_offset_mm: float = 0.0,
    camera_turn_deg: float = 0.0,
) -> Rig:
    """The lab as it really is: the target shifted on the ceiling (and ``height_offset_mm``
    higher) and the camera tilted on its mount (about b1 and b2) and turned about its own
    optical axis (``camera_turn_deg``) against what the rig file says (triangle rigs).

    Parameters
    ----------
    rig : Rig
        The rig file's setup.
    target_offset_mm : (float, float)
        The target's shift on the ceiling along n1, n2 (mm).
    camera_askew_deg : (float, float)
        The camera's tilt on its mount about b1, b2 (deg).
    height_offset_mm : float
        How much higher the target really is (mm).
    camera_turn_deg : float
        The camera's turn about its optical axis (deg).

    Returns
    -------
    Rig
        The setup to render frames with (the rig file's stays what the sensor is
        told)."""
    if rig.kind != "triangle":
        if any(target_offset_mm) or any(camera_askew_deg) or height_offset_mm or camera_turn_deg:
            raise ValueError("target offset and camera askew apply to triangle rigs only")
        return rig
    v = rig.target.vertices_mm.copy()
    v[:, 0] += target_offset_mm[0]
    v[:, 1] += target_offset_mm[1]
    v[:, 2] += height_offset_mm
    a = np.radians(camera_askew_deg)
    R_bc = rot_x(a[0]) @ rot_y(a[1]) @ rig.R_bc @ rot_z(np.radians(camera_turn_deg))
    return replace(
        rig, target=replace(rig.target, vertices_mm=v), mount=replace(rig.mount, rotation=R_bc)
    )


@dataclass(frozen=True)
class Clutter:
    """Scenario switches of `visvec simulate` (fractions of frames affected)."""

    lights: float = 0.0
    occluder: float = 0.0


def scene_for_frame(base: Scene, clutter: Clutter, rig: Rig, rng: np.random.Generator) -> Scene:
    """The base scene, with ceiling lights and a person leaning over for some frames."""
    sc = base
    c = rig.target.centroid_mm
    if rng.random() < clutter.lights:
        lights = []
        for _ in range(rng.integers(1, 4)):
            ang = rng.uniform(0, 2 * np.pi)
            r = rng.uniform(750.0, 1100.0)
            lights.append(
                Light(c[0] + r * np.cos(ang), c[1] + r * np.sin(ang), rng.uniform(80.0, 150.0))
            )
        sc = replace(sc, lights=tuple(lights))
    if rng.random() < clutter.occluder:
        ang = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(0.0, 300.0)
        sc = replace(
            sc,
            occluder=Occluder(
                c[0] * 0.6 + r * np.cos(ang),
                c[1] * 0.6 + r * np.sin(ang),
                z_mm=rng.uniform(1000.0, 1500.0),
                radius_mm=rng.uniform(80.0, 220.0),
                level=rng.uniform(60.0, 200.0),
            ),
        )
    return sc


def simulate(
    rig: Rig,
    out_dir: str | Path,
    n_frames: int,
    *,
    scene: Scene | None = None,
    seed: int = 0,
    max_tilt_deg: float = 5.0,
    motion: str = "random",
    fps: float | None = None,
    clutter: Clutter | None = None,
    render_rig: Rig | None = None,
    spot_scene: SpotScene | None = None,
    progress: Callable[[int], None] | None = None,
    readout_ms: float | None = None,
    yaw_rate_dps: float | None = None,
    exposure_ms: float | None = None,
    imu: bool = False,
) -> Path:
    """Render ``n_frames`` frames into ``out_dir`` and write ``out_dir/truth.csv``
    (with ``imu``, a sweep's or swing's gyro too: `write_gyro`).

    Parameters
    ----------
    rig : Rig
        The rig (its camera gives the image size).
    render_rig : Rig, optional
        The true geometry to render with (see :func:`true_rig`); ``rig`` by default.
    readout_ms : float, optional
        A rolling shutter's readout (triangle rigs; default the rig's
        ``[camera] readout_ms``): each frame of a ``sweep`` or ``swing`` is rendered with
        its body rate, the truth being the centre row's attitude. Other motions are still
        frames.
    exposure_ms : float, optional
        Each row's exposure time (triangle rigs; default the rig's ``[camera]
        exposure_ms``, else 0): a ``sweep``'s or ``swing``'s frames are blurred by their
        motion.
    yaw_rate_dps : float, optional
        The ``sweep``'s yaw rate, a ``swing``'s peak rate (default: 0.8 of a turn over
        the sequence, the tilts wobbling 1.3 and 0.9 times; with a rate, they nutate
        every 7.7 and 11 s).

    Returns
    -------
    Path of truth.csv.
    """
    scene = Scene() if scene is None else scene
    clutter = Clutter() if clutter is None else clutter
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    fps = fps or rig.fps
    turn, wobble = 0.8 * 2.0 * np.pi, (1.3, 0.9)
    if yaw_rate_dps is not None:
        # a turn at a set rate: the tilts nutate with periods of 7.7 s and 11 s
        span_s = (n_frames - 1) / fps
        turn, wobble = np.radians(yaw_rate_dps) * span_s, (0.13 * span_s, 0.09 * span_s)
    if motion in ("sweep", "swing"):
        path = smooth_path(max_tilt_deg, rng, motion, turn, wobble)
        eul = path(np.linspace(0.0, 1.0, n_frames))
        if imu:
            write_gyro(out, path, (n_frames - 1) / fps, seed + 1)
    else:
        if imu:
            raise ValueError("a gyro is simulated for a sweep or a swing only")
        eul = random_attitudes(n_frames, max_tilt_deg, rng, motion, turn, wobble)
    world = render_rig or rig
    readout = rig.readout_ms if readout_ms is None else readout_ms
    if exposure_ms is None:
        exposure_ms = rig.exposure_ms or 0.0
    Rs = np.array([euler_to_matrix(*e) for e in eul])
    # the platform moves between frames only in a sweep or a swing (the others are
    # still frames)
    moving = motion in ("sweep", "swing")
    rates = body_rates(Rs, 1.0 / fps) if moving else np.zeros((n_frames, 3))
    peak_dps = float(np.degrees(np.linalg.norm(rates, axis=1).max())) if len(rates) else 0.0
    if readout and world.kind == "triangle" and peak_dps > rig.max_rate_dps:
        # the sensor bounds a rolling shutter's shear by the rig's fastest turn while a
        # frame's rate is not known yet (the first, or the first after a loss)
        logging.getLogger("visvec").warning(
            "the %s turns at up to %.0f deg/s, beyond the rig's [platform] max_rate_dps = "
            "%g: with a rolling shutter, a frame whose rate is not known yet (the first, "
            "or the first after a loss) gets a sigma that covers %g deg/s only. "
            "--yaw-rate-dps sets the turn (a sweep over more --frames is slower)",
            motion, peak_dps, rig.max_rate_dps, rig.max_rate_dps,
        )  # fmt: skip
    truth = out / "truth.csv"
    width = max(4, len(str(n_frames - 1)))
    with open(truth, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(TRUTH_COLUMNS)
        for i, R in enumerate(Rs):
            if world.kind == "markers":
                img = render_markers(world, R, spot_scene or SpotScene(), rng)
            else:
                sc = scene_for_frame(scene, clutter, world, rng)
                img = render_frame(world, R, sc, rng, readout, rates[i], exposure_ms)
            name = f"frame_{i:0{width}d}.png"
            write_image(out / name, img)
            e = np.degrees(matrix_to_euler(R))
            q = matrix_to_quat(R)
            w.writerow(
                [i, name, f"{i / fps:.6f}", *(f"{x:.9f}" for x in e), *(f"{x:.12f}" for x in q)]
            )
            if progress is not None:
                progress(i)
    return truth
