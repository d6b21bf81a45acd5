"""`visvec track`: rows from a live camera, a video file or a stream URL."""

from __future__ import annotations

import click

from visvec import recording
from visvec.cli.camera_fusion import camera_out_option, check_fusable, run_fused_camera
from visvec.cli.common import (
    FiniteFloat,
    KindCommand,
    check_new_recording,
    check_output,
    load,
    note_codec,
    note_inputs,
    note_uncalibrated,
    output_options,
    rig_options,
)
from visvec.cli.frames import run_frames
from visvec.cli.view import foxglove_server, linger, open_foxglove, open_view
from visvec.errors import SourceError
from visvec.fuse.camera import paced
from visvec.sources import open_source


@click.command(cls=KindCommand)
@rig_options
@click.option(
    "--camera",
    "camera",
    default=None,
    help="Camera index, video file or stream URL (default: the rig's device).",
)
@click.option(
    "--retry-s",
    type=FiniteFloat(min=0),
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
@click.option(
    "--imu",
    "imu_src",
    default=None,
    metavar="SOURCE",
    help="Fuse an IMU stream with the camera's fixes in this process: the rows are the "
    "fused ones at the IMU's rate. SOURCE as for `visvec fuse --imu` (udp://HOST:PORT, "
    "-, serial:///dev/DEVICE?baud=N, a file).",
)
@camera_out_option
@click.option(
    "--record",
    type=click.Path(file_okay=False),
    default=None,
    metavar="DIR",
    help="Keep the run as a recording in this new folder: the frames (lossless) with "
    "their times, the IMU's rows as they came (with --imu), the rig and calibration "
    "files, the rows. `visvec batch DIR --rig RIG` replays it to the same rows.",
)
@click.option(
    "--realtime",
    is_flag=True,
    help="Deliver a recording's frames at their own pace, as a camera would (a replay).",
)
@output_options
def track(
    rig_path, calibration, camera, retry_s, save_frames, imu_src, camera_out, record, realtime,
    out, fmt, method, overlay, max_frames, serve, covariance, ros_images
):  # fmt: skip
    """Stream one attitude row per frame, flushed row by row, until the source ends,
    --max-frames, or Ctrl-C. With --imu, stream fused rows at the IMU's rate."""
    rig = load(rig_path, calibration)
    note_inputs(camera)
    check_output(out)
    check_output(overlay, "--overlay")
    check_output(save_frames, "--save-frames")
    check_output(camera_out, "--camera-out")
    if imu_src is not None:
        check_fusable(rig, overlay, save_frames)
    elif camera_out:
        raise click.UsageError("--camera-out goes with --imu")
    if save_frames:
        check_new_recording(save_frames)  # before the camera is opened
    spec = camera if camera is not None else rig.device
    if spec is None:
        raise click.UsageError("no --camera given and the rig's [camera] has no device")
    if record:
        if save_frames:
            raise click.UsageError("--record keeps the frames itself: not with --save-frames")
        check_output(record, "--record")
        check_new_recording(record, "--record")  # before the camera is opened
        if recording.is_recording(record):
            raise click.BadParameter(f"{record} already holds a recording: give a new folder "
                                     "for each recording", param_hint="--record")  # fmt: skip
    if isinstance(spec, str) and "://" in spec:
        # said before connecting: a rig file's device can point anywhere
        from urllib.parse import urlsplit

        u = urlsplit(spec)
        try:
            port = f":{u.port}" if u.port else ""
        except ValueError:
            port = ""
        click.echo(f"visvec: connecting to {u.scheme}://{u.hostname}{port}", err=True)
    # bound before the camera opens: a port in use is refused first (exit 2)
    view = open_view(serve, rig, rig_path, method, _shown(spec))
    if imu_src is None:
        fox, fox_server = open_foxglove(rig, method), None
    else:
        fox, fox_server = None, foxglove_server()
    try:
        src = open_source(
            spec if isinstance(spec, int) else str(spec),
            fps=rig.fps,
            max_frames=max_frames,
            retry_s=retry_s,
            size=(rig.camera.width, rig.camera.height),
            controls=rig.controls,
        )
    except SourceError as exc:
        if fox is not None:
            fox.live.close()
            fox.live.srv.stop()
        if fox_server is not None:
            fox_server.stop()
        raise SourceError(f"{exc}{_advice(spec)}") from None
    if record:
        # begun once the camera is open: a camera that cannot be opened leaves no
        # recording behind (the same folder can be given again)
        recording.start(record, rig_path, calibration, str(spec), imu_src)
    # what a camera runs with, and the settings it refused or that move the measurement
    for line in getattr(src, "settings", []):
        click.echo(f"visvec: {line}", err=True)
    for line in getattr(src, "settings_warnings", []):
        click.echo(f"visvec: warning: {line}", err=True)
    if view is not None:
        view.state.info.extend(getattr(src, "settings", []))
        view.state.info.extend(f"warning: {w}" for w in getattr(src, "settings_warnings", []))
    # said once the camera is open, before the first row: a live run may go on for hours
    note_uncalibrated(rig)
    codec_line = note_codec(rig, src)
    if view is not None and codec_line:
        view.state.info.append(codec_line)
    source = src
    if realtime:
        src = paced(src)
    try:
        if imu_src is not None:
            run_fused_camera(rig, src, imu_src, method, out, fmt, camera_out, view, fox_server,
                             record)  # fmt: skip
            return
        run_frames(
            rig,
            src,
            out=out,
            fmt=fmt,
            method=method,
            overlay=overlay,
            max_frames=max_frames,
            save_frames=save_frames or record,
            what="track",
            covariance=covariance,
            ros_images=ros_images,
            watchers=[
                w
                for w in (
                    view.state if view is not None else None,
                    fox,
                    _row_recorder(record, rig, method),
                )
                if w
            ],
        )
        if record:
            from pathlib import Path

            n = len(list(Path(record).glob("frame_*.png")))
            click.echo(f"visvec: recorded in {record}: {n} frames and the rows; `visvec batch "
                       f"{record} --rig RIG` replays it", err=True)  # fmt: skip
    finally:
        note_passed_over(source)
        linger(view)


def _row_recorder(record, rig, method):
    """The recording's rows.csv (--record without --imu), or None."""
    if not record:
        return None
    from pathlib import Path

    from visvec.cli.frames import RowRecorder
    from visvec.pipeline import make_pipeline

    return RowRecorder(Path(record) / "rows.csv", make_pipeline(rig, method).row_type.columns)


def note_passed_over(src) -> None:
    """How many frames of a live stream came while the pipeline was busy with an
    earlier one, and were passed over for the newest (visvec.sources.reader)."""
    n = getattr(src, "dropped", 0)
    if n:
        click.echo(
            f"visvec: {n} frames of the stream came while the pipeline was busy and were "
            "passed over for the newest (the rows skip their numbers)",
            err=True,
        )


def _advice(spec) -> str:
    """What the command line offers when the camera cannot be opened."""
    if str(spec).isdigit():
        return "; --camera also takes a video file or URL"
    if "://" in str(spec):
        return " (--retry-s sets how long it is waited for)"
    return ""


def _shown(spec) -> str:
    """The camera as the page names it: a URL without its user and password."""
    if isinstance(spec, int):
        return f"camera {spec}"
    text = str(spec)
    if "://" in text and "@" in text.split("://", 1)[1].split("/", 1)[0]:
        scheme, rest = text.split("://", 1)
        return f"{scheme}://" + rest.split("@", 1)[1]
    return text
