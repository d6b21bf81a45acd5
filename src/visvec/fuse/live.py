"""Live inputs of `visvec fuse`: rows from a file (followed as it grows), standard
input, UDP datagrams or a serial device, fused as they arrive.

A SOURCE is a path, ``-`` (standard input), ``udp://HOST:PORT`` (one row per datagram,
or several lines in one) or ``serial:///dev/ttyUSB0?baud=115200`` (line-delimited, with
the optional extra ``pyserial``). Rows are the CSV rows visvec reads from files (the
header first, as the first line or datagram) or JSON lines (an object per line, keyed
by the same columns). Each source is read by its own thread into one queue, so that a
slow or silent input never holds up the other; the fusion thread takes the events in
arrival order: an inertial sample is fused and its row written at once, a fix is handed
to the engine when it arrives (its ``time_s`` on the inertial samples' clock).

A malformed line or datagram is counted and skipped; an inertial clock that steps back
is refused per sample (``imu_time_back``).
"""

from __future__ import annotations

import csv
import heapq
import io
import json
import math
import os
import queue
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from urllib.parse import parse_qs, urlsplit

import numpy as np

from visvec.clocks import ClockTie
from visvec.errors import ConfigError, InputFileError
from visvec.fuse.gate import warm_up
from visvec.fuse.inputs import (
    ATTITUDE_FIX,
    ATTITUDE_IMU,
    PLANAR_FIX,
    PLANAR_IMU,
    STATUSES,
    Fix,
    fix_cov,
    fix_from_row,
    row_cov,
    untimed,
)
from visvec.fuse.inputs import _fix_cov as sigma_cov
from visvec.fuse.run import fused_rows
from visvec.rotations import quat_to_matrix
from visvec.sinks import row_writer

SERIAL_RETRY_S = 1.0
QUIET_END_S = 0.5  # the camera has ended and the IMU said nothing for this long: stop


def is_live(source: str, follow: bool) -> bool:
    return follow or source == "-" or source.startswith(("udp://", "serial://"))


@dataclass
class Event:
    kind: str  # "imu" | "fix" | "end" | "bad" | "note"
    source: str
    arrival: float  # time.monotonic() when it arrived
    row: dict | None = None
    text: str = ""


@dataclass
class LineParser:
    """Rows from lines: JSON objects, or CSV after its header line."""

    header: list[str] | None = None
    columns: tuple[str, ...] | None = None  # given by option: no header expected

    def __post_init__(self):
        if self.columns:
            self.header = list(self.columns)

    def feed(self, line: str) -> dict | None:
        line = line.strip()
        if not line:
            return None
        if line.startswith("{"):
            obj = json.loads(line)  # ValueError: malformed
            if not isinstance(obj, dict):
                raise ValueError("not a JSON object")
            return {str(k): ("" if v is None else str(v)) for k, v in obj.items()}
        fields = next(csv.reader(io.StringIO(line)))
        if self.header is None:
            self.header = [f.strip() for f in fields]
            return None
        if len(fields) != len(self.header):
            raise ValueError(f"{len(fields)} fields, the header has {len(self.header)}")
        return dict(zip(self.header, fields, strict=True))


def _lines_file(path: str, follow: bool, stop: threading.Event, notes) -> Iterator[str]:
    try:
        fh = open(path, newline="")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc.strerror})") from None
    with fh:
        buf, n, told = "", 0, not follow
        while not stop.is_set():
            chunk = fh.readline()
            if chunk:
                buf += chunk
                if buf.endswith("\n"):
                    n += 1
                    yield buf
                    buf = ""
                continue
            if not follow:
                if buf:
                    yield buf
                return
            if not told:  # said once what was there, after its rows: now it is followed
                notes.put(f"{path}: {n} lines read, following")
                told = True
            time.sleep(0.005)


def _lines_stdin(stop: threading.Event) -> Iterator[str]:
    for line in sys.stdin:
        if stop.is_set():
            return
        yield line


