"""Shared fixtures: rigs, shared data location, helpers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from visvec.rig import load_rig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SHARED_DATA = ROOT.parent / "shared" / "data"


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
