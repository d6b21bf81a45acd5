"""Options and the frame loop shared by the commands."""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import sys
from pathlib import Path

import click

from visvec.data import inter_frame
from visvec.errors import ConfigError
from visvec.rig import Rig, load_rig
from visvec.sinks import UdpStream, open_sink

# the fastest frame rate an --fps may say (Hz): beyond it a frame's time rounds away
FPS_MAX = 10000.0


class FiniteFloat(click.FloatRange):
    """A number option (optionally within a range) that refuses NaN and infinity, which
    click's FloatRange lets through (every comparison with NaN is false)."""

    def convert(self, value, param, ctx):
        v = super().convert(value, param, ctx)
        if not math.isfinite(v):
            self.fail(f"{value!r}: expected a finite number", param, ctx)
        return v

    def _describe_range(self) -> str:
        # no bounds: nothing to say (click would print "x<=None")
        if self.min is None and self.max is None:
            return ""
        return super()._describe_range()


# an option whose help starts with one of these applies to that kind (or mode) only:
# `--help` lists it under that heading, after the options for every kind
KIND_PREFIXES = ("Triangle", "Markers", "Starfield", "Lamps", "Budget")


# the headings a command's --help puts its options under, by what they are about (the
# options of one kind go under that kind's heading, after these)
OPTION_GROUPS = {
    "Input options": ("--camera", "--retry-s", "--realtime", "--fps", "--follow", "--fixes",
                      "--max-frames", "--max-samples", "--silent-s"),
    "Rig options": ("--rig", "--calibration"),
    "Estimator options": ("--method",),
    "Output options": ("--out", "--format", "--covariance", "--ros-images", "--overlay",
                       "--save-frames", "--record", "--camera-out", "--out-dir", "--truth",
                       "--errors", "--summary"),
    "Live view options": ("--serve", "--keep-view", "--foxglove", "--foxglove-image-hz"),
    "Fusion options": ("--imu", "--gyro-range-dps", "--rest-s", "--max-rate-dps",
                       "--max-accel-mps2", "--gyro-noise-dps", "--accel-noise-mps2",
                       "--fix-sigma-deg", "--clock-jitter-ms", "--no-misalignment",
                       "--history-s"),
}  # fmt: skip
_GROUP_OF = {opt: head for head, opts in OPTION_GROUPS.items() for opt in opts}


class KindCommand(click.Command):
    """A command whose --help groups its options: by what they are about
    (OPTION_GROUPS), and those that apply to one target kind (their help starts
    "Triangle:", "Lamps:", ...) under that kind's heading."""

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        groups: dict[str, list[tuple[str, str]]] = {}
        for param in self.get_params(ctx):
            rec = param.get_help_record(ctx)
            if rec is None:
                continue
            names = [o for o in getattr(param, "opts", ()) if o.startswith("--")]
            head = next((_GROUP_OF[o] for o in names if o in _GROUP_OF), "Options")
            text = rec[1]
            for k in KIND_PREFIXES:
                if text.startswith(k + ":"):
                    head = f"{k} options" if k != "Budget" else "--budget options"
                    rest = text[len(k) + 1 :].lstrip()
                    rec = (rec[0], rest[:1].upper() + rest[1:])
                    break
            groups.setdefault(head, []).append(rec)
        # (what fits no heading, --help among it, last)
        order = [*OPTION_GROUPS, *(f"{k} options" for k in KIND_PREFIXES[:-1]),
                 "--budget options", "Options"]  # fmt: skip
        for head, recs in sorted(groups.items(), key=lambda kv: order.index(kv[0])):
            with formatter.section(head):
                formatter.write_dl(recs)


