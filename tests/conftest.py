"""Shared fixtures: rigs, shared data location, helpers."""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SHARED_DATA = ROOT.parent / "shared" / "data"
TEST_DATA = ROOT / "tests" / "data"  # small files the tests own
SAMPLES = ROOT / "data" / "sample_frames"  # the shipped recording


@pytest.fixture(scope="session")
def rig640():
    return load_rig(CONFIGS / "triangle.toml")


@pytest.fixture(scope="session")
def rig320():
    return load_rig(CONFIGS / "triangle-320.toml")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def shared(*parts: str) -> Path:
    """Path in ../shared/data; the test is skipped when it is not there."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


def rig_variant(rig_path: Path, key: str, old: str, new: str, out: Path) -> Path:
    """A copy of the rig file ``rig_path`` at ``out`` whose one line ``key = old`` (a
    comment may follow) says ``key = new``: a lab whose rig file is wrong in one value."""
    lines = Path(rig_path).read_text().splitlines(keepends=True)
    hits = [i for i, line in enumerate(lines) if line.split("#")[0].split() == [key, "=", old]]
    assert len(hits) == 1, f"{rig_path}: no single line {key} = {old}"
    lines[hits[0]] = lines[hits[0]].replace(f"{key} = {old}", f"{key} = {new}", 1)
    out.write_text("".join(lines))
    return out


def attitudes(n: int, seed: int, tilt_deg: float = 5.0) -> list[np.ndarray]:
    """n attitudes R_NB: yaw uniform over the circle, pitch and roll uniform within
    +-``tilt_deg``."""
    r = np.random.default_rng(seed)
    return [
        euler_to_matrix(r.uniform(-np.pi, np.pi), *np.radians(r.uniform(-tilt_deg, tilt_deg, 2)))
        for _ in range(n)
    ]


# the command line, run as a user would


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def rows_of(text):
    return list(csv.DictReader(io.StringIO(text)))


def assert_within_3_sigma(rows, truth):
    """Every row's yaw, pitch and roll within 3 of its sigma of the truth file's."""
    for x, t in zip(rows, truth, strict=True):
        for k in ("yaw", "pitch", "roll"):
            err = (float(x[f"{k}_deg"]) - float(t[f"{k}_deg"]) + 180.0) % 360.0 - 180.0
            assert abs(err) < 3.0 * float(x[f"sigma_{k}_deg"]), (x["frame"], k)


def besides_the_zero_tilt_note(stderr: str) -> str:
    """stderr without the note a run on an uncalibrated triangle rig starts with, and
    without the summary line every run of frames ends with (checked there: it says
    every frame was ok)."""
    note = "visvec: note: no zero-tilt calibration given"
    lines = [x for x in stderr.splitlines(keepends=True) if not x.startswith(note)]
    summary = re.compile(r"visvec: (\d+) frames, (\d+) ok \(")
    kept = []
    for x in lines:
        m = summary.match(x)
        if m:
            assert m.group(1) == m.group(2), x  # a summary of a run with refusals
            continue
        kept.append(x)
    return "".join(kept)


def wait_until(condition, what: str, timeout: float = 30.0, poll_s: float = 0.02) -> None:
    """Wait for ``condition()`` to hold, failing with ``what`` after ``timeout`` s: a
    test waits for the event it needs, not a guessed time."""
    import time

    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout:g} s")
        time.sleep(poll_s)


def data_rows(path: Path) -> int:
    """Complete data rows in a CSV file being written (0 before it exists)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return 0
    return max(0, text.count("\n") - 1)


class Stderr:
    """A child process's stderr read line by line in a thread, so that a test can wait
    for a message (the device opened, a file read to its end) and read all of it at
    the end."""

    def __init__(self, proc):
        import threading

        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._read, args=(proc.stderr,), daemon=True)
        self._thread.start()

    def _read(self, fh) -> None:
        for line in fh:
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def count(self, text: str) -> int:
        with self._cond:
            return sum(text in line for line in self.lines)

    def wait_for(self, text: str, times: int = 1, timeout: float = 30.0) -> None:
        with self._cond:
            self._cond.wait_for(
                lambda: sum(text in x for x in self.lines) >= times or self._closed, timeout
            )
        if self.count(text) < times:
            raise AssertionError(f"{text!r} not said {times}x on stderr:\n{self.text}")

    @property
    def text(self) -> str:
        with self._cond:
            return "".join(self.lines)

    def rest(self, timeout: float = 20.0) -> str:
        """All of it, once the process has closed its stderr."""
        self._thread.join(timeout)
        return self.text
