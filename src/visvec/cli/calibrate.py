"""`visvec calibrate zero-tilt` and `visvec calibrate camera`."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import click
import numpy as np

from visvec.calib.camera import RECIPES, calibrate_camera, camera_section, parse_pattern
from visvec.calib.tomlout import dumps
from visvec.calib.zero_tilt import calibrate_zero_tilt, calibration_sections
from visvec.cli.common import load, rig_options
from visvec.data import Status
from visvec.errors import ConfigError, SourceError
from visvec.pipeline import TrianglePipeline
from visvec.sources import open_source
from visvec.sources.folder import IMAGE_SUFFIXES, natural_key


@click.group()
def calibrate():
    """Calibrate the rig: zero-tilt offsets, camera intrinsics."""


@calibrate.command("zero-tilt")
@click.argument("frames", type=click.Path())
@rig_options
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Calibration file to write (use with --calibration).",
)
def zero_tilt(frames, rig_path, calibration, out):
    """Zero-tilt offsets from FRAMES (folder or video) taken with the platform level at
    several yaws: target offset from the rotation axis and camera mounting tilt (for
    --method full), zero-tilt centroid (for --method paper)."""
    rig = load(rig_path, calibration)
    if rig.kind != "triangle":
        raise ConfigError(
            f"{rig_path}: [target] kind = {rig.kind!r}: zero-tilt calibration is for triangle rigs"
        )
    pipe = TrianglePipeline(rig, "full")
    dets, names, bad = [], [], 0
    for frame in open_source(frames, fps=rig.fps, retry_s=0.0):
        row = pipe.process(frame)
        if pipe.last_detection is not None and pipe.last_detection.status is Status.OK:
            dets.append(pipe.last_detection)
            names.append(frame.name or f"frame {frame.index}")
        else:
            bad += 1
            click.echo(
                f"frame {frame.index}: skipped ({row.status}: {';'.join(row.warnings)})", err=True
            )
    res = calibrate_zero_tilt(dets, rig)
    sec = calibration_sections(res, rig)
    click.echo(f"zero-tilt calibration from {len(dets)} frames ({bad} skipped)")
    click.echo(
        f"  target offset from the axis: dx {res.target_offset_mm[0]:+.2f} +- "
        f"{res.sigma_target_offset_mm[0]:.2f} mm, dy {res.target_offset_mm[1]:+.2f} +- "
        f"{res.sigma_target_offset_mm[1]:.2f} mm"
    )
    click.echo(
        f"  camera mounting tilt: about b1 {res.camera_tilt_deg[0]:+.4f} +- "
        f"{res.sigma_camera_tilt_deg[0]:.4f} deg, about b2 {res.camera_tilt_deg[1]:+.4f}"
        f" +- {res.sigma_camera_tilt_deg[1]:.4f} deg"
    )
    click.echo(
        f"  zero-tilt centroid (paper): u {res.centroid_px[0]:.3f} +- "
        f"{res.sigma_centroid_px[0]:.3f} px, v {res.centroid_px[1]:.3f} +- "
        f"{res.sigma_centroid_px[1]:.3f} px"
    )
    click.echo(
        f"  residual: rms {res.rms_px:.4f} px, worst frame {float(np.max(res.residual_px)):.4f} px"
    )
    click.echo("  per frame (yaw found, rms vertex residual):")
    for name, yaw, r in zip(names, res.yaw_deg, res.residual_px, strict=True):
        click.echo(f"    {name}: yaw {yaw:+9.3f} deg, {r:.4f} px")
    if not res.converged:
        click.echo("visvec: error: the calibration did not converge; nothing written", err=True)
        raise SystemExit(1)
    header = (
        f"visvec zero-tilt calibration, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC\n"
        f"rig {rig_path}, frames {frames} ({len(dets)} used)"
    )
    Path(out).write_text(dumps(sec, header))
    click.echo(f"wrote {out}")


@calibrate.command("camera")
@click.argument("frames", type=click.Path(exists=False))
@click.option("--pattern", required=True, help="Inner corners, COLSxROWS (for example 9x6).")
@click.option(
    "--square-mm",
    required=True,
    type=click.FloatRange(min=0, min_open=True),
    help="Chessboard square size, mm.",
)
@click.option(
    "--recipe",
    type=click.Choice(list(RECIPES)),
    default="precise",
    show_default=True,
    help="Corner detection recipe.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the [camera] section to this file.",
)
def camera(frames, pattern, square_mm, recipe, out):
    """Intrinsics and distortion from chessboard photos (a folder or a glob)."""
    pat = parse_pattern(pattern)
    p = Path(frames)
    if p.is_dir():
        files = [f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES]
    else:
        files = [f for f in p.parent.glob(p.name) if f.suffix.lower() in IMAGE_SUFFIXES]
    files.sort(key=lambda f: natural_key(f.name))
    if not files:
        raise SourceError(f"{frames}: no images found")
    cal = calibrate_camera(files, pat, square_mm, recipe)
    click.echo(
        f"camera calibration from {len(cal.files)} views "
        f"({len(cal.skipped)} without the pattern: {', '.join(cal.skipped) or '-'})"
    )
    click.echo(
        f"  fx {cal.K[0, 0]:.3f}  fy {cal.K[1, 1]:.3f}  cx {cal.K[0, 2]:.3f}  "
        f"cy {cal.K[1, 2]:.3f} px"
    )
    click.echo("  dist " + " ".join(f"{x:+.6f}" for x in cal.dist))
    click.echo(f"  rms reprojection error {cal.rms_px:.4f} px")
    for name, e in zip(cal.files, cal.per_view_px, strict=True):
        flag = "  <- outlier" if name in cal.outliers else ""
        click.echo(f"    {name}: {e:.4f} px{flag}")
    sec = {"camera": camera_section(cal)}
    text = dumps(
        sec,
        f"visvec camera calibration ({recipe}), pattern {pattern}, "
        f"square {square_mm} mm, rms {cal.rms_px:.4f} px",
    )
    if out:
        Path(out).write_text(text)
        click.echo(f"wrote {out}")
    else:
        click.echo(text)
