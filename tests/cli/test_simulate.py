"""`visvec simulate` (visvec.cli.simulate): recordings with truth, a rolling shutter,
motion blur."""

import csv

import cv2
import numpy as np
import pytest

from conftest import CONFIGS, assert_within_3_sigma, rows_of, run

RIG = str(CONFIGS / "triangle.toml")


def test_simulate_writes_frames_and_truth(tmp_path):
    r = run(
        "simulate",
        "--rig",
        CONFIGS / "triangle-320.toml",
        "--out",
        tmp_path / "s",
        "--frames",
        "3",
        "--seed",
        "4",
    )
    assert r.exit_code == 0
    truth = list(csv.DictReader(open(tmp_path / "s" / "truth.csv")))
    assert [t["file"] for t in truth] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    img = cv2.imread(str(tmp_path / "s" / "frame_0000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320) and img.dtype == np.uint8


def test_simulate_a_rolling_shutter_sweep_that_batch_corrects(tmp_path):
    """`simulate --readout-ms` renders a sweep with each frame's rates; `batch` with the
    rig's readout_ms corrects every frame after the first, which says it is uncorrected
    and whose sigma covers the turn."""
    rig = tmp_path / "rig.toml"
    text = (CONFIGS / "triangle.toml").read_text()
    rig.write_text(
        text.replace("readout_ms = 0.0", "readout_ms = 25.0").replace(
            "max_rate_dps = 10.0", "max_rate_dps = 20.0"
        )
    )
    sim = ["simulate", "--rig", RIG, "--frames", "10", "--seed", "5", "--motion", "sweep"]
    fast = ["--yaw-rate-dps", "20", "--max-tilt-deg", "3"]
    assert run(*sim, "--out", tmp_path / "g", *fast).exit_code == 0
    r = run(*sim, "--out", tmp_path / "s", *fast, "--readout-ms", "25")
    assert r.exit_code == 0, r.output
    a = cv2.imread(str(tmp_path / "g" / "frame_0004.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(tmp_path / "s" / "frame_0004.png"), cv2.IMREAD_GRAYSCALE)
    assert np.count_nonzero(a != b) > 500  # rows exposed at their own attitudes
    truth = list(csv.DictReader(open(tmp_path / "s" / "truth.csv")))
    yaw = np.unwrap(np.radians([float(t["yaw_deg"]) for t in truth]))
    np.testing.assert_allclose(np.degrees(np.diff(yaw)) * 30.0, 20.0, rtol=1e-6)
    r = run("batch", tmp_path / "s", "--rig", rig)
    rows = rows_of(r.stdout)
    assert r.exit_code == 0 and [x["status"] for x in rows] == ["ok"] * 10
    uncorrected = [i for i, x in enumerate(rows) if "rolling_shutter_uncorrected" in x["warnings"]]
    assert uncorrected == [0]
    assert_within_3_sigma(rows, truth)
    bad = run(*sim, "--out", tmp_path / "x", "--readout-ms", "40")
    assert bad.exit_code == 2 and "--readout-ms" in bad.output
    bad = run("simulate", "--rig", RIG, "--out", tmp_path / "x", "--yaw-rate-dps", "5")
    assert bad.exit_code == 2 and "--motion sweep" in bad.output


@pytest.mark.slow  # 10 s on a slow host
def test_motion_blur_of_a_long_exposure_neither_loses_nor_biases_the_triangle(tmp_path):
    """`simulate --exposure-ms 33` blurs a 40 deg/s sweep by its motion (each row
    collects light over 33 ms, centred on its time); tracked, every frame is ok and
    within 3 sigma: a blur symmetric about the exposure's middle moves no edge."""
    rig = str(CONFIGS / "triangle-320.toml")
    sim = ["simulate", "--rig", rig, "--frames", "10", "--seed", "8", "--motion", "sweep"]
    fast = ["--yaw-rate-dps", "40"]
    assert run(*sim, "--out", tmp_path / "sharp", *fast).exit_code == 0
    r = run(*sim, "--out", tmp_path / "blur", *fast, "--exposure-ms", "33")
    assert r.exit_code == 0, r.output
    a = cv2.imread(str(tmp_path / "sharp" / "frame_0005.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(tmp_path / "blur" / "frame_0005.png"), cv2.IMREAD_GRAYSCALE)
    assert np.count_nonzero(np.abs(a.astype(int) - b) > 3) > 100  # edges smeared
    r = run("batch", tmp_path / "blur", "--rig", rig)
    rows = rows_of(r.stdout)
    truth = list(csv.DictReader(open(tmp_path / "blur" / "truth.csv")))
    assert [x["status"] for x in rows] == ["ok"] * 10
    assert_within_3_sigma(rows, truth)
    bad = run(*sim, "--out", tmp_path / "x", "--exposure-ms", "50")
    assert bad.exit_code == 2 and "--exposure-ms" in bad.output


def test_a_rolling_shutter_sweep_faster_than_the_rigs_bound_is_said(tmp_path):
    """A sweep rendered with a rolling shutter turning faster than the rig's [platform]
    max_rate_dps (what the sensor's sigma covers before it knows a frame's rate) is said
    on stderr, with the option that sets the turn; one within it is not."""
    rig = CONFIGS / "triangle-320.toml"
    fast = run("simulate", "--rig", rig, "--out", tmp_path / "a", "--frames", "4",
               "--motion", "sweep", "--readout-ms", "25")  # fmt: skip
    assert fast.exit_code == 0
    assert "beyond the rig's [platform] max_rate_dps = 10" in fast.output
    assert "--yaw-rate-dps" in fast.output
    slow = run("simulate", "--rig", rig, "--out", tmp_path / "b", "--frames", "4",
               "--motion", "sweep", "--readout-ms", "25", "--yaw-rate-dps", "5")  # fmt: skip
    assert slow.exit_code == 0 and "max_rate_dps" not in slow.output
