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