def _lines_udp(url: str, stop: threading.Event, notes) -> Iterator[str]:
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None:
        raise ConfigError(f"{url}: expected udp://HOST:PORT")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((parts.hostname, port))
    except OSError as exc:
        sock.close()
        raise ConfigError(f"{url}: cannot listen there ({exc.strerror})") from None
    sock.settimeout(0.1)
    notes.put(f"{url}: listening")
    with sock:
        while not stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            text = data.decode("utf-8", errors="replace")
            yield from text.splitlines()


def serial_settings(url: str) -> tuple[str, int]:
    parts = urlsplit(url)
    q = parse_qs(parts.query)
    try:
        baud = int(q.get("baud", ["115200"])[0])
    except ValueError:
        raise ConfigError(f"{url}: baud must be a whole number") from None
    if not parts.path:
        raise ConfigError(f"{url}: expected serial:///dev/DEVICE?baud=N")
    return parts.path, baud


def _lines_serial(url: str, stop: threading.Event, notes: queue.Queue) -> Iterator[str]:
    try:
        import serial  # pyserial, the optional extra visvec[serial]
    except ImportError:
        raise ConfigError(
            f"{url}: serial devices need pyserial: pip install 'visvec[serial]'"
        ) from None
    device, baud = serial_settings(url)
    while not stop.is_set():
        try:
            port = serial.Serial(device, baud, timeout=0.1)
        except (serial.SerialException, OSError) as exc:
            notes.put(f"{device}: cannot open ({exc}); retrying every {SERIAL_RETRY_S:g} s")
            stop.wait(SERIAL_RETRY_S)
            continue
        notes.put(f"{device}: open at {baud} baud")
        with port:
            buf = b""
            try:
                while not stop.is_set():
                    buf += port.read(4096)
                    *lines, buf = buf.split(b"\n")
                    for raw in lines:
                        yield raw.decode("utf-8", errors="replace")
            except (serial.SerialException, OSError) as exc:
                notes.put(f"{device}: lost ({exc}); retrying every {SERIAL_RETRY_S:g} s")
        stop.wait(SERIAL_RETRY_S)


@dataclass
class Reader:
    """One source read by a thread into ``events``."""

    name: str  # "imu" or "fix"
    source: str
    events: queue.Queue
    follow: bool = False
    columns: tuple[str, ...] | None = None
    stop: threading.Event = field(default_factory=threading.Event)
    n_bad: int = 0

    def lines(self) -> Iterator[str]:
        if self.source == "-":
            return _lines_stdin(self.stop)
        if self.source.startswith("udp://"):
            return _lines_udp(self.source, self.stop, _NoteQueue(self))
        if self.source.startswith("serial://"):
            return _lines_serial(self.source, self.stop, _NoteQueue(self))
        return _lines_file(self.source, self.follow, self.stop, _NoteQueue(self))

    def check(self) -> None:
        """Refuse a source that cannot work before anything starts."""
        if self.source.startswith("serial://"):
            serial_settings(self.source)
        elif self.source != "-" and not self.source.startswith("udp://"):
            if not os.path.isfile(self.source) and not self.follow:
                raise InputFileError(f"{self.source}: no such file")

    def run(self) -> None:
        parser = LineParser(columns=self.columns)
        try:
            for line in self.lines():
                try:
                    row = parser.feed(line)
                except (ValueError, csv.Error) as exc:
                    self.n_bad += 1
                    self.events.put(Event("bad", self.name, time.monotonic(), text=str(exc)))
                    continue
                if row is not None:
                    self.events.put(Event(self.name, self.name, time.monotonic(), row))
        except (InputFileError, ConfigError) as exc:
            self.events.put(Event("note", self.name, time.monotonic(), text=str(exc)))
        self.events.put(Event("end", self.name, time.monotonic()))

    def start(self) -> threading.Thread:
        th = threading.Thread(target=self.run, name=f"visvec-{self.name}", daemon=True)
        th.start()
        return th


class _NoteQueue:
    def __init__(self, reader: Reader):
        self.reader = reader

    def put(self, text: str) -> None:
        self.reader.events.put(Event("note", self.reader.name, time.monotonic(), text=text))


