"""The camera and an IMU in one process (`track --imu`, `batch --imu`)."""

from __future__ import annotations

import queue
from contextlib import ExitStack, nullcontext
from pathlib import Path

import click

from visvec.cli.common import rows_out
from visvec.cli.frames import FrameRecorder
from visvec.cli.fuse import (
    echo_learned,
    live_setup,
    live_summary,
    options_model,
    with_declared_range,
)
from visvec.cli.view import foxglove_live, open_foxglove, say_published
from visvec.errors import ConfigError, InputFileError
from visvec.fuse.camera import CameraFixes
from visvec.fuse.inputs import Fix, fix_from_row, read_imu
from visvec.fuse.live import EventLog, Reader, read_event_log, replay_live, run_live
from visvec.fuse.options import FusionOptions
from visvec.fuse.replay import fuse as run_fusion
from visvec.fuse.run import fused_rows
from visvec.output import AttitudeRow, PoseRow
from visvec.pipeline import make_pipeline
from visvec.recording import EVENTS, manifest, rows_file, write_imu_csv
from visvec.sinks import Tee, row_writer
from visvec.sinks.foxglove import Published

camera_out_option = click.option(
    "--camera-out",
    default=None,
    type=click.Path(dir_okay=False),
    help="With --imu: the camera's own rows to this file (or udp://HOST:PORT).",
)


def check_fusable(rig, overlay, save_frames) -> None:
    """Refuse, before anything starts, what cannot be fused."""
    if rig.kind == "starfield":
        raise click.UsageError("--imu: a starfield rig gives rates, not fixes to fuse")
    if overlay or save_frames:
        raise click.UsageError("--overlay and --save-frames do not go with --imu yet")


def _planar(rig) -> bool:
    return rig.kind == "lamps"


def run_fused_camera(rig, frames, imu_src, method, out, fmt, camera_out, view=None,
                     fox_server=None, record=None) -> None:  # fmt: skip
    """Camera in a thread, IMU read in another, fused rows written by this one. With
    ``fox_server`` (--foxglove), the fused rows published under /visvec and the
    camera's under /visvec/camera. With ``record`` (--record: a folder that
    visvec.recording.start made), the run kept there (visvec.recording)."""
    planar = _planar(rig)
    events: queue.Queue = queue.Queue()
    imu = Reader("imu", imu_src, events)
    try:
        imu.check()
    except (ConfigError, InputFileError) as exc:
        raise click.BadParameter(str(exc), param_hint="--imu") from None
    pipe = make_pipeline(rig, method)

    opts = FusionOptions(gyro_range_dps=rig.imu.gyro_range_dps)

    setup = live_setup(opts)
    log = None
    with ExitStack() as stack:
        cam_sink = None
        if camera_out:
            cam_sink = stack.enter_context(
                rows_out(camera_out, fmt, pipe.row_type.columns, "--camera-out")
            )
        frame_rec = None
        if record:
            # the recording: its frames (after each row), the camera's and the fused
            # rows, every event the fusion loop takes
            rec = Path(record)
            kept = stack.enter_context(rows_file(rec / "camera.csv", pipe.row_type.columns))
            cam_sink = kept if cam_sink is None else Tee(cam_sink, kept)
            frame_rec = FrameRecorder(rec)
            stack.callback(frame_rec.close)
            log = EventLog(rec / EVENTS)
            stack.callback(log.close)
        state = view.state if view is not None else None
        fox_cam = (open_foxglove(rig, method, "/visvec/camera", fox_server)
                   if fox_server is not None else None)  # fmt: skip
        if fox_server is not None:
            stack.callback(fox_server.stop)
            stack.callback(fox_cam.close)
        watchers = [w for w in (frame_rec, state, fox_cam) if w is not None]
        camera = CameraFixes(frames, pipe, events, cam_sink, watcher=_Watchers(watchers))

        def open_rows(is_planar: bool):
            cols = PoseRow.columns if is_planar else AttitudeRow.columns
            sink = stack.enter_context(rows_out(out, fmt, cols))
            if record:
                kept = stack.enter_context(rows_file(Path(record) / "rows.csv", cols))
                sink = Tee(sink, kept)
            if fox_server is not None:
                live = foxglove_live(fox_server, cols, rig, image=False)
                stack.callback(say_published, live, False)
                sink = Published(sink, live)
            return sink if state is None else _Shown(sink, state)

        summary = run_live(imu, camera, setup, open_rows, kind=planar, end_with_fixes=True,
                           echo=lambda m: click.echo(m, err=True), record=log)  # fmt: skip
        camera.stop.set()
    click.echo(live_summary(summary) + f"; camera: {camera.n_frames} frames, {camera.n_ok} ok",
               err=True)  # fmt: skip
    echo_learned(summary.engine)
    if record:
        n = write_imu_csv(record)
        click.echo(f"visvec: recorded in {record}: {camera.n_frames} frames, {n} IMU rows, "
                   f"the rows; `visvec batch {record} --rig RIG` replays it", err=True)  # fmt: skip
    if summary.refused:
        raise SystemExit(2)