def rig_options(f=None, *, required: bool = True, unless: str | None = None):
    """--rig and --calibration (``@rig_options``, or ``@rig_options(required=False,
    unless="--budget")`` for a command that can run without a rig in that mode)."""
    if f is None:
        return lambda g: rig_options(g, required=required, unless=unless)
    f = click.option(
        "--calibration",
        "calibration",
        type=click.Path(dir_okay=False),
        multiple=True,
        help="Calibration file (from `visvec calibrate`) overriding the rig; repeat it to "
        "apply several in order, a later one winning (camera, zero-tilt, readout).",
    )(f)
    f = click.option(
        "--rig",
        "rig_path",
        required=required,
        type=click.Path(dir_okay=False),
        help="Rig file (TOML), see configs/." + (f"  [required unless {unless}]" if unless else ""),
    )(f)
    return f


def _scheduler_address(ctx, param, value):
    if value is None:
        return None
    if "://" not in value:
        value = f"tcp://{value}"
    scheme, _, rest = value.partition("://")
    host, _, port = rest.rpartition(":")
    if scheme not in ("tcp", "tls", "ucx", "inproc") or not host or not port.isdigit():
        raise click.BadParameter(
            f"{value!r}: expected a Dask scheduler address, tcp://HOST:PORT (as `dask "
            "scheduler` prints it)"
        )
    return value


def scheduler_options(f):
    """--scheduler and --workers: where a study's independent tasks run
    (visvec.distribute)."""
    f = click.option(
        "--workers", type=click.IntRange(min=1), default=None,
        help="Worker processes on this machine [all cores]: a local Dask cluster when the "
        "[dask] extra is installed, else a process pool (1: this process alone).",
    )(f)  # fmt: skip
    f = click.option(
        "--scheduler", metavar="ADDRESS", default=None, callback=_scheduler_address,
        help="A running Dask scheduler (tcp://HOST:PORT) whose workers run the tasks; they "
        "need this version of visvec (docs: studies on a cluster).",
    )(f)  # fmt: skip
    return f


def result_options(f):
    """--errors, --summary (batch, rate)."""
    f = click.option(
        "--summary",
        type=click.Path(dir_okay=False),
        default=None,
        help="Write the run's figures as JSON: rows, ok share, statuses and reasons; with "
        "--truth the error statistics and the sigma calibration check too.",
    )(f)
    f = click.option(
        "--errors",
        type=click.Path(dir_okay=False),
        default=None,
        help="With --truth: write each frame's errors (yaw and heading wrapped to +-180) "
        "and errors over their sigma as CSV, for plotting.",
    )(f)
    return f


def _format_available(ctx, param, value):
    if value == "rosbag2":
        from visvec.sinks.ros import check_available

        check_available()  # the extra installed, or exit 2 before any work
    return value


def meta_option(name: str, key: str, **kw):
    """An option whose value goes to the context's meta under ``key`` (read where it
    is used: visvec.cli.view), not to the command's parameters."""
    return click.option(name, expose_value=False,
                        callback=lambda ctx, _p, v: ctx.meta.__setitem__(key, v), **kw)  # fmt: skip


def foxglove_option(f):
    """--foxglove [HOST:]PORT, kept in the context's meta (visvec.cli.view)."""
    return meta_option(
        "--foxglove",
        "visvec.foxglove",
        metavar="[HOST:]PORT",
        default=None,
        help="Publish the rows live to Foxglove: a Foxglove WebSocket server on "
        "HOST:PORT (HOST 127.0.0.1 unless given; PORT 0: any free port) with the "
        "channels an --out *.mcap file holds, as they are made (pip install "
        '"visvec[foxglove]"). With an IMU: the fused rows under /visvec, the camera\'s '
        "under /visvec/camera. A recording is then replayed at its own pace.",
    )(f)