def _num(row: dict, key: str) -> float:
    x = float((row.get(key) or "").strip())  # ValueError: malformed
    if not math.isfinite(x):
        raise ValueError(f"{key} is not finite")
    return x


def imu_kind(row: dict) -> bool | None:
    """planar (True), 3-D (False), or None when the row has neither set of columns."""
    if all(k in row for k in ATTITUDE_IMU):
        return False
    if all(k in row for k in PLANAR_IMU):
        return True
    return None


def parse_imu(row: dict, planar: bool) -> tuple[float, np.ndarray, np.ndarray | None]:
    """(time_s, gyro rad/s (3,), accel m/s^2 (2,) or None); ValueError if malformed."""
    t = _num(row, "time_s")
    if planar:
        g = np.array([0.0, 0.0, math.radians(_num(row, "gz_dps"))])
        return t, g, np.array([_num(row, "ax_mps2"), _num(row, "ay_mps2")])
    return t, np.radians([_num(row, k) for k in ATTITUDE_IMU]), None


def parse_fix(row: dict, planar: bool) -> Fix | None:
    """An ok row as a fix (available at its exposure plus ``latency_ms``, or when it
    arrives if that is later), None for another status or an untimed row (its time is
    not its exposure's: visvec.fuse.inputs.UNTIMED); ValueError if malformed."""
    status = (row.get("status") or "").strip()
    if status not in STATUSES:
        raise ValueError(f"status {status!r}")
    if status != "ok" or untimed(row):
        return None
    t = _num(row, "time_s")
    lat = _num(row, "latency_ms") if (row.get("latency_ms") or "").strip() else 0.0
    if lat < 0:
        raise ValueError(f"latency_ms = {lat}: must be >= 0")
    if planar:
        x, y, h = (_num(row, k) for k in PLANAR_FIX)
        value = np.array([x, y, math.radians(h)])
        sig_cols = ("sigma_x_mm", "sigma_y_mm", "sigma_heading_deg")
    else:
        q = np.array([_num(row, k) for k in ATTITUDE_FIX])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"quaternion norm {norm:.6f}")
        value = quat_to_matrix(q / norm)
        sig_cols = ("sigma_yaw_deg", "sigma_pitch_deg", "sigma_roll_deg")
    cov = None
    full = row_cov(lambda k: _num(row, k) if (row.get(k) or "").strip() else None, planar)
    if full is not None:
        cov = fix_cov(full, value, planar)
    elif all((row.get(k) or "").strip() for k in sig_cols):
        s = np.array([_num(row, k) for k in sig_cols])
        if np.any(s <= 0):
            raise ValueError("sigma columns must be positive")
        cov = sigma_cov(s, value, planar)
    return Fix(t, t + lat / 1000.0, value, cov, 0)


class LatencyTally:
    """The rows' latencies (ms) as a histogram of LATENCY_BINS_PER_DECADE log-spaced bins
    a decade from LATENCY_LO_MS to LATENCY_HI_MS: a run of hours keeps a few kB, not
    every row's number (a list of them grew by 11 MB an hour at 100 Hz, 115 MB at 1
    kHz), and the median is read to 0.3 % (half a bin)."""

    def __init__(self):
        n = int(round(math.log10(LATENCY_HI_MS / LATENCY_LO_MS) * LATENCY_BINS_PER_DECADE))
        self.counts = np.zeros(n + 2, np.int64)  # with one bin below and one above
        self.n = 0

    def add(self, ms: float) -> None:
        if ms > LATENCY_LO_MS:
            k = int(math.log10(ms / LATENCY_LO_MS) * LATENCY_BINS_PER_DECADE) + 1
            k = min(k, len(self.counts) - 1)
        else:
            k = 0
        self.counts[k] += 1
        self.n += 1

    def __len__(self) -> int:
        return self.n

    def median(self) -> float:
        """The median's bin, at its geometric centre (the edge bins: their bound)."""
        if not self.n:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self.counts), self.n // 2 + 1))
        if k == 0:
            return LATENCY_LO_MS
        if k == len(self.counts) - 1:
            return LATENCY_HI_MS
        return LATENCY_LO_MS * 10.0 ** ((k - 0.5) / LATENCY_BINS_PER_DECADE)


