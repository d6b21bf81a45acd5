"""The frame loop of `batch`, `rate` and `track`: each frame's row is written (and
flushed) first; then the run's watchers see the frame, its row and its detection (the
frames kept, the overlays drawn, the status line, the live view), so none of them adds
to a row's latency."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Protocol

import click

from visvec.cli.common import check_new_recording, make_folder, open_out
from visvec.data import Frame
from visvec.errors import NoOkRows
from visvec.imageio import write_image
from visvec.output import Row
from visvec.pipeline import Pipeline, make_pipeline
from visvec.rig import Rig
from visvec.sinks import open_sink


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
        self._times.write("file,time_s\n")

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        if frame.image is None:
            return
        name = f"frame_{frame.index:06d}.png"
        if not write_image(self.dir / name, frame.image):
            raise click.ClickException(f"{self.dir / name}: cannot write the frame")
        self._times.write(f"{name},{frame.time_s:.6f}\n")
        self._times.flush()

    def close(self) -> None:
        self._times.close()


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


class Progress:
    """A status line on stderr every ``interval`` seconds, for an operator watching a run
    whose rows go to a file: frames, the ok share, the frame rate, the last ok values,
    and why the others were not ok (the counts the pipeline ``pipe`` keeps of its rows);
    and one at the end."""

    def __init__(self, interval: float, pipe: Pipeline):
        self.interval = interval
        self.pipe = pipe
        self.t0 = time.monotonic()
        self.next = self.t0 + interval
        self.last: Row | None = None

    def see(self, frame: Frame, row: Row, pipe: Pipeline) -> None:
        self.update(row)

    def update(self, row: Row) -> None:
        if row.ok:
            self.last = row
        now = time.monotonic()
        if now >= self.next:
            self.next = now + self.interval
            click.echo(self.line(now), err=True)

    def close(self) -> None:
        click.echo(self.line(), err=True)

    def line(self, now: float | None = None) -> str:
        dt = (time.monotonic() if now is None else now) - self.t0
        n, refused = self.pipe.n_rows, self.pipe.refused
        n_ok = n - sum(refused.values())
        text = (
            f"visvec: {n} frames, {n_ok} ok ({100.0 * n_ok / max(n, 1):.1f} %)"
            f", {n / max(dt, 1e-9):.1f} frames/s"
        )
        if self.last is not None:
            vals = ", ".join(
                f"{name.removesuffix('_deg').removesuffix('_mm').removesuffix('_dps')} {v:+.4f}"
                for name, v in zip(type(self.last).value_columns, self.last.values(), strict=True)
            )
            text += f"; last ok (frame {self.last.frame}): {vals}"
        if refused:
            top = refused.most_common(PROGRESS_REASONS)
            text += "; not ok: " + ", ".join(f"{reason} {n}" for reason, n in top)
        return text


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
) -> list[Row]:
    """Process frames, writing each row as it is made; Ctrl-C ends the loop cleanly.

    Returns the rows only with ``keep_rows`` (a live camera can run for hours: rows are
    not held in memory unless the caller needs them). ``save_frames``: a folder where
    every readable frame is kept losslessly (see :class:`FrameRecorder`). ``progress``:
    seconds between status lines on stderr (see :class:`Progress`), and one at the end.
    ``watchers``: more that see each frame after its row (the live view).
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
    if progress is not None:
        seen.append(Progress(progress, pipe))
    seen.extend(watchers or ())
    with open_out(out) as stream:
        sink = open_sink(fmt, stream, pipe.row_type.columns)
        try:
            for frame in frames:
                row = pipe.process(frame)
                sink.write(row.as_dict())
                n += 1
                n_ok += int(row.ok)
                if keep_rows:
                    rows.append(row)
                if row.status == "read_error":
                    click.echo(
                        f"visvec: frame {frame.index}: {frame.error or pipe.check_frame(frame)}",
                        err=True,
                    )
                if pipe.last_error:
                    click.echo(
                        f"visvec: frame {frame.index}: internal error, frame refused "
                        f"({pipe.last_error}); please report it",
                        err=True,
                    )
                # after the row is out: nothing a watcher does adds to its latency
                for w in seen:
                    w.see(frame, row, pipe)
                if max_frames is not None and n >= max_frames:
                    break
        except KeyboardInterrupt:
            interrupted = True
            click.echo(f"visvec: interrupted after {n} frames; all rows written", err=True)
        finally:
            for w in seen:
                w.close()
    for line in pipe.notes():
        click.echo(line, err=True)
    if n > 0 and n_ok == 0 and not interrupted:
        raise NoOkRows(f"none of the {n} frames gave an ok row (the reasons above)")
    return rows
