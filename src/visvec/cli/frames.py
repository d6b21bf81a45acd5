"""The frame loop of `batch`, `rate` and `track`: each frame's row is written (and
flushed) first; then the run's watchers see the frame, its row and its detection (the
frames kept, the overlays drawn, the status line, the live view), so none of them adds
to a row's latency."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Protocol

import click

from visvec.cli.common import check_new_recording, make_folder, ros_output, rows_out
from visvec.data import Frame
from visvec.errors import NoOkRows
from visvec.imageio import write_image
from visvec.output import Row
from visvec.pipeline import Pipeline, make_pipeline
from visvec.rig import Rig


class Watcher(Protocol):
    """What sees each frame after its row is out."""

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None: ...

    def close(self) -> None: ...


class FrameRecorder:
    """Raw frames saved as DIR/frame_NNNNNN.png with DIR/times.csv (file,time_s), the
    sidecar a folder source reads: `visvec batch DIR` replays the run with its times.
    Each frame's line is flushed when the frame is saved."""

    def __init__(self, folder: str | Path):
        self.dir = Path(folder)
        check_new_recording(self.dir)
        make_folder(self.dir, "--save-frames")
        self._times = open(self.dir / "times.csv", "w", newline="")  # noqa: SIM115
        # frame: its number in the run; late: read late (its row warned read_late, no
        # fix): a replay (`batch DIR`) gives the run's rows
        self._times.write("file,time_s,time_unix,frame,late\n")

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        if frame.image is None:
            return
        name = f"frame_{frame.index:06d}.png"
        if not write_image(self.dir / name, frame.image):
            raise click.ClickException(f"{self.dir / name}: cannot write the frame")
        unix = "" if frame.time_unix is None else f"{frame.time_unix:.6f}"
        # time_s to the last bit: a replay times its frames as the run did
        self._times.write(f"{name},{frame.time_s!r},{unix},{frame.index},{int(frame.late)}\n")
        self._times.flush()

    def close(self) -> None:
        self._times.close()


class RowRecorder:
    """Each row, as written, into a recording's rows.csv (`track --record`)."""

    def __init__(self, path: Path, columns):
        from visvec.recording import rows_file
        from visvec.sinks.writers import row_writer

        self._file = rows_file(path, columns)
        self.write = row_writer(self._file.__enter__())

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        self.write(row)

    def close(self) -> None:
        self._file.__exit__(None, None, None)


class RosImages:
    """Each frame with its detection drawn, into the ROS 2 output as a JPEG
    CompressedImage (``--ros-images``)."""

    def __init__(self, sink, rig: Rig):
        self.sink = sink
        self.rig = rig

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        if frame.image is None:
            return
        import cv2

        from visvec.overlay import draw_overlay

        img = draw_overlay(frame.image, pipe.last_detection, row, self.rig)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            self.sink.image(frame.time_s, buf.tobytes())

    def close(self) -> None:
        pass


class OverlayWriter:
    """Each frame with its detection drawn (:func:`visvec.overlay.draw_overlay`) as
    DIR/overlay_NNNNNN.png."""

    def __init__(self, folder: str | Path, rig: Rig):
        self.dir = Path(folder)
        self.rig = rig
        make_folder(self.dir, "--overlay")

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        if frame.image is None:
            return
        from visvec.overlay import draw_overlay

        img = draw_overlay(frame.image, pipe.last_detection, row, self.rig)
        if not write_image(self.dir / f"overlay_{frame.index:06d}.png", img):
            raise click.ClickException(
                f"{self.dir}: cannot write the overlay of frame {frame.index}"
            )

    def close(self) -> None:
        pass


# the reasons a status line names for the rows not ok (the most frequent first)
PROGRESS_REASONS = 2
# the bar's text (the ok share, the last values) is remade at most this often (s)
TEXT_EVERY_S = 0.5


class Progress:
    """The run's progress on stderr (:class:`visvec.cli.progress.Work`: a bar at a
    terminal, a status line every ``every`` seconds otherwise), and its summary line at
    the end: frames, the ok share, the frame rate, the last ok values, and why the
    others were not ok (the counts the pipeline ``pipe`` keeps of its rows)."""

    def __init__(self, pipe: Pipeline, what: str, total: int | None, bar: bool,
                 every: float | None = None):  # fmt: skip
        from visvec.cli.progress import Work

        self.pipe = pipe
        self.work = Work(what, total, "frame", bar=bar)
        if every is not None and self.work.bar is None:
            self.work.every = every
            self.work.next = self.work.t0 + every
        self.t0 = time.monotonic()
        self.last: Row | None = None
        self.text_at = 0.0
        self.quiet = False

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        if row.ok:
            self.last = row
        now = time.monotonic()
        text = None
        if now >= self.text_at:  # the text only when it may be shown
            self.text_at = now + TEXT_EVERY_S
            text = self.text()
        self.work.update(1, text)

    def close(self) -> None:
        self.work.close()
        if not self.quiet:
            click.echo(self.line(), err=True)

    def text(self) -> str:
        """The ok share (a bar's text); with the last ok values (a status line's)."""
        n, refused = self.pipe.n_rows, self.pipe.refused
        n_ok = n - sum(refused.values())
        text = f"ok {100.0 * n_ok / max(n, 1):.1f} %"
        if self.last is not None and self.work.bar is None:
            text += "; last " + self._values()
        return text

    def _values(self) -> str:
        return ", ".join(
            f"{name.removesuffix('_deg').removesuffix('_mm').removesuffix('_dps')} {v:+.4f}"
            for name, v in zip(type(self.last).value_columns, self.last.values(), strict=True)
        )

    def line(self, now: float | None = None) -> str:
        """The summary: frames, ok share, rate, the last ok values, the reasons."""
        dt = (time.monotonic() if now is None else now) - self.t0
        n, refused = self.pipe.n_rows, self.pipe.refused
        n_ok = n - sum(refused.values())
        text = (
            f"visvec: {n} frames, {n_ok} ok ({100.0 * n_ok / max(n, 1):.1f} %)"
            f", {n / max(dt, 1e-9):.1f} frames/s"
        )
        if self.last is not None:
            text += f"; last ok (frame {self.last.frame}): {self._values()}"
        if refused:
            top = refused.most_common(PROGRESS_REASONS)
            text += "; not ok: " + ", ".join(f"{reason} {n}" for reason, n in top)
        return text


