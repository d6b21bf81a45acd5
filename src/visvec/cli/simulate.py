"""`visvec simulate`: synthetic frames of the rig's target with truth.csv."""

from __future__ import annotations

import sys
from dataclasses import replace

import click

from visvec.cli.common import FiniteFloat, KindCommand, check_new_recording, load, rig_options
from visvec.cli.progress import Work
from visvec.sim.lamps import LampScene, PerimeterPath, simulate_imu, simulate_lamps
from visvec.sim.markers import SpotScene
from visvec.sim.scene import Scene
from visvec.sim.simulate import Clutter, true_rig
from visvec.sim.simulate import simulate as run_simulation
from visvec.sim.stars import PAPER_CASES, StarScene, simulate_stars


@click.command(cls=KindCommand)
@rig_options
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for the frames and truth.csv.",
)
@click.option("--frames", "n_frames", type=click.IntRange(1, 1_000_000), default=20,
              show_default=True, help="How many frames to render.")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the attitudes and the noise (same seed, same frames).")  # fmt: skip
@click.option(
    "--motion",
    type=click.Choice(["random", "sweep", "swing", "level", "perimeter", "rest"]),
    default=None,
    help="Attitudes: random (default), a smooth sweep (a steady yaw turn), a swing (the "
    "yaw out and back once over the frames), or level at many yaws; lamps: "
    "perimeter (default: pushed around the table) or rest.",
)
@click.option(
    "--max-tilt-deg",
    type=FiniteFloat(0, 60),
    default=5.0,
    show_default=True,
    help="Pitch and roll each within +-this (random: uniform, so the tilt reaches 1.41x it; "
    "sweep and swing: 0.8x it). Tilts beyond the rig's [platform] max_tilt_deg are rows "
    "rejected as impossible_tilt.",
)
@click.option(
    "--noise",
    type=FiniteFloat(0, 100),
    default=2.0,
    show_default=True,
    help="Read noise sigma, grey levels.",
)
@click.option(
    "--contrast",
    type=FiniteFloat(-255, 255),
    default=28.0,
    show_default=True,
    help="Triangle: the triangle over the board, grey levels.",
)
@click.option(
    "--blur",
    type=FiniteFloat(0, 20),
    default=0.6,
    show_default=True,
    help="Triangle: defocus blur sigma, px.",
)
@click.option(
    "--exposure",
    type=FiniteFloat(0, 100),
    default=1.0,
    show_default=True,
    help="Triangle: exposure factor (> 1 over-exposes).",
)
@click.option(
    "--lights",
    type=FiniteFloat(0, 1),
    default=0.0,
    show_default=True,
    help="Triangle: fraction of frames with ceiling lights in view.",
)
@click.option(
    "--occluder",
    type=FiniteFloat(0, 1),
    default=0.0,
    show_default=True,
    help="Triangle: fraction of frames with a person leaning over.",
)
@click.option(
    "--no-triangle", is_flag=True, help="Triangle: render the board without the triangle."
)
@click.option(
    "--reflections",
    type=click.IntRange(0, 100),
    default=0,
    show_default=True,
    help="Markers: stray reflection spots per frame.",
)
@click.option(
    "--target-offset-mm",
    nargs=2,
    type=FiniteFloat(-10000, 10000),
    default=(0.0, 0.0),
    help="Triangle: shift the real target on the ceiling (dx dy) against the rig file.",
)
@click.option(
    "--target-height-mm",
    type=FiniteFloat(-10000, 10000),
    default=0.0,
    help="Triangle: hang the real target this much higher than the rig file says (a "
    "ceiling measured wrong).",
)
@click.option(
    "--camera-askew-deg",
    nargs=2,
    type=FiniteFloat(-45, 45),
    default=(0.0, 0.0),
    help="Triangle: tilt the real camera on its mount (about b1, b2) against the rig file.",
)
@click.option(
    "--camera-turn-deg",
    type=FiniteFloat(-45, 45),
    default=0.0,
    help="Triangle: turn the real camera about its own optical axis against the rig file "
    "(what only stops at known yaws calibrate: calibrate zero-tilt --yaw-deg).",
)
@click.option(
    "--case",
    type=click.IntRange(1, 4),
    default=None,
    help="Starfield: the paper's case 1-4 (1 and 5 deg/s out of plane, 1 and 5 deg/s "
    "about the boresight, each with the orbital rate).",
)
@click.option(
    "--rate-dps",
    nargs=3,
    type=FiniteFloat(-10000, 10000),
    default=None,
    help="Starfield: constant rate wx wy wz (deg/s, camera frame).",
)
@click.option(
    "--spurious",
    type=FiniteFloat(0, 5),
    default=0.0,
    show_default=True,
    help="Lamps: extra bright spots per frame, as a fraction of the lamps in view.",
)
@click.option(
    "--imu",
    is_flag=True,
    help="Also write imu.csv and imu_truth.csv over the frames' time span: lamps, a 100 Hz "
    "planar gyro and accelerometer with bias, noise and faults; triangle and markers "
    "(--motion sweep or swing), a 100 Hz 3-D gyro with bias and noise.",
)
@click.option(
    "--readout-ms",
    type=FiniteFloat(),
    default=None,
    help="Triangle: a rolling shutter's readout, first to last row (default: the rig's "
    "[camera] readout_ms); a --motion sweep or swing is rendered with its rates.",
)
@click.option(
    "--exposure-ms",
    type=FiniteFloat(min=0),
    default=None,
    help="Triangle: each row's exposure time, blurring a --motion sweep or swing (default: the "
    "rig's [camera] exposure_ms, else 0).",
)
@click.option(
    "--yaw-rate-dps",
    type=FiniteFloat(-3600, 3600),
    default=None,
    help="Triangle: the yaw rate of a --motion sweep, the peak rate of a swing (default: "
    "0.8 of a turn over the frames).",
)
@click.option(
    "--fps",
    type=FiniteFloat(min=0.01),
    default=None,
    help="Frame rate of the rendered sequence (default: the rig's).",
)
@click.option(
    "--webcam",
    is_flag=True,
    help="Triangle: the frames through a webcam's image chain (Bayer mosaic and "
    "demosaicing, shot and read noise, vignetting, a breathing gain, chromatic aberration, "
    "hot pixels, sRGB tone curve, Motion-JPEG at 85), each step at a usual webcam's "
    "value (visvec.sim.webcam); --noise does not apply then.",
)
@click.option(
    "--webcam-set",
    "webcam_set",
    multiple=True,
    metavar="KEY=VALUE",
    help="Triangle: set a step of the --webcam chain (repeatable; off switches one off): "
    "vignetting, gain_sigma, electrons_at_white, read_noise_e, sensitivity_r, "
    "sensitivity_b, bayer, chromatic_aberration, hot_pixels, srgb, jpeg_quality, seed.",
)
def simulate(
    rig_path,
    calibration,
    out_dir,
    n_frames,
    seed,
    motion,
    max_tilt_deg,
    noise,
    contrast,
    blur,
    exposure,
    lights,
    occluder,
    no_triangle,
    reflections,
    target_offset_mm,
    target_height_mm,
    camera_askew_deg,
    camera_turn_deg,
    case,
    rate_dps,
    spurious,
    imu,
    readout_ms,
    exposure_ms,
    yaw_rate_dps,
    fps,
    webcam,
    webcam_set,
):
    """Render frames of the rig's target at known attitudes (or, for a starfield rig, a
    sky turning at a known rate); write OUT/truth.csv."""
    camera_askew_deg = (*camera_askew_deg, camera_turn_deg)  # about b1, b2, and its axis
    chain = _webcam_chain(webcam, webcam_set)
    try:
        _simulate(rig_path, calibration, out_dir, n_frames, seed, motion, max_tilt_deg, noise,
                  contrast, blur, exposure, lights, occluder, no_triangle, reflections,
                  target_offset_mm, target_height_mm, camera_askew_deg, case, rate_dps,
                  spurious, imu, readout_ms, exposure_ms, yaw_rate_dps, fps, chain)  # fmt: skip
    except KeyboardInterrupt:
        click.echo(
            f"visvec: interrupted: the simulation in {out_dir} is incomplete (its truth.csv "
            "lists the frames written). A folder that holds a recording is never written "
            f"over: to make it whole, delete {out_dir} and run the same command again, or "
            "give a new --out folder",
            err=True,
        )
        sys.exit(130)


