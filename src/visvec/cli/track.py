"""`visvec track`: rows from a live camera, a video file or a stream URL."""

from __future__ import annotations

import sys

import click

from visvec.cli.common import (
    check_new_recording,
    load,
    note_uncalibrated,
    output_options,
    rig_options,
    run_frames,
)
from visvec.sources import open_source

STATUS_EVERY_S = 2.0


@click.command()
@rig_options
@click.option(
    "--camera",
    "camera",
    default=None,
    help="Camera index, video file or stream URL (default: the rig's device).",
)
@click.option(
    "--retry-s",
    type=click.FloatRange(min=0),
    default=5.0,
    show_default=True,
    help="How long to retry a camera that stops delivering frames before exit 3.",
)
@click.option(
    "--save-frames",
    type=click.Path(file_okay=False),
    default=None,
    help="Also keep every frame losslessly in this folder (PNG, with times.csv), for "
    "`visvec batch` or `calibrate zero-tilt` later.",
)
@output_options
def track(
    rig_path, calibration, camera, retry_s, save_frames, out, fmt, method, overlay, max_frames
):
    """Stream one attitude row per frame, flushed row by row, until the source ends,
    --max-frames, or Ctrl-C."""
    rig = load(rig_path, calibration)
    if save_frames:
        check_new_recording(save_frames)  # before the camera is opened
    spec = camera if camera is not None else rig.device
    if spec is None:
        raise click.UsageError("no --camera given and the rig's [camera] has no device")
    src = open_source(
        spec if isinstance(spec, int) else str(spec),
        fps=rig.fps,
        max_frames=max_frames,
        retry_s=retry_s,
        size=(rig.camera.width, rig.camera.height),
    )
    # said once the camera is open, before the first row: a live run may go on for hours
    note_uncalibrated(rig)
    run_frames(
        rig,
        src,
        out=out,
        fmt=fmt,
        method=method,
        overlay=overlay,
        max_frames=max_frames,
        save_frames=save_frames,
        # rows to a file and a person at the terminal: a status line every 2 s
        progress=STATUS_EVERY_S if out is not None and sys.stderr.isatty() else None,
    )
