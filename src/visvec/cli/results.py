"""--errors and --summary: a run's results against its truth, for plotting and scripts
(batch, rate, fuse)."""

from __future__ import annotations

import csv
import io
import json

import click

from visvec.cli.common import check_output, write_whole
from visvec.evaluate import frame_errors, summary_dict


def check_results(truth, errors, summary, imu=None) -> None:
    """--errors and --summary: refused before any work when unwritable or meaningless."""
    check_output(errors, "--errors")
    check_output(summary, "--summary")
    if errors and not truth:
        raise click.UsageError("--errors needs --truth (errors against what?)")
    if imu and (errors or summary):
        raise click.UsageError("--errors and --summary are for frames' rows; with --imu, "
                               "`visvec fuse --truth` compares the fused rows")  # fmt: skip


def write_results(errors, summary, rows, truth_rows, stats, names) -> None:
    """--errors (each row's errors against the truth, CSV) and --summary (the run's
    figures, JSON), where asked for."""
    if errors and truth_rows is not None:
        write_whole(errors, _csv(frame_errors(rows, truth_rows, names), names))
    if summary:
        write_whole(summary, json.dumps(summary_dict(rows, stats, names), indent=2) + "\n")


def _csv(records: list[dict], names) -> str:
    cols = ["frame", "time_s", "status", *(f"err_{k}" for k in names),
            *(f"z_{k}" for k in names)]  # fmt: skip
    buf = io.StringIO()
    w = csv.DictWriter(buf, cols, lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow({k: ("" if v is None else (f"{v:.9g}" if isinstance(v, float) else v))
                    for k, v in r.items()})  # fmt: skip
    return buf.getvalue()