def output_options(f=None, *, rates: bool = False):
    """--out, --format, --method, --overlay, --max-frames, --serve, --foxglove,
    --covariance, --ros-images (``@output_options``; ``@output_options(rates=True)``
    for `rate`, whose --method lists the starfield's estimators)."""
    if f is None:
        return lambda g: output_options(g, rates=rates)
    f = click.option(
        "--ros-images",
        is_flag=True,
        help="With an --out *.mcap file or --format rosbag2: also each frame with its "
        "detection drawn, as sensor_msgs/CompressedImage (JPEG) on /visvec/overlay/compressed.",
    )(f)
    f = click.option(
        "--covariance",
        is_flag=True,
        help="Add the values' full 3x3 covariance to each row (its upper triangle, "
        "cov_<a>_<b>, in the values' units squared: deg^2 for yaw, pitch, roll; "
        "(deg/s)^2 for rates; mm^2, mm deg, deg^2 for a planar pose).",
    )(f)
    f = meta_option(
        "--foxglove-image-hz", "visvec.foxglove_image_hz", type=FiniteFloat(min=0),
        default=5.0, show_default=True,
        help="With --foxglove: frames with their detection drawn, at most this many a "
        "second (0: none).",
    )(f)  # fmt: skip
    f = foxglove_option(f)
    f = meta_option(
        "--keep-view", "visvec.keep_view", is_flag=True,
        help="With --serve: at the run's end keep the page (showing that the run ended) "
        "until Ctrl-C, instead of ending with the run.",
    )(f)  # fmt: skip
    f = click.option(
        "--serve",
        metavar="[HOST:]PORT",
        default=None,
        help="Show a live view in a web browser at http://HOST:PORT/ (HOST 127.0.0.1, "
        "this computer only, unless given; 0.0.0.0 for every network; PORT 0: any free "
        "port): the frame with its detection, the last row, the last minute's values and "
        "set-up aids. A recording is then replayed at its own pace; the page ends with the "
        "run (--keep-view keeps it).",
    )(f)
    f = click.option(
        "--max-frames",
        type=click.IntRange(min=1),
        default=None,
        help="Stop after this many frames.",
    )(f)
    f = click.option(
        "--overlay",
        type=click.Path(file_okay=False),
        default=None,
        help="Write each frame with the detection drawn on it to this folder.",
    )(f)
    from visvec.pipeline import METHODS, RATE_METHODS

    f = click.option(
        "--method",
        type=click.Choice(RATE_METHODS if rates else METHODS),
        default=None,
        help="Estimator: 'poisson' (default) or 'crassidis'." if rates else
        "Estimator, by the rig's kind. Triangle: 'full' (default; camera model, lever "
        "arm) or 'paper'; markers: 'full' (default) or a PnP baseline (pnp-*); lamps: "
        "'full'; starfield: 'poisson' (default) or 'crassidis' (as `rate`).",
    )(f)  # fmt: skip
    f = click.option(
        "--format",
        "fmt",
        type=click.Choice(["csv", "jsonl", "rosbag2"]),
        default="csv",
        show_default=True,
        callback=_format_available,
        help="Row format; rosbag2: a ROS 2 bag folder at --out (ROS 2 messages, as an "
        '--out *.mcap file holds them; pip install "visvec[ros]").',
    )(f)
    f = click.option(
        "--out",
        type=click.Path(dir_okay=False),
        default=None,
        help="Output file, or udp://HOST:PORT for one datagram per row (default, or '-': "
        "standard output).",
    )(f)
    return f


def load(
    rig_path: str, calibration: tuple[str, ...] = (), kind: str | None = None, what: str = ""
) -> Rig:
    """The rig (with its calibration files, in order); refused unless its target is
    ``kind`` if given."""
    note_inputs(rig_path, *calibration)
    rig = load_rig(rig_path, calibration)
    if kind is not None and rig.kind != kind:
        raise ConfigError(f"{rig_path}: [target] kind = {rig.kind!r}: {what} is for {kind} rigs")
    return rig


def note_defaults(rig: Rig) -> None:
    """Say on stderr, once, the defaults a rig runs with that refuse frames: an
    attitude rig without [platform] max_tilt_deg refuses every frame tilted more than
    its default 10 deg as impossible_tilt."""
    if rig.kind in ("triangle", "markers") and not rig.max_tilt_given:
        click.echo(
            f"visvec: note: the rig file has no [platform] max_tilt_deg: the default "
            f"{rig.max_tilt_deg:g} deg applies, and every frame tilted more is refused as "
            "impossible_tilt (set it to the largest tilt your platform can make)",
            err=True,
        )