def replay_fused(rig, folder, method, out, fmt, camera_out) -> None:
    """A `track --imu --record` recording replayed: its frames through the pipeline
    (the camera's rows, to ``camera_out``), then the fusion loop given the recorded
    events (visvec.fuse.live.replay_live): the fused rows are the run's."""
    from visvec.sources import open_source

    folder = Path(folder)
    planar = _planar(rig)
    pipe = make_pipeline(rig, method)
    rows = {}
    with (rows_out(camera_out, fmt, pipe.row_type.columns, "--camera-out") if camera_out
          else nullcontext()) as sink:  # fmt: skip
        write = row_writer(sink) if sink is not None else None
        for frame in open_source(str(folder), fps=rig.fps, retry_s=0.0):
            row = pipe.process(frame)
            rows[row.frame] = row
            if write is not None:
                write(row)
    events = read_event_log(folder / EVENTS)
    opts = FusionOptions(gyro_range_dps=rig.imu.gyro_range_dps)

    setup = live_setup(opts)
    m = manifest(folder)
    with ExitStack() as stack:

        def open_rows(is_planar: bool):
            cols = PoseRow.columns if is_planar else AttitudeRow.columns
            return stack.enter_context(rows_out(out, fmt, cols))

        summary = replay_live(events, rows, setup, open_rows, kind=planar, end_with_fixes=True,
                              echo=lambda msg: click.echo(msg, err=True),
                              sources=(str(m.get("imu")), str(m.get("source"))))  # fmt: skip
    click.echo(live_summary(summary) + f"; camera: {len(rows)} frames replayed", err=True)
    echo_learned(summary.engine)


class _Shown:
    """A sink whose rows the live view also shows (after they are written)."""

    def __init__(self, sink, state):
        self.sink = sink
        self.state = state

    def write(self, row: dict) -> None:
        self.sink.write(row)
        self.state.fused(row)

    def write_row(self, row) -> None:
        self.write(row.as_dict())


class _Watchers:
    """The camera's watchers (the live view, Foxglove), each seeing every frame."""

    def __init__(self, watchers):
        self.watchers = watchers

    def see(self, frame, row, pipe) -> None:
        for w in self.watchers:
            w.see(frame, row, pipe)


def run_fused_batch(rig, frames, imu_path, method, out, fmt, camera_out) -> None:
    """A recording and its IMU file: every frame processed, its ok rows fixes available
    at their exposure plus the processing latency, then the replay (as `visvec fuse`)."""
    planar = _planar(rig)
    pipe = make_pipeline(rig, method)
    fixes: list[Fix] = []
    with (
        rows_out(camera_out, fmt, pipe.row_type.columns, "--camera-out")
        if camera_out
        else (nullcontext()) as sink
    ):
        for frame in frames:
            row = pipe.process(frame)
            if sink is not None:
                sink.write(row.as_dict())
            f = fix_from_row(row, planar)  # its full covariance kept
            if f is not None:
                fixes.append(f)
    imu = read_imu(imu_path, planar=planar)
    opts = with_declared_range(FusionOptions(), rig.imu.gyro_range_dps, "the rig's [imu]")
    opts = with_declared_range(opts, imu.gyro_range_dps, imu_path)
    model, limits = options_model(planar, imu.period_s, opts)
    n = n_ok = 0
    with rows_out(out, fmt, PoseRow.columns if planar else AttitudeRow.columns) as sink:
        write = row_writer(sink)
        for row in fused_rows(
            run_fusion(imu, fixes, model, limits=limits, gyro_range_dps=opts.gyro_range_dps), model
        ):
            write(row)
            n += 1
            n_ok += int(row.ok)
    click.echo(f"visvec: {n} inertial samples, {n_ok} fused; {len(fixes)} ok fixes", err=True)
