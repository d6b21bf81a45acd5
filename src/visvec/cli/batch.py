"""`visvec batch`: rows for a folder of images or a video file, or for many recordings
(one output each) on this machine's cores or a Dask cluster."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from visvec import recording
from visvec.cli.camera_fusion import camera_out_option, check_fusable, replay_fused, run_fused_batch
from visvec.cli.common import (
    FPS_MAX,
    FiniteFloat,
    KindCommand,
    check_output,
    load,
    note_codec,
    note_inputs,
    note_uncalibrated,
    output_options,
    result_options,
    rig_options,
    scheduler_options,
)
from visvec.cli.frames import run_frames
from visvec.cli.progress import Work
from visvec.cli.results import check_results, write_results
from visvec.cli.view import linger, open_foxglove, open_view
from visvec.distribute import TaskPool
from visvec.evaluate import error_stats, read_truth
from visvec.fuse.camera import paced
from visvec.pipeline import make_pipeline
from visvec.sources import open_source
from visvec.sources.folder import FolderSource


@click.command(cls=KindCommand)
@click.argument("paths", metavar="PATH...", nargs=-1, required=True, type=click.Path())
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
    type=FiniteFloat(min=0, max=FPS_MAX, min_open=True),
    default=None,
    help="Frame rate (Hz) of a folder of frames without times.csv or truth.csv times "
    "(default: the rig's fps); a folder's own times are used before it.",
)
@click.option(
    "--out-dir", type=click.Path(file_okay=False), default=None,
    help="Many recordings: one output per recording in this folder (NAME.csv or "
    "NAME.jsonl), the recordings processed side by side (--workers, --scheduler).",
)  # fmt: skip
@scheduler_options
@camera_out_option
@result_options
@output_options
def batch(paths, rig_path, calibration, truth, imu_path, fps, out_dir, scheduler, workers,
          camera_out, errors, summary, out, fmt, method, overlay, max_frames, serve, covariance,
          ros_images):  # fmt: skip
    """Process PATH: a folder of images (natural sort order), a video file, or a folder
    `track --record` made; or many of them with --out-dir, one output each."""
    rig = load(rig_path, calibration)
    if out_dir is not None or len(paths) > 1:
        given = [name for name, v in (("--out", out), ("--truth", truth), ("--imu", imu_path),
                                      ("--overlay", overlay), ("--serve", serve),
                                      ("--errors", errors), ("--summary", summary),
                                      ("--camera-out", camera_out),
                                      ("--ros-images", ros_images)) if v]  # fmt: skip
        if out_dir is None:
            raise click.UsageError("several recordings need --out-dir (one output each)")
        if fmt == "rosbag2":
            given.append("--format rosbag2")
        if given:
            raise click.UsageError(f"{', '.join(given)}: one recording's options; with "
                                   "--out-dir each recording has its own output")  # fmt: skip
        run_many(rig, paths, out_dir, fmt, method, max_frames, covariance, fps, scheduler,
                 workers)  # fmt: skip
        return
    if scheduler is not None or workers is not None:
        raise click.UsageError("--scheduler and --workers go with several recordings "
                               "(--out-dir)")  # fmt: skip
    path = paths[0]
    note_inputs(path, truth, imu_path)
    check_output(out)
    check_output(overlay, "--overlay")
    check_output(camera_out, "--camera-out")
    check_results(truth, errors, summary, imu_path)
    if recording.is_recording(path):
        # a `track --record` recording: said first if this rig is not the one recorded
        for what in recording.differences(path, rig_path, calibration):
            click.echo(f"visvec: warning: {path} is a recording of a live run; {what}: the "
                       "rows will differ from the run's", err=True)  # fmt: skip
        if recording.manifest(path).get("imu"):
            given = [name for name, v in (("--imu", imu_path), ("--truth", truth),
                                          ("--overlay", overlay), ("--serve", serve),
                                          ("--errors", errors), ("--summary", summary),
                                          ("--max-frames", max_frames)) if v]  # fmt: skip
            if given:
                raise click.UsageError(f"{', '.join(given)}: not with the replay of a fused "
                                       f"run (its IMU is in {path})")  # fmt: skip
            check_fusable(rig, None, None)
            replay_fused(rig, path, method, out, fmt, camera_out)
            return
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
        note_codec(rig, src)
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
    fox = open_foxglove(rig, method)
    try:
        src = open_source(path, fps=fps or rig.fps, max_frames=max_frames, retry_s=0.0)
    except BaseException:
        if fox is not None:
            fox.live.close()
            fox.live.srv.stop()
        raise
    rig = with_fps(rig, src, fps, path)
    if view is not None or fox is not None:
        src = paced(src)  # watched: at its own pace
    # once the frames are found, before the first row (as `track` does)
    note_uncalibrated(rig)
    note_codec(rig, src)
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
            watchers=[w for w in (view.state if view is not None else None, fox) if w],
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


def run_many(rig, paths, out_dir, fmt, method, max_frames, covariance, fps, scheduler,
             workers) -> None:  # fmt: skip
    """Each recording's rows to OUT_DIR/NAME.csv (or .jsonl), the recordings as tasks of
    a TaskPool; a line per recording at the end."""
    note_inputs(*paths)
    for p in paths:
        if not Path(p).exists():
            raise click.BadParameter(f"{p}: no such folder or video", param_hint="PATH")
    names = [Path(p).name or Path(p).resolve().name for p in paths]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise click.BadParameter(f"{', '.join(dup)}: two recordings of one name would write one "
                                 "output; rename one", param_hint="PATH")  # fmt: skip
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ext = "jsonl" if fmt == "jsonl" else "csv"
    tasks = [(rig, str(p), str(out / f"{n}.{ext}"), fmt, method, max_frames, covariance, fps)
             for p, n in zip(paths, names, strict=True)]  # fmt: skip
    for t in tasks:
        check_output(t[2])
    finished: set[int] = set()

    def done(i: int, r) -> None:
        finished.add(i)
        bar.update(1)

    try:
        with TaskPool(scheduler, workers) as pool:
            click.echo(f"visvec: {len(tasks)} recordings on {pool.where}", err=True)
            with Work("batch", len(tasks), unit="recording") as bar:
                results = pool.map(batch_one, tasks, done)
    except KeyboardInterrupt:
        # each output not finished named on a line of its own; no worker's traceback
        for i, t in enumerate(tasks):
            if i in finished:
                continue
            o = Path(t[2])
            state = f"incomplete ({_rows_in(o)} rows)" if o.is_file() else "not written"
            click.echo(f"visvec: interrupted: {o}: {state}", err=True)
        raise SystemExit(130) from None
    for p, t, r in zip(paths, tasks, results, strict=True):
        click.echo(f"{p}: {r['ok']} ok of {r['rows']} rows -> {t[2]}")


class _Count:
    """A watcher that counts a run's rows and its ok ones."""

    def __init__(self):
        self.rows = self.ok = 0

    def see(self, frame, row, pipe) -> None:
        self.rows += 1
        self.ok += bool(row.ok)

    def close(self) -> None:
        pass