# the latency tally's range (ms) and resolution
LATENCY_LO_MS, LATENCY_HI_MS = 1e-3, 1e5
LATENCY_BINS_PER_DECADE = 400


@dataclass
class LiveSummary:
    samples: int = 0
    ok: int = 0
    fixes: int = 0
    bad: dict = field(default_factory=dict)  # source -> malformed lines skipped
    latencies_ms: LatencyTally = field(default_factory=LatencyTally)
    interrupted: bool = False
    refused: bool = False
    engine: object = None  # the fusion engine, once the first inertial row made it


class EventLog:
    """What a live fusion took, in order, as JSON lines (``events.jsonl`` of `track
    --record`): each event with the moment it was taken (``n``, time.monotonic()): an
    inertial row as it came, a fix of this process's camera by its frame number and
    exposure (its row is the replayed frame's), a stream's fix as it came, the notes,
    malformed rows and ends, and every idle tenth of a second (``tick``). `replay_live`
    gives the run's rows again from it."""

    FLUSH_EVERY = 200  # events (and at every tick): a crash loses at most these

    def __init__(self, path):
        import json

        self._dumps = json.dumps
        self.fh = open(path, "w", encoding="utf-8")  # noqa: SIM115 - closed by close()
        self._n = 0

    def start(self, now: float) -> None:
        self._put({"k": "start", "n": now})

    def event(self, ev: Event | None, now: float) -> None:
        if ev is None:
            self._put({"k": "tick", "n": now})
            self.fh.flush()
            return
        d = {"k": ev.kind, "n": now, "s": ev.source, "a": ev.arrival}
        if ev.row is not None and "_row" in ev.row:
            d["frame"] = ev.row["_row"].frame
            d["x"] = ev.row["_host_exposure"]
        elif ev.row is not None:
            d["row"] = ev.row
        if ev.text:
            d["text"] = ev.text
        self._put(d)

    def _put(self, d: dict) -> None:
        self.fh.write(self._dumps(d) + "\n")
        self._n += 1
        if self._n % self.FLUSH_EVERY == 0:
            self.fh.flush()

    def close(self) -> None:
        self.fh.close()


def read_event_log(path) -> list[dict]:
    """The events of an EventLog, in order.

    Raises
    ------
    InputFileError
        A line that is not a JSON object with ``k`` and ``n``, naming it.
    """
    import json

    out = []
    with open(path, encoding="utf-8") as fh:
        for line_no, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                d = json.loads(line)
                float(d["n"]), str(d["k"])
            except (ValueError, KeyError, TypeError):
                raise InputFileError(f"{path}: line {line_no}: not an event of a recording "
                                     "(a JSON object with k and n)") from None  # fmt: skip
            out.append(d)
    return out


def replay_live(events: list[dict], frame_rows: dict, setup, open_rows, *, silent_s: float = 2.0,
                echo=print, kind: bool | None = None, end_with_fixes: bool = False,
                sources: tuple[str, str] = ("imu", "camera")) -> LiveSummary:  # fmt: skip
    """A live fusion again from its EventLog: every event given to the same loop at the
    moment it was taken, the camera's fixes the rows ``frame_rows`` (frame number ->
    Row) of its frames processed again; the fused rows are the run's (but latency_ms,
    the time this replay spent on them)."""

    class _Source:
        def __init__(self, source):
            self.source = source

    start = next((e["n"] for e in events if e["k"] == "start"), events[0]["n"] if events else 0.0)
    run = _LiveRun(_Source(sources[0]), _Source(sources[1]), setup, open_rows, silent_s, echo,
                   kind, end_with_fixes, now=start)  # fmt: skip
    warm_up()
    for e in events:
        k = e["k"]
        if k == "start":
            continue
        if k == "tick":
            ev = None
        elif k == "fix" and "frame" in e:
            row = frame_rows.get(int(e["frame"]))
            if row is None:
                raise InputFileError(f"frame {e['frame']}: a fix of the recording whose frame "
                                     "is not in it")  # fmt: skip
            ev = Event("fix", e["s"], e["a"], {"_row": row, "_host_exposure": e["x"]})
        else:
            ev = Event(k, e.get("s", ""), e.get("a", e["n"]), e.get("row"), e.get("text", ""))
        if not run.take(ev, now=e["n"]):
            break
    return run.summary


