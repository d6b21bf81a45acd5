"""`visvec batch`: rows for a folder of images or a video file."""

from __future__ import annotations

import click

from visvec.cli.common import load, note_uncalibrated, output_options, rig_options, run_frames
from visvec.evaluate import error_stats, read_truth
from visvec.pipeline import make_pipeline
from visvec.sources import open_source


@click.command()
@click.argument("path", type=click.Path())
@rig_options
@click.option(
    "--truth",
    type=click.Path(dir_okay=False),
    default=None,
    help="Truth CSV (from `visvec simulate`): print error statistics.",
)
@output_options
def batch(path, rig_path, calibration, truth, out, fmt, method, overlay, max_frames):
    """Process a folder of images (natural sort order) or a video file."""
    rig = load(rig_path, calibration)
    run_batch(rig, path, truth, out, fmt, method, overlay, max_frames)


def run_batch(rig, path, truth, out, fmt, method, overlay, max_frames) -> None:
    """Rows of a folder or video; with a truth file, the error statistics after them."""
    names = make_pipeline(rig, method).row_type.value_columns
    truth_rows = read_truth(truth, names) if truth else None
    src = open_source(path, fps=rig.fps, max_frames=max_frames, retry_s=0.0)
    # once the frames are found, before the first row (as `track` does)
    note_uncalibrated(rig)
    rows = run_frames(
        rig,
        src,
        out=out,
        fmt=fmt,
        method=method,
        overlay=overlay,
        max_frames=max_frames,
        keep_rows=truth_rows is not None,
    )
    if truth_rows is not None:
        stats = error_stats(rows, truth_rows, names)
        for line in stats.lines():
            click.echo(line, err=out is None)
