"""Row writers. Each row is flushed as soon as it is written, so that a crash or a
Ctrl-C loses nothing already produced."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from typing import IO


class CsvSink:
    """CSV with a header line; empty fields for None."""

    def __init__(self, stream: IO[str], columns: Sequence[str]):
        self.stream = stream
        self.writer = csv.DictWriter(stream, fieldnames=list(columns), lineterminator="\n")
        self.writer.writeheader()
        stream.flush()

    def write(self, row: dict[str, object]) -> None:
        self.writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
        self.stream.flush()


class JsonlSink:
    """One JSON object per line, same keys as the CSV columns; null for empty fields."""

    def __init__(self, stream: IO[str], columns: Sequence[str]):
        self.stream = stream
        self.columns = list(columns)

    def write(self, row: dict[str, object]) -> None:
        self.stream.write(json.dumps({k: row.get(k) for k in self.columns}) + "\n")
        self.stream.flush()


def open_sink(fmt: str, stream: IO[str], columns: Sequence[str]) -> CsvSink | JsonlSink:
    """A sink of format ``"csv"`` or ``"jsonl"`` on an open text stream."""
    if fmt == "csv":
        return CsvSink(stream, columns)
    if fmt == "jsonl":
        return JsonlSink(stream, columns)
    raise ValueError(f"format = {fmt!r}: expected 'csv' or 'jsonl'")
