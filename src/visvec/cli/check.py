"""`visvec check`: a rig file's geometry, the attitudes that keep its target in view, and
the accuracy it gives on simulated frames."""

from __future__ import annotations

import math
from dataclasses import replace

import click
import numpy as np

from visvec.check import (
    ATTITUDE_KINDS,
    CHUNK_FRAMES,
    camera_points,
    envelope,
    field_of_view_deg,
    simulated_accuracy,
)
from visvec.cli.common import load, rig_options, scheduler_options
from visvec.cli.progress import Work
from visvec.detect.edges import side_lengths
from visvec.distribute import TaskPool
from visvec.sim.markers import SpotScene
from visvec.sim.scene import Scene


@click.command()
@rig_options
@click.option(
    "--frames",
    "n_frames",
    type=click.IntRange(min=0),
    default=40,
    show_default=True,
    help="Simulated frames for the expected accuracy (0: none).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@scheduler_options
def check(rig_path, calibration, n_frames, seed, scheduler, workers):
    """What the rig's camera sees and how well: its field, the target's image at zero
    attitude, the tilts that keep the target in view at every yaw, and the accuracy of
    frames simulated within [platform] max_tilt_deg. Checks the rig file first (exit 2)."""
    rig = load(rig_path, calibration)
    cam = rig.camera
    fov = field_of_view_deg(rig)
    field = (
        f"field {fov[0]:.1f} x {fov[1]:.1f} deg ({fov[2]:.1f} diagonal)"
        if fov is not None
        else f"the lens model's field ends {cam.field_radius_px:.0f} px from the principal "
        "point, inside the image"
    )
    click.echo(
        f"rig {rig_path}: {rig.kind} target, camera {cam.width}x{cam.height}, "
        f"fx {cam.fx:g} px, {field}"
    )
    if rig.kind == "lamps":
        _lamp_map_lines(rig)
    if rig.kind not in ATTITUDE_KINDS:
        click.echo(
            f"  rig file valid; the view envelope and the simulated accuracy are for "
            f"{' and '.join(ATTITUDE_KINDS)} rigs (a {rig.kind} rig: `visvec simulate`, then "
            "`visvec batch ... --truth`)"
        )
        return
    for text, warn in geometry_lines(rig):
        click.echo(text, err=warn)
    if n_frames:
        _accuracy(rig, n_frames, seed, scheduler, workers)


def _lamp_map_lines(rig) -> None:
    """How unique the lamp map's triangles are for this camera's view (issue 35)."""
    from visvec.detect.lamps import LampIdentifier

    u = LampIdentifier(rig).uniqueness()
    click.echo(f"  lamp map: {u.words()}")
    if u.too_few_unique:
        click.echo(f"visvec: warning: {rig.target.lamps.path}: {u.warning()}", err=True)


def geometry_lines(rig) -> list[tuple[str, bool]]:
    """What `visvec check` says of the rig's geometry (the target at zero attitude, the
    tilts that keep it in view), as (line, is a warning); the live view shows it too."""
    return [*_zero_attitude(rig), *_envelope(rig)]


def _zero_attitude(rig) -> list[tuple[str, bool]]:
    p_c = camera_points(rig, np.eye(3)[None])[0]
    uv = rig.camera.project(p_c)
    dist = float(np.linalg.norm(p_c.mean(axis=0)))
    c = np.nanmean(uv, axis=0)
    if rig.kind == "triangle":
        sides = " / ".join(f"{s:.0f}" for s in side_lengths(uv))
        shape = f"sides {sides} px"
    else:
        shape = f"{int(np.isfinite(uv).all(axis=1).sum())} of {len(uv)} LEDs in the image"
    return [
        (
            f"  at zero attitude: target {dist:.0f} mm from the camera, its image centred at "
            f"({c[0]:.1f}, {c[1]:.1f}) px, {shape}",
            False,
        )
    ]


def _envelope(rig) -> list[tuple[str, bool]]:
    env = envelope(rig)
    what = "the whole triangle" if rig.kind == "triangle" else f"all {env.n_points} LEDs"
    max_tilt = rig.max_tilt_deg
    out: list[tuple[str, bool]] = []
    if math.isnan(env.full_tilt_deg):
        out.append(
            (
                f"  in view: even level, {what} is in view at only {100 * env.level_share:.0f} % "
                "of yaws (a target off the axis circles the image as the platform turns: a "
                "wider lens, or the target nearer the axis)",
                False,
            )
        )
    elif env.limit is None:
        out.append(
            (
                f"  in view: {what} at every yaw and tilt direction up to {env.span_deg:g} deg "
                "of tilt (the largest sampled)",
                False,
            )
        )
    else:
        out.append(
            (
                f"  in view: {what} at every yaw and tilt direction up to "
                f"{env.full_tilt_deg:g} deg of tilt (first lost at yaw {env.limit[0]:+.0f} deg, "
                f"tilting about the axis {env.limit[1]:.0f} deg from b1)",
                False,
            )
        )
    line = (
        f"  at [platform] max_tilt_deg {max_tilt:g}: {what} in view at "
        f"{100 * env.share_at_max:.0f} % of yaws and directions"
    )
    if rig.kind == "markers":
        line += f"; at least {env.fewest_at_max} LEDs in view within it"
    out.append((line, False))
    if env.share_at_max < 1.0:
        out.append(
            (
                "  warning: the target leaves the view within the platform's range: frames "
                "there are rejected (partly_out_of_view); a wider lens or a smaller target "
                "keeps it, or lower max_tilt_deg if the platform cannot tilt that far",
                True,
            )
        )
    return out


def _figures(out) -> str:
    """'; RMS error ...; RMS sigma ...' of a simulated run's ok rows ('' without)."""
    if not out.n_ok:
        return ""
    rms = out.rms()
    sig = np.sqrt(np.mean(np.square(out.sigma_deg), axis=0))
    return (
        f"; RMS error yaw {rms[0]:.2g}, pitch {rms[1]:.2g}, roll {rms[2]:.2g} deg; "
        f"RMS sigma {sig[0]:.2g}, {sig[1]:.2g}, {sig[2]:.2g} deg"
    )


def _accuracy(rig, n_frames: int, seed: int, scheduler: str | None, workers: int | None) -> None:
    if rig.kind == "triangle":
        sc = Scene()
        scene = (
            f"noise {sc.noise_sigma:g} grey levels, contrast {sc.contrast:g}, "
            f"blur {sc.blur_sigma_px:g} px"
        )
    else:
        ss = SpotScene()
        scene = (
            f"spot sigma {ss.psf_sigma_px:g} px, noise {ss.noise_sigma:g} grey levels; the "
            f"rows' sigma from the centroid noise as a run's first {CHUNK_FRAMES} frames learn it "
            f"from [detect] centroid_sigma_px {rig.detect.centroid_sigma_px:g}; later rows' "
            f"is narrower"
        )
    click.echo(
        f"  simulated: {n_frames} frames at random yaws and tilts within "
        f"{rig.max_tilt_deg:g} deg, each cold (the simulator's default scene: {scene})"
    )
    # forty frames: local processes unless a scheduler is named (a local Dask cluster
    # takes longer to start than the frames take)
    pool = TaskPool(scheduler, workers, local_dask=False)
    # a triangle rig on the edge lines: the same frames with the pixel fit too, so that a
    # lab sees what refine = "pixels" gives its geometry
    pixels = rig.kind == "triangle" and rig.detect.refine == "lines"
    with pool, Work("check", (4 if pixels else 2) * n_frames, unit="step") as bar:
        out = simulated_accuracy(rig, n_frames, seed, pool, progress=bar.update)
        click.echo(f"    ok {out.n_ok} of {out.n}{_figures(out)}")
        reasons = out.reasons()
        if reasons:
            click.echo("    not ok: " + ", ".join(f"{k} {v}" for k, v in sorted(reasons.items())))
        if pixels:
            with_pixels = replace(rig, detect=replace(rig.detect, refine="pixels"))
            out_p = simulated_accuracy(with_pixels, n_frames, seed, pool, progress=bar.update)
            click.echo(
                f'    with [detect] refine = "pixels" (1.33x the time a frame with the '
                f"fast extra): ok {out_p.n_ok} of {out_p.n}{_figures(out_p)}"
            )
    click.echo(
        "    (the rig file's geometry exactly, a clean scene: what the geometry allows; "
        "a real lab adds its calibration's errors)"
    )
