"""`visvec rate`: angular rate from a star-field recording, or the paper's error budget."""

from __future__ import annotations

import math

import click

from visvec.cli.batch import run_batch
from visvec.cli.common import (
    FPS_MAX,
    FiniteFloat,
    KindCommand,
    check_output,
    load,
    note_inputs,
    output_options,
    result_options,
    rig_options,
)
from visvec.estimate.rate import rate_budget


@click.command(cls=KindCommand)
@click.argument("path", type=click.Path(), required=False)
@rig_options(required=False, unless="--budget")
@click.option(
    "--truth",
    type=click.Path(dir_okay=False),
    default=None,
    help="Truth CSV (from `visvec simulate`): print error statistics.",
)
@click.option(
    "--budget",
    is_flag=True,
    help="Print the paper's error budget (Fasano et al. Eqs. 14, 26, 28) and exit.",
)
@click.option(
    "--ifov-deg",
    type=FiniteFloat(min=0, min_open=True),
    default=None,
    help="Budget: angle of one pixel (default: the rig's, else 0.017).",
)
@click.option(
    "--fps",
    type=FiniteFloat(min=0, max=FPS_MAX, min_open=True),
    default=None,
    help="Frame rate (Hz): of a folder of frames without times.csv (default: the rig's "
    "fps), and for --budget (default: the rig's, else 10).",
)
@click.option(
    "--stars",
    type=FiniteFloat(min=1),
    default=40.0,
    show_default=True,
    help="Budget: stars detected per frame.",
)
@click.option(
    "--pixels-per-star",
    type=FiniteFloat(min=1),
    default=10.0,
    show_default=True,
    help="Budget: pixels above the threshold per star.",
)
@click.option(
    "--off-boresight-deg",
    type=FiniteFloat(min=0, min_open=True),
    default=5.0,
    show_default=True,
    help="Budget: mean angle of the stars from the boresight.",
)
@click.option(
    "--rate-dps",
    type=FiniteFloat(),
    default=0.0,
    show_default=True,
    help="Budget: rate about the boresight (for the full Eq. 26).",
)
@result_options
@output_options(rates=True)
def rate(
    path, rig_path, calibration, truth, budget, ifov_deg, fps, stars, pixels_per_star,
    off_boresight_deg, rate_dps, errors, summary, out, fmt, method, overlay, max_frames, serve,
    covariance, ros_images,
):  # fmt: skip
    """Angular rate (deg/s, camera frame) from consecutive star images in PATH (a folder
    or a video), one row per frame; or, with --budget, the expected 1-sigma accuracy."""
    rig = load(rig_path, calibration, "starfield", "visvec rate") if rig_path else None
    note_inputs(path, truth)
    check_output(out)
    check_output(overlay, "--overlay")
    if budget:
        if ifov_deg is None:
            ifov_deg = math.degrees(math.atan(1.0 / rig.camera.fx)) if rig else 0.017
        if fps is None:
            fps = rig.fps if rig else 10.0
        b = rate_budget(ifov_deg, fps, stars, pixels_per_star, off_boresight_deg, rate_dps)
        click.echo(
            f"error budget (Fasano et al. 2013) for IFOV {ifov_deg:.4g} deg, {fps:g} fps, "
            f"{stars:g} stars of {pixels_per_star:g} px, {off_boresight_deg:g} deg "
            "off the boresight:"
        )
        click.echo(f"  sigma wx = sigma wy = {b.cross:.3g} deg/s   (Eq. 14)")
        click.echo(f"  sigma wz            = {b.boresight:.3g} deg/s   (Eq. 28)")
        if rate_dps:
            click.echo(
                f"  sigma wz at {rate_dps:g} deg/s = {b.boresight_full:.3g} deg/s   (Eq. 26)"
            )
        return
    if path is None or rig is None:
        raise click.UsageError("give PATH and --rig (or --budget)")
    run_batch(rig, path, truth, out, fmt, method, overlay, max_frames, serve, rig_path, "rate",
              errors=errors, summary=summary, covariance=covariance,
              ros_images=ros_images, fps=fps)  # fmt: skip