def _say_errors(frame, row: Row, pipe) -> None:
    """A frame that could not be read, or that the pipeline failed on, said on stderr
    beside its row."""
    if row.status == "read_error":
        click.echo(f"visvec: frame {frame.index}: {frame.error or pipe.check_frame(frame)}",
                   err=True)  # fmt: skip
    if pipe.last_error:
        click.echo(
            f"visvec: frame {frame.index}: internal error, frame refused "
            f"({pipe.last_error}); please report it",
            err=True,
        )


def run_frames(
    rig: Rig,
    frames,
    *,
    out: str | None,
    fmt: str,
    method: str | None,
    overlay: str | None,
    max_frames: int | None,
    keep_rows: bool = False,
    save_frames: str | None = None,
    progress: float | None = None,
    watchers: list[Watcher] | None = None,
    what: str = "batch",
    covariance: bool = False,
    ros_images: bool = False,
) -> list[Row]:
    """Process frames, writing each row as it is made; Ctrl-C ends the loop cleanly.

    Returns the rows only with ``keep_rows`` (a live camera can run for hours: rows are
    not held in memory unless the caller needs them). ``save_frames``: a folder where
    every readable frame is kept losslessly (see :class:`FrameRecorder`). The progress
    (see :class:`Progress`: ``what`` the run is, a bar at a terminal unless the rows go
    to the same terminal, else a status line every ``progress`` seconds, default
    `visvec --status-every`) and a summary line at the end go to stderr.
    ``watchers``: more that see each frame after its row (the live view).
    ``covariance``: each row with its values' 3x3 covariance (Row.cov_columns).
    ``ros_images``: the frames with their detection drawn into the ROS 2 output.
    What the run found out about the rig (the pipeline's notes: a target's height off
    the rig file's, a rolling shutter it does not declare) goes to stderr at the end.
    """
    pipe = make_pipeline(rig, method)
    rows: list[Row] = []
    n = n_ok = 0
    interrupted = False
    seen: list[Watcher] = []
    if overlay:
        seen.append(OverlayWriter(overlay, rig))
    if save_frames:
        seen.insert(0, FrameRecorder(save_frames))
    try:
        total = len(frames)
    except TypeError:
        total = None
    # rows to stdout at a terminal are the progress already: no bar over them
    bar = not (out in (None, "-") and sys.stdout.isatty())
    status = Progress(pipe, what, total, bar, progress)
    seen.append(status)
    seen.extend(watchers or ())
    columns = pipe.row_type.columns + (pipe.row_type.cov_columns() if covariance else ())
    if ros_images and not ros_output(out, fmt):
        raise click.UsageError("--ros-images goes with an --out *.mcap file or --format rosbag2")
    with rows_out(out, fmt, columns, source=str(rig.path or "")) as sink:
        if ros_images:
            seen.insert(0, RosImages(sink, rig))
        try:
            for frame in frames:
                row = pipe.process(frame)
                d = row.as_dict()
                if covariance:
                    d.update(row.cov_dict())
                sink.write(d)
                n += 1
                n_ok += int(row.ok)
                if keep_rows:
                    rows.append(row)
                _say_errors(frame, row, pipe)
                # after the row is out: nothing a watcher does adds to its latency
                for w in seen:
                    w.see(frame, row, pipe)
                if max_frames is not None and n >= max_frames:
                    break
        except KeyboardInterrupt:
            interrupted = True
            click.echo(f"visvec: interrupted after {n} frames; all rows written", err=True)
        except BrokenPipeError:
            status.quiet = True  # the rows' reader went away (`| head`): end quietly
            raise
        finally:
            for w in seen:
                w.close()
    for line in pipe.notes():
        click.echo(line, err=True)
    if n > 0 and n_ok == 0 and not interrupted:
        raise NoOkRows(f"none of the {n} frames gave an ok row (the reasons above)")
    return rows
