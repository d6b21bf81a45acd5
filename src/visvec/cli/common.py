"""Options and the frame loop shared by the commands."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import click
import cv2

from visvec.errors import ConfigError
from visvec.output import Row
from visvec.pipeline import METHODS, make_pipeline
from visvec.rig import Rig, load_rig
from visvec.sinks import open_sink


def rig_options(f=None, *, required: bool = True):
    """--rig and --calibration (``@rig_options``, or ``@rig_options(required=False)``
    for a command that can run without a rig)."""
    if f is None:
        return lambda g: rig_options(g, required=required)
    f = click.option(
        "--calibration",
        "calibration",
        type=click.Path(dir_okay=False),
        help="Calibration file (from `visvec calibrate`) overriding the rig.",
    )(f)
    f = click.option(
        "--rig",
        "rig_path",
        required=required,
        type=click.Path(dir_okay=False),
        help="Rig file (TOML), see configs/.",
    )(f)
    return f


def output_options(f):
    """--out, --format, --method, --overlay, --max-frames."""
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
    f = click.option(
        "--method",
        type=click.Choice(METHODS),
        default=None,
        help="Estimator. Triangle: 'full' (default; camera model, lever arm) or 'paper'; "
        "markers: 'full' (default) or a PnP baseline; starfield: 'poisson' (default) or "
        "'crassidis'.",
    )(f)
    f = click.option(
        "--format",
        "fmt",
        type=click.Choice(["csv", "jsonl"]),
        default="csv",
        show_default=True,
        help="Row format.",
    )(f)
    f = click.option(
        "--out",
        type=click.Path(dir_okay=False),
        default=None,
        help="Output file (default: standard output).",
    )(f)
    return f


def load(rig_path: str, calibration: str | None, kind: str | None = None, what: str = "") -> Rig:
    """The rig (with its calibration); refused unless its target is ``kind`` if given."""
    rig = load_rig(rig_path, calibration)
    if kind is not None and rig.kind != kind:
        raise ConfigError(f"{rig_path}: [target] kind = {rig.kind!r}: {what} is for {kind} rigs")
    return rig


@contextlib.contextmanager
def open_out(path: str | None):
    if path is None:
        yield sys.stdout
    else:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", newline="") as fh:
            yield fh


def run_frames(
    rig: Rig,
    frames,
    *,
    out: str | None,
    fmt: str,
    method: str | None,
    overlay: str | None,
    max_frames: int | None,
) -> list[Row]:
    """Process frames, writing each row as it is made; Ctrl-C ends the loop cleanly."""
    pipe = make_pipeline(rig, method)
    rows: list[Row] = []
    ov = Path(overlay) if overlay else None
    if ov is not None:
        ov.mkdir(parents=True, exist_ok=True)
    with open_out(out) as stream:
        sink = open_sink(fmt, stream, pipe.row_type.columns)
        try:
            for frame in frames:
                row = pipe.process(frame)
                sink.write(row.as_dict())
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
                if ov is not None and frame.image is not None:
                    from visvec.overlay import draw_overlay

                    img = draw_overlay(frame.image, pipe.last_detection, row, rig)
                    cv2.imwrite(str(ov / f"overlay_{frame.index:06d}.png"), img)
                if max_frames is not None and len(rows) >= max_frames:
                    break
        except KeyboardInterrupt:
            click.echo(f"visvec: interrupted after {len(rows)} frames; all rows written", err=True)
    return rows