def run_live(imu: Reader, fixes, setup, open_rows, *, max_samples: int | None = None,
             silent_s: float = 2.0, echo=print, kind: bool | None = None,
             end_with_fixes: bool = False,
             record: EventLog | None = None) -> LiveSummary:  # fmt: skip
    """Fuse two live sources until the inertial source ends, ``max_samples`` rows, or
    Ctrl-C. ``setup(planar)`` gives (engine, model) once the first inertial row tells
    the kind; ``open_rows(planar)`` a sink with ``write(row)``; every row is written
    (and flushed by the sink) as soon as its sample is fused. A source silent for
    ``silent_s`` is said once on stderr (and, for the fixes, on every row:
    ``fixes_silent``), and again when it is back. ``end_with_fixes`` (a camera in this
    process): the run also ends once the fixes' source has ended and the IMU has
    been quiet for QUIET_END_S. ``record``: every event taken, and when, to an
    EventLog (`replay_live` gives the rows again)."""
    run = _LiveRun(imu, fixes, setup, open_rows, silent_s, echo, kind, end_with_fixes)
    if record is not None:
        record.start(run.started)
    # what the filters import on their first fix (scipy.special, half a second), here,
    # before any row waits on it
    warm_up()
    for r in (imu, fixes):
        r.start()
    try:
        while True:
            try:
                ev = imu.events.get(timeout=0.1)
            except queue.Empty:
                ev = None
            now = time.monotonic()
            go = run.take(ev, now)
            if record is not None:
                record.event(ev, now)  # after the event's row is out: it waits for no log
            if not go:
                break
            if max_samples is not None and run.summary.samples >= max_samples:
                break
    except KeyboardInterrupt:
        run.summary.interrupted = True
    finally:
        imu.stop.set()
        fixes.stop.set()
    return run.summary