def _rows_in(path: Path) -> int:
    """The rows a CSV or JSON-lines output holds (its lines less a CSV's header)."""
    with open(path, errors="replace") as fh:
        n = sum(1 for _ in fh)
    return max(n - (path.suffix == ".csv"), 0)


def with_fps(rig, src, fps: float | None, path, say: bool = True):
    """The rig the run's pipeline is made with: at --fps where the frames are timed by
    it (a folder without its own times), so that what expects the frame interval (the
    star field's frame jumps and rates) expects that one; the rig as it is where the
    source has its own times (a folder's times.csv or truth.csv, a video's container),
    said on stderr."""
    if not fps:
        return rig
    own = getattr(src, "times_from", None)
    if own is None and not isinstance(src, FolderSource):
        own = "the video's own"  # a video's frames are timed by its container
    if own:
        if say:
            click.echo(f"visvec: note: {path} has its own frame times ({own}): they are "
                       f"used, not --fps {fps:g}", err=True)  # fmt: skip
        return rig
    return replace(rig, fps=fps)


def batch_one(task) -> dict:
    """One recording of :func:`run_many`: its rows written, their count and ok count."""
    rig, path, out, fmt, method, max_frames, covariance, fps = task
    src = open_source(path, fps=fps or rig.fps, max_frames=max_frames, retry_s=0.0)
    rig = with_fps(rig, src, fps, path, say=False)
    count = _Count()
    run_frames(rig, src, out=out, fmt=fmt, method=method, overlay=None, max_frames=max_frames,
               watchers=[count], what=f"batch {Path(path).name}",
               covariance=covariance)  # fmt: skip
    return {"rows": count.rows, "ok": count.ok}
