"""Row writers. Each row is flushed as soon as it is written, so that a crash or a
Ctrl-C loses nothing already produced."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import socket
import stat
from collections.abc import Sequence
from typing import IO
from urllib.parse import urlsplit

from visvec.errors import ConfigError, OutputError


def _json_value(v: object) -> object:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


class _Lines:
    """Writes whole lines: each flushed at once, and on a write error (a full disk) the
    file is cut back to its last whole line and OutputError names it."""

    def __init__(self, stream: IO[str]):
        self.stream = stream
        self.n = 0  # rows written (the header is not one)
        self._fd: int | None | bool = False  # not looked up yet

    def put(self, text: str, row: bool = True) -> None:
        s = self.stream
        if self._fd is False:
            self._fd = _regular_fd(s)
        fd = self._fd
        try:
            if fd is None:
                s.write(text)
                s.flush()
            else:
                # a file: straight to it, so that nothing of a row that failed part-way
                # stays in a buffer to be written again at close
                pos = os.lseek(fd, 0, os.SEEK_END)
                data = text.encode("utf-8")
                try:
                    while data:
                        data = data[os.write(fd, data) :]
                except OSError:
                    os.ftruncate(fd, pos)
                    raise
        except BrokenPipeError:
            raise  # the reader went away (`| head`): the run ends quietly (cli.main)
        except OSError as exc:
            name = getattr(s, "name", "the output")
            raise OutputError(
                f"{name}: cannot write ({exc.strerror or exc}); it holds {self.n} complete "
                "rows and no part of another"
            ) from None
        self.n += int(row)


def _regular_fd(stream) -> int | None:
    """The descriptor of a stream that is a regular file, else None."""
    try:
        fd = stream.fileno()
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        stream.flush()
        return fd
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        return None


class CsvSink:
    """CSV with a header line; empty fields for None."""

    def __init__(self, stream: IO[str], columns: Sequence[str]):
        self.stream = stream
        self.columns = list(columns)
        self.lines = _Lines(stream)
        # one buffer and writer for every line (a row of a 1 kHz IMU costs microseconds)
        self._buf = io.StringIO()
        self._csv = csv.writer(self._buf, lineterminator="\n")
        self._known = frozenset(self.columns)
        self._columns = tuple(self.columns)
        self.lines.put(self._line(dict(zip(self.columns, self.columns, strict=True))), row=False)

    def _line(self, row: dict[str, object]) -> str:
        if len(row) == len(self.columns) and list(row) == self.columns:
            # a row's own columns in their order (every output row): its values as they are
            fields = ["" if v is None else v for v in row.values()]
        else:
            extra = row.keys() - self._known
            if extra:
                raise ValueError(f"fields not in the columns: {sorted(extra)}")
            fields = ["" if (v := row.get(k)) is None else v for k in self.columns]
        return self._format(fields)

    def _format(self, fields: list) -> str:
        buf = self._buf
        buf.seek(0)
        buf.truncate()
        self._csv.writerow(fields)
        return buf.getvalue()

    def write(self, row: dict[str, object]) -> None:
        self.lines.put(self._line(row))

    def write_row(self, row) -> None:
        """A `visvec.output.Row` of these columns, written from its `fields` (no dict
        made: a fused row of a 1 kHz IMU costs microseconds)."""
        if row.columns != self._columns:
            self.write(row.as_dict())
            return
        self.lines.put(self._format(["" if v is None else v for v in row.fields()]))


def row_writer(sink):
    """The function that writes a `visvec.output.Row` to ``sink``: its own row writer
    where it has one (CSV: no dict made), else its dict."""
    own = getattr(sink, "write_row", None)
    return own if own is not None else (lambda row: sink.write(row.as_dict()))


class Tee:
    """Rows to several sinks in turn (a run's output and its recording's copy)."""

    def __init__(self, *sinks):
        self.sinks = sinks
        self._rows = [row_writer(k) for k in sinks]

    def write(self, row: dict) -> None:
        for k in self.sinks:
            k.write(row)

    def write_row(self, row) -> None:
        for w in self._rows:
            w(row)


class JsonlSink:
    """One JSON object per line, same keys as the CSV columns; null for empty fields."""

    def __init__(self, stream: IO[str], columns: Sequence[str]):
        self.stream = stream
        self.columns = list(columns)
        self.lines = _Lines(stream)

    def write(self, row: dict[str, object]) -> None:
        # NaN and infinity are not JSON: such a value is written as null
        obj = {k: _json_value(row.get(k)) for k in self.columns}
        self.lines.put(json.dumps(obj, allow_nan=False) + "\n")


class UdpStream:
    """A text stream whose every flush is one UDP datagram to ``url`` =
    ``udp://HOST:PORT``: with a sink, one datagram per row (and the CSV header first).

    Rows are fire-and-forget, as UDP is: a receiver that is not there, or a full
    network buffer, never stops the sensor; ``dropped`` counts the datagrams the system
    refused to send.

    Raises
    ------
    ConfigError
        If ``url`` is not udp://HOST:PORT or HOST does not resolve.
    """

    def __init__(self, url: str):
        parts = urlsplit(url)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme != "udp" or not parts.hostname or port is None or parts.path:
            raise ConfigError(f"{url}: expected udp://HOST:PORT (for example udp://127.0.0.1:5005)")
        try:
            info = socket.getaddrinfo(parts.hostname, port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise ConfigError(f"{url}: cannot resolve {parts.hostname!r} ({exc.strerror})") from exc
        family, _, _, _, self.address = info[0]
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.url = url
        self.dropped = 0
        self._buf: list[str] = []

    def write(self, text: str) -> int:
        self._buf.append(text)
        return len(text)

    def flush(self) -> None:
        if not self._buf:
            return
        data = "".join(self._buf).encode()
        self._buf = []
        try:
            self.sock.sendto(data, self.address)
        except OSError:
            self.dropped += 1

    def close(self) -> None:
        self.flush()
        self.sock.close()


def open_sink(fmt: str, stream: IO[str], columns: Sequence[str]) -> CsvSink | JsonlSink:
    """A sink of format ``"csv"`` or ``"jsonl"`` on an open text stream."""
    if fmt == "csv":
        return CsvSink(stream, columns)
    if fmt == "jsonl":
        return JsonlSink(stream, columns)
    raise ValueError(f"format = {fmt!r}: expected 'csv' or 'jsonl'")