def note_codec(rig: Rig, src) -> str | None:
    """Say on stderr, before the first row, that a triangle rig's frames come through a
    codec that predicts frames from earlier ones (the source's ``codec``, Frame.codec)
    and what that means for its rows (visvec.pipeline.triangle.codec_advice). Returns
    the line (for the live view's information), or None."""
    codec = getattr(src, "codec", "")
    from visvec.pipeline.triangle import codec_advice

    advice = codec_advice(rig, codec) if rig.kind == "triangle" and inter_frame(codec) else ""
    if not advice:
        return None
    line = f"note: {advice}"
    click.echo(f"visvec: {line}", err=True)
    return line


def note_uncalibrated(rig: Rig) -> None:
    """Say on stderr, once, that a triangle rig has no zero-tilt calibration: its tilts
    then carry whatever mounting error and target offset the rig file has (a camera
    0.5 deg askew reads 0.5 deg of tilt), which no row's sigma covers."""
    note_defaults(rig)
    if rig.kind == "triangle" and rig.zero_tilt.centroid_px is None:
        click.echo(
            "visvec: note: no zero-tilt calibration given (`visvec calibrate zero-tilt`, "
            "then --calibration): the tilts carry whatever mounting error and target offset "
            "the rig file has, which the sigma does not cover",
            err=True,
        )


try:
    import fcntl
except ImportError:  # not POSIX: outputs are not locked
    fcntl = None


def _discard_close(fh) -> None:
    try:
        fh.close()
    except OSError:
        try:
            os.close(fh.fileno())
        except (OSError, ValueError):
            pass


def _lock(fh) -> None:
    """An exclusive lock on an open file, or OSError if another process holds one."""
    if fcntl is not None:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


_INPUTS: list[Path] = []  # the files and folders this run reads
_OUTPUTS: list[tuple[Path, str]] = []  # the outputs this run writes, and their options


def forget_inputs() -> None:
    _INPUTS.clear()
    _OUTPUTS.clear()


def note_inputs(*paths) -> None:
    """Files or folders this run reads: no output may be one of them or lie inside
    an input folder (see `check_output`)."""
    for p in paths:
        if p is None or isinstance(p, int):
            continue
        p = str(p)
        if "://" in p or p == "-" or p.isdigit():
            continue
        _INPUTS.append(Path(p))


def check_output(path, option: str = "--out") -> None:
    """Refuse (exit 2, before any work) an output that is one of this run's inputs, or
    lies inside an input folder (a replay of that folder would pick it up), or shares
    its path with another of the run's outputs (or holds it, or lies in it)."""
    if path is None:
        return
    p = Path(str(path))
    if "://" in str(path) or str(path) == "-":
        return
    if ros_output(str(path)):
        from visvec.sinks.ros import check_available

        check_available()  # the extra installed, or exit 2 before any work
    target = p.resolve()
    for inp in _INPUTS:
        try:
            src = inp.resolve()
        except OSError:
            continue
        if target == src or (p.exists() and inp.exists() and os.path.samefile(p, inp)):
            raise click.BadParameter(f"{path}: this is an input of the run", param_hint=option)
        if inp.is_dir() and src in target.parents:
            raise click.BadParameter(
                f"{path}: inside the input folder {inp}; put outputs elsewhere",
                param_hint=option,
            )
    # one run's outputs each at a path of its own (--out rows.csv --errors rows.csv
    # would leave the error table where the rows were; a folder output may not hold
    # another output, nor lie in one)
    for other, opt in _OUTPUTS:
        if opt == option and other == target:
            break  # the same output asked again (as it opens)
        if other == target or other in target.parents or target in other.parents:
            raise click.BadParameter(
                f"{path}: also where {opt} goes; each output of a run needs a path of its own",
                param_hint=option,
            )
    else:
        _OUTPUTS.append((target, option))
    # the nearest folder that exists must be a folder, and one this user may write in
    for parent in p.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise click.BadParameter(
                    f"{path}: {parent} is a file, not a folder", param_hint=option
                )
            if not os.access(parent, os.W_OK | os.X_OK):
                raise click.BadParameter(
                    f"{path}: {parent} is not writable by this user", param_hint=option
                )
            break