def _webcam_chain(webcam: bool, settings: tuple[str, ...]):
    """The webcam chain --webcam and --webcam-set ask for (None without them); a bad
    KEY=VALUE refused before any frame."""
    if not webcam and not settings:
        return None
    from visvec.sim.webcam import WebcamChain

    pairs = {}
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep:
            raise click.BadParameter(f"{item!r}: expected KEY=VALUE", param_hint="--webcam-set")
        pairs[key.strip()] = value
    try:
        return WebcamChain().with_settings(pairs)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--webcam-set") from None


def _check_timing(rig, motion, triangle_only, readout_ms, exposure_ms, yaw_rate_dps) -> None:
    """Refuse, before any frame is made, the triangle scene's options on another kind
    of rig and a readout, exposure or turn the rig's frame rate cannot hold."""
    if rig.kind != "triangle" and (
        triangle_only
        or readout_ms is not None
        or exposure_ms is not None
        or yaw_rate_dps is not None
    ):
        raise click.UsageError(
            "--lights, --occluder, --no-triangle, --target-offset-mm, --target-height-mm, "
            "--camera-askew-deg, --camera-turn-deg, --readout-ms, --exposure-ms and "
            "--yaw-rate-dps apply to triangle rigs only"
        )
    if exposure_ms is not None and exposure_ms > 1000.0 / rig.fps:
        raise click.BadParameter(
            f"{exposure_ms:g} ms: expected at most a frame interval ({1000.0 / rig.fps:g} ms)",
            param_hint="--exposure-ms",
        )
    if yaw_rate_dps is not None and motion not in ("sweep", "swing"):
        raise click.UsageError("--yaw-rate-dps sets the rate of --motion sweep or swing")
    if readout_ms is not None and abs(readout_ms) > 1000.0 / rig.fps:
        raise click.BadParameter(
            f"{readout_ms:g} ms: expected at most a frame interval ({1000.0 / rig.fps:g} ms; "
            "negative: the last row read first)",
            param_hint="--readout-ms",
        )