class _LiveRun:
    """The state of a live fusion and what each event does to it (run_live)."""

    def __init__(self, imu, fixes, setup, open_rows, silent_s, echo, kind, end_with_fixes,
                 now: float | None = None):  # fmt: skip
        self.imu, self.setup, self.open_rows = imu, setup, open_rows
        self.silent_s, self.echo, self.kind = silent_s, echo, kind
        self.end_with_fixes = end_with_fixes
        self.summary = LiveSummary()
        self.engine = self.model = self.sink = self.planar = None
        self.waiting: list = []  # fixes that came before the first inertial row
        self.held: list = []  # fixes that arrived before the IMU's clock reached their latency
        self.tie = ClockTie()  # host time (time.monotonic) minus IMU time
        self.fixes_ended = False
        now = time.monotonic() if now is None else now
        self.started = now
        self.last = {"imu": now, "fix": now}
        self.silent = {"imu": False, "fix": False}
        self.source_of = {"imu": imu.source, "fix": getattr(fixes, "source", "camera")}

    def take(self, ev: Event | None, now: float | None = None) -> bool:
        """Handle one event (None: nothing came for 0.1 s) at ``now`` (time.monotonic()
        unless a replay gives the moment it was taken); False ends the run."""
        now = time.monotonic() if now is None else now
        for src in ("imu", "fix"):
            if not self.silent[src] and now - self.last[src] > self.silent_s:
                self.silent[src] = True
                self.echo(f"visvec: {self.source_of[src]}: nothing for {self.silent_s:g} s")
        if ev is None:
            return not (self.fixes_ended and now - self.last["imu"] > QUIET_END_S)
        if ev.kind == "end":
            if ev.source == "imu":
                return False
            self.fixes_ended = self.end_with_fixes
        elif ev.kind == "note":
            self.echo(f"visvec: {ev.text}")
        elif ev.kind == "bad":
            self.bad(ev.source, ev.text)
        else:
            self.last[ev.kind] = ev.arrival
            if self.silent[ev.kind]:
                self.silent[ev.kind] = False
                self.echo(f"visvec: {self.source_of[ev.kind]}: back")
            if ev.kind == "fix":
                if self.engine is None:
                    self.waiting.append((ev.row, ev.arrival))
                else:
                    self.add_fix(ev.row, ev.arrival)
                return True
            return self.sample(ev)
        return True

    def bad(self, source: str, text: str) -> None:
        """A malformed row: counted, and said for the first three of each source."""
        self.summary.bad[source] = self.summary.bad.get(source, 0) + 1
        if self.summary.bad[source] <= 3:
            self.echo(f"visvec: {self.source_of[source]}: malformed row skipped ({text})")

    def add_fix(self, row: dict, arrival: float) -> None:
        """A fix held until the IMU's clock reaches the time it became available."""
        try:
            # this process's camera hands its row itself (fix_from_row: its full
            # covariance kept); a stream's rows are text
            f = fix_from_row(row["_row"], self.planar) if "_row" in row else \
                parse_fix(row, self.planar)  # fmt: skip
        except ValueError as exc:
            self.bad("fix", str(exc))
            return
        if f is not None and "_host_exposure" in row:
            # a fix of this process's camera: its exposure and arrival, on the host's
            # clock, taken onto the IMU's by the learned offset
            clock = self.tie.offset
            f = replace(f, time_s=float(row["_host_exposure"]) - clock,
                        available_s=arrival - clock)  # fmt: skip
        if f is not None:
            self.summary.fixes += 1
            heapq.heappush(self.held, (f.available_s, id(f), f))

    def _start(self, row: dict) -> bool:
        """The first inertial row tells the kind: the engine and the sink are made;
        False when the rig's fixes need the other kind."""
        planar = imu_kind(row)
        if planar is None:
            self.bad("imu", "no gyro columns")
            return True
        if self.kind is not None and planar != self.kind:
            self.echo(f"visvec: {self.imu.source}: a {'planar' if planar else '3-D'} IMU's "
                      f"rows; this rig's fixes need a {'planar' if self.kind else '3-D'} IMU "
                      f"({','.join(PLANAR_IMU if self.kind else ATTITUDE_IMU)})")  # fmt: skip
            self.summary.refused = True
            return False
        self.planar = planar
        self.engine, self.model = self.setup(planar)
        self.summary.engine = self.engine
        self.sink = self.open_rows(planar)
        self.write = row_writer(self.sink)
        return True

    def sample(self, ev: Event) -> bool:
        """An inertial sample: fused with the fixes available by its time, its row
        written at once."""
        if self.planar is None:
            if not self._start(ev.row):
                return False
            if self.planar is None:
                return True
        try:
            t, g, a = parse_imu(ev.row, self.planar)
        except ValueError as exc:
            self.bad("imu", str(exc))
            return True
        # the IMU's clock against the host's: the lower envelope of arrival - time over
        # the last CLOCK_WINDOW_S (the sample that took the least time to arrive sets it)
        self.tie.add(ev.arrival, t)
        if self.waiting:  # fixes that came before the IMU's first sample: its clock is known
            for row, arrival in self.waiting:
                self.add_fix(row, arrival)
            self.waiting.clear()
        while self.held and self.held[0][0] <= t:
            self.engine.add_fix(heapq.heappop(self.held)[2])
        fs = self.engine.step(t, g, a)
        if self.silent["fix"]:
            fs = replace(fs, warnings=(*fs.warnings, "fixes_silent"))
        row = next(fused_rows(iter([fs]), self.model))
        latency = (time.monotonic() - ev.arrival) * 1000.0
        row = replace(row, latency_ms=latency)
        self.write(row)
        self.summary.samples += 1
        self.summary.ok += int(row.ok)
        self.summary.latencies_ms.add(latency)
        return True