def write_whole(path, text: str) -> None:
    """Write a small file whole or not at all: a temporary file beside it, then a
    rename (a full disk or a crash leaves the old file, never half a new one)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise click.ClickException(f"{p}: cannot write ({exc.strerror})") from None


@contextlib.contextmanager
def open_out(path: str | None, option: str = "--out"):
    """The text stream rows go to: stdout, the file ``path``, or with
    ``udp://HOST:PORT`` one datagram per row (:class:`~visvec.sinks.UdpStream`).

    A file is locked while it is written: a second run given the same file is
    refused (exit 2) instead of mixing its rows into the first's."""
    if path is None or path == "-":
        yield sys.stdout
    elif "://" in path and not path.startswith("udp://"):
        raise click.BadParameter(
            f"{path}: expected a file, - (standard output) or udp://HOST:PORT",
            param_hint=option,
        )
    elif path.startswith("udp://"):
        try:
            stream = UdpStream(path)
        except ConfigError as exc:
            raise click.BadParameter(str(exc), param_hint="--out") from exc
        try:
            yield stream
        finally:
            stream.close()
            if stream.dropped:
                click.echo(f"visvec: {path}: {stream.dropped} rows could not be sent", err=True)
    else:
        check_output(path, option)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        try:
            fh = open(path, "a", newline="")  # noqa: SIM115 - truncated once locked
        except OSError as exc:
            raise click.BadParameter(
                f"{path}: cannot write ({exc.strerror})", param_hint=option
            ) from None
        try:
            try:
                _lock(fh)
            except OSError:
                raise click.BadParameter(
                    f"{path}: another run is writing this file", param_hint=option
                ) from None
            if Path(path).is_file():
                fh.truncate(0)
            yield fh
        except BaseException:
            # a write already failed and was reported (OutputError): what is left in the
            # buffer is the row that was cut back, and closing must not write it again
            _discard_close(fh)
            raise
        else:
            fh.close()


def ros_output(path: str | None, fmt: str = "csv") -> bool:
    """Whether rows go out as ROS 2 messages: an .mcap file, or --format rosbag2."""
    return fmt == "rosbag2" or (path is not None and str(path).lower().endswith(".mcap"))


@contextlib.contextmanager
def rows_out(path: str | None, fmt: str, columns, option: str = "--out", source: str = ""):
    """A sink for rows of ``columns`` at ``path``: ROS 2 messages in an MCAP file for a
    ``.mcap`` path (see visvec.sinks.ros), else CSV or JSON lines through
    :func:`open_out` (a file, stdout or UDP); closed at the end."""
    if ros_output(path, fmt):
        from visvec.sinks.ros import McapSink

        if path is None or "://" in str(path) or str(path) == "-":
            raise ConfigError(f"{option}: ROS 2 messages go to a .mcap file or, with "
                              "--format rosbag2, a new bag folder")  # fmt: skip
        sink = McapSink(str(path), columns, source, bag=fmt == "rosbag2")
        try:
            yield sink
        finally:
            sink.close()
        return
    with open_out(path, option) as stream:
        yield open_sink(fmt, stream, columns)


def make_folder(folder: Path, option: str) -> None:
    """Make an output folder before any work, or refuse the option (exit 2)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise click.BadParameter(
            f"{folder}: cannot make this folder ({exc.strerror})", param_hint=option
        ) from None


def check_new_recording(folder: str | Path, option: str = "--save-frames") -> None:
    """Refuse (usage error, exit 2) a folder for a new recording (--save-frames,
    simulate --out) that already holds one: its frames would be overwritten one by one,
    or stale ones left beside the new, and its times.csv or truth.csv lost."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    held = [p for p in folder.iterdir()
            if p.name in ("times.csv", "truth.csv") or p.name.startswith("frame_")]  # fmt: skip
    if held:
        raise click.BadParameter(
            f"{folder} already holds a recording ({len(held)} frame_*, times.csv or "
            "truth.csv files): give a new folder for each recording",
            param_hint=option,
        )