def _simulate(rig_path, calibration, out_dir, n_frames, seed, motion, max_tilt_deg, noise,
              contrast, blur, exposure, lights, occluder, no_triangle, reflections,
              target_offset_mm, target_height_mm, camera_askew_deg, case, rate_dps, spurious,
              imu, readout_ms, exposure_ms, yaw_rate_dps, fps, chain=None) -> None:  # fmt: skip
    rig = load(rig_path, calibration)
    if chain is not None and rig.kind != "triangle":
        raise click.UsageError("--webcam applies to triangle rigs only")
    lamp_only = spurious > 0 or motion in ("perimeter", "rest")
    if lamp_only and rig.kind != "lamps":
        raise click.UsageError("--spurious and --motion perimeter|rest apply to lamps rigs")
    if imu and rig.kind not in ("lamps", "triangle", "markers"):
        raise click.UsageError("--imu applies to lamps, triangle and markers rigs")
    if imu and rig.kind != "lamps" and motion not in ("sweep", "swing"):
        raise click.UsageError("--imu: a triangle or markers rig's gyro needs --motion sweep "
                               "or swing (the other motions are still frames)")  # fmt: skip
    check_new_recording(out_dir, "--out")
    if rig.kind == "lamps":
        if motion not in (None, "perimeter", "rest"):
            raise click.UsageError(f"--motion {motion}: a lamps rig moves by perimeter or rest")
        _lamps(rig, out_dir, n_frames, seed, noise, motion or "perimeter", spurious, imu, fps)
        return
    if fps is not None and rig.kind != "starfield":
        raise click.UsageError("--fps applies to starfield and lamps rigs")
    motion = motion or "random"
    if rig.kind == "starfield":
        _stars(rig, out_dir, n_frames, seed, noise, case, rate_dps, fps)
        return
    if case is not None or rate_dps is not None:
        raise click.UsageError("--case and --rate-dps apply to starfield rigs only")
    triangle_only = (lights or occluder or no_triangle or any(target_offset_mm)
                     or target_height_mm or any(camera_askew_deg))  # fmt: skip
    _check_timing(rig, motion, bool(triangle_only), readout_ms, exposure_ms, yaw_rate_dps)
    spots = SpotScene(noise_sigma=noise, reflections=reflections)
    scene = replace(
        Scene(),
        noise_sigma=noise,
        contrast=contrast,
        blur_sigma_px=blur,
        exposure=exposure,
        show_triangle=not no_triangle,
        webcam=chain,
    )
    world = true_rig(rig, tuple(target_offset_mm), tuple(camera_askew_deg[:2]), target_height_mm,
                     camera_askew_deg[2])  # fmt: skip
    with Work("simulate", n_frames) as bar:
        truth = run_simulation(
            rig,
            out_dir,
            n_frames,
            scene=scene,
            seed=seed,
            max_tilt_deg=max_tilt_deg,
            motion=motion,
            clutter=Clutter(lights=lights, occluder=occluder),
            render_rig=world,
            spot_scene=spots,
            progress=lambda i: bar.update(1),
            readout_ms=readout_ms,
            yaw_rate_dps=yaw_rate_dps,
            exposure_ms=exposure_ms,
            imu=imu,
        )
    click.echo(f"wrote {n_frames} frames and {truth}", err=True)
    if imu:
        click.echo(f"wrote {truth.parent / 'imu.csv'} (3-D gyro, 100 Hz) and "
                   f"{truth.parent / 'imu_truth.csv'}", err=True)  # fmt: skip


