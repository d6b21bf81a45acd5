"""`visvec batch`: rows for a folder of images or a video file."""

from __future__ import annotations

import click

from visvec.cli.camera_fusion import camera_out_option, check_fusable, run_fused_batch
from visvec.cli.common import (
    FiniteFloat,
    KindCommand,
    check_output,
    load,
    note_inputs,
    note_uncalibrated,
    output_options,
    result_options,
    rig_options,
)
from visvec.cli.frames import run_frames
from visvec.cli.results import check_results, write_results
from visvec.cli.view import linger, open_view
from visvec.evaluate import error_stats, read_truth
from visvec.fuse.camera import paced
from visvec.pipeline import make_pipeline
from visvec.sources import open_source


@click.command(cls=KindCommand)
@click.argument("path", type=click.Path())
@rig_options
@click.option(
    "--truth",
    type=click.Path(dir_okay=False),
    default=None,
    help="Truth CSV (from `visvec simulate`): print error statistics.",
)
@click.option(
    "--imu",
    "imu_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="An IMU file on the frames' clock: the rows are the fused ones at its rate, the "
    "frames' ok rows the fixes (available at their exposure plus their latency).",
)
@click.option(
    "--fps",
    type=FiniteFloat(min=0, min_open=True),
    default=None,
    help="Frame rate (Hz) of a folder of frames without times.csv (default: the rig's fps).",
)
@camera_out_option
@result_options
@output_options
def batch(path, rig_path, calibration, truth, imu_path, fps, camera_out, errors, summary, out,
          fmt, method, overlay, max_frames, serve, covariance, ros_images):  # fmt: skip
    """Process a folder of images (natural sort order) or a video file."""
    rig = load(rig_path, calibration)
    note_inputs(path, truth, imu_path)
    check_output(out)
    check_output(overlay, "--overlay")
    check_output(camera_out, "--camera-out")
    check_results(truth, errors, summary, imu_path)
    if imu_path is not None:
        check_fusable(rig, overlay, None)
        if serve:
            raise click.UsageError(
                "--serve does not go with --imu on a recording yet; `visvec track --imu ... "
                "--serve` shows a live fused run"
            )
        if truth:
            raise click.UsageError("--truth compares frames; give `visvec fuse --truth` the "
                                   "fused rows' truth instead")  # fmt: skip
        src = open_source(path, fps=rig.fps, max_frames=max_frames, retry_s=0.0)
        note_uncalibrated(rig)
        run_fused_batch(rig, src, imu_path, method, out, fmt, camera_out)
        return
    if camera_out:
        raise click.UsageError("--camera-out goes with --imu")
    run_batch(rig, path, truth, out, fmt, method, overlay, max_frames, serve, rig_path,
              errors=errors, summary=summary, covariance=covariance,
              ros_images=ros_images, fps=fps)  # fmt: skip


def run_batch(
    rig, path, truth, out, fmt, method, overlay, max_frames, serve=None, rig_path="",
    what="batch", errors=None, summary=None, covariance=False, ros_images=False, fps=None,
) -> None:  # fmt: skip
    """Rows of a folder or video; with a truth file, the error statistics after them
    (and with ``errors``, ``summary`` files of them). With ``serve``, a live view, the
    frames replayed at their own pace."""
    check_results(truth, errors, summary)
    names = make_pipeline(rig, method).row_type.value_columns
    truth_rows = read_truth(truth, names) if truth else None
    view = open_view(serve, rig, rig_path, method, str(path))  # a bad port: before the frames
    src = open_source(path, fps=fps or rig.fps, max_frames=max_frames, retry_s=0.0)
    if fps and getattr(src, "times", None):
        click.echo(f"visvec: note: {path} has its own frame times (times.csv): --fps "
                   f"{fps:g} is not used for them", err=True)  # fmt: skip
    if view is not None:
        src = paced(src)
    # once the frames are found, before the first row (as `track` does)
    note_uncalibrated(rig)
    try:
        rows = run_frames(
            rig,
            src,
            out=out,
            fmt=fmt,
            method=method,
            overlay=overlay,
            max_frames=max_frames,
            keep_rows=truth_rows is not None or summary is not None,
            watchers=[view.state] if view is not None else None,
            what=what,
            covariance=covariance,
            ros_images=ros_images,
        )
    finally:
        linger(view)
    stats = None
    if truth_rows is not None:
        stats = error_stats(rows, truth_rows, names)
        for line in stats.lines():
            click.echo(line, err=out is None)
    write_results(errors, summary, rows, truth_rows, stats, names)