def _lamps(rig, out_dir, n_frames, seed, noise, motion, spurious, imu, fps) -> None:
    path = PerimeterPath(rest=motion == "rest")
    scene = replace(
        LampScene(exposure_ms=rig.exposure_ms or LampScene.exposure_ms),
        noise_sigma=noise,
        spurious=spurious,
    )
    fps = fps or rig.fps
    with Work("simulate", n_frames) as bar:
        truth = simulate_lamps(
            rig, out_dir, n_frames, path=path, scene=scene, seed=seed, fps=fps,
            progress=lambda i: bar.update(1),
        )  # fmt: skip
    click.echo(f"wrote {n_frames} frames ({motion}) and {truth}", err=True)
    if imu:
        files = simulate_imu(path, (n_frames - 1) / fps, out_dir, seed=seed + 1)
        click.echo(f"wrote {files[0]} and {files[1]}", err=True)


def _stars(rig, out_dir, n_frames, seed, noise, case, rate_dps, fps) -> None:
    if case is not None and rate_dps is not None:
        raise click.UsageError("give --case or --rate-dps, not both")
    w = PAPER_CASES[case] if case is not None else tuple(rate_dps or PAPER_CASES[1])
    scene = replace(StarScene(exposure_ms=rig.exposure_ms or 50.0), read_noise_dn=noise)
    with Work("simulate", n_frames) as bar:
        truth = simulate_stars(
            rig, out_dir, n_frames, w, seed=seed, scene=scene, fps=fps,
            progress=lambda i: bar.update(1),
        )  # fmt: skip
    click.echo(
        f"wrote {n_frames} frames turning at {w[0]:g}, {w[1]:g}, {w[2]:g} deg/s and {truth}",
        err=True,
    )
