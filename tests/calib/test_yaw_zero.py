"""Yaw zero: the camera's turn about b3 on its mount, from level stops at known yaws
(calibrate zero-tilt --yaw-deg), which level frames alone cannot tell from yaw zero."""

from __future__ import annotations

import csv
import shutil
import tomllib

import numpy as np
import pytest

from visvec.calib.zero_tilt import ZeroTiltResult, yaw_reference

from conftest import ROOT, run

RIG = ROOT / "configs" / "triangle.toml"
TURN = 0.3


@pytest.fixture(scope="module")
def stops(tmp_path_factory):
    """8 level stops (one frame each) of a lab whose camera is turned 0.3 deg about its
    optical axis and tilted on its mount, the target off the axis; their true yaws."""
    tmp = tmp_path_factory.mktemp("yaw")
    r = run("simulate", "--rig", RIG, "--out", tmp / "level", "--frames", 8, "--motion", "level",
            "--camera-turn-deg", TURN, "--camera-askew-deg", 0.5, -0.4,
            "--target-offset-mm", 12, -9)  # fmt: skip
    assert r.exit_code == 0, r.output
    truth = list(csv.DictReader(open(tmp / "level" / "truth.csv")))
    folders = []
    for k, t in enumerate(truth):
        d = tmp / f"stop{k}"
        d.mkdir()
        shutil.copy(tmp / "level" / t["file"], d / t["file"])
        folders.append(d)
    return tmp, folders, [float(t["yaw_deg"]) for t in truth]


def test_turn_from_two_known_stops(stops, tmp_path):
    tmp, folders, yaws = stops
    given = [f"{y:.6f}" if k in (0, 3) else "-" for k, y in enumerate(yaws)]
    cal = tmp_path / "cal.toml"
    r = run("calibrate", "zero-tilt", *folders, "--rig", RIG, "--out", cal,
            *[x for y in given for x in ("--yaw-deg", y)], "--yaw-sigma-deg", 0.005)  # fmt: skip
    assert r.exit_code == 0, r.output
    rep = tomllib.loads(cal.read_text())["report"]
    assert rep["yaw_stops"] == 2
    # the true turn within 3 sigma, and the sigma no wider than the reference allows
    assert abs(rep["camera_turn_deg"] - TURN) < 3 * rep["sigma_camera_turn_deg"]
    assert rep["sigma_camera_turn_deg"] < 0.01
    said = f"camera turn about b3 (yaw zero): {rep['camera_turn_deg']:+.4f} +- "
    assert said in r.output
    # the calibrated rig reads a stop's yaw as the reference's
    r = run("batch", folders[5], "--rig", RIG, "--calibration", cal)
    row = next(csv.DictReader(r.stdout.splitlines()))
    assert abs(float(row["yaw_deg"]) - yaws[5]) < 0.02


def test_without_known_yaws_the_turn_is_said_uncalibrated(stops, tmp_path):
    tmp, folders, yaws = stops
    cal = tmp_path / "cal.toml"
    r = run("calibrate", "zero-tilt", *folders, "--rig", RIG, "--out", cal)
    assert r.exit_code == 0, r.output
    assert "yaw zero: not calibrated" in r.output and "--yaw-deg" in r.output
    assert "not calibrated" in tomllib.loads(cal.read_text())["report"]["yaw_zero"]
    # and the yaw then carries the turn
    r = run("batch", folders[5], "--rig", RIG, "--calibration", cal)
    row = next(csv.DictReader(r.stdout.splitlines()))
    assert abs(float(row["yaw_deg"]) - yaws[5] - TURN) < 0.02


def test_yaw_deg_must_match_the_recordings(stops, tmp_path):
    tmp, folders, yaws = stops
    r = run("calibrate", "zero-tilt", *folders[:3], "--rig", RIG, "--out", tmp_path / "c.toml",
            "--yaw-deg", 10, "--yaw-deg", 20)  # fmt: skip
    assert r.exit_code == 2 and "2 values for 3 recordings" in r.output
    r = run("calibrate", "zero-tilt", *folders[:2], "--rig", RIG, "--out", tmp_path / "c.toml",
            "--yaw-deg", "north", "--yaw-deg", "-")  # fmt: skip
    assert r.exit_code == 2 and "'north'" in r.output


def test_stops_that_disagree_are_flagged():
    """Two stops whose turns differ by 1 deg against a 0.01 deg reference: the scatter
    check says so; one stop alone has no such check."""
    n = 4
    res = ZeroTiltResult(
        target_offset_mm=np.zeros(2), sigma_target_offset_mm=np.zeros(2),
        camera_tilt_deg=np.zeros(2), sigma_camera_tilt_deg=np.zeros(2), height_offset_mm=0.0,
        sigma_height_offset_mm=0.0, centroid_px=np.zeros(2), sigma_centroid_px=np.zeros(2),
        yaw_deg=np.array([10.3, 10.3, 41.3, 41.3]), residual_px=np.zeros(n), rms_px=0.0,
        converged=True, outliers=np.zeros(n, dtype=bool),
    )  # fmt: skip
    out = yaw_reference(res, np.array([10.0, 10.0, 40.0, 40.0]), np.array([0, 0, 1, 1]), 0.01)
    assert out.yaw_stops == 2 and out.yaw_stop_chi2_dof > 100
    assert out.camera_turn_deg == pytest.approx(0.8, abs=1e-9)  # the stops' mean
    one = yaw_reference(res, np.array([10.0, 10.0, np.nan, np.nan]), np.array([0, 0, 1, 1]), 0.01)
    assert one.camera_turn_deg == pytest.approx(0.3) and np.isnan(one.yaw_stop_chi2_dof)
    assert one.sigma_camera_turn_deg == pytest.approx(0.01)


def test_fps_sets_the_rate_of_a_folder_without_times(tmp_path):
    """`rate FOLDER --fps 10` on star frames at 10 Hz with no times.csv: the rates are
    the truth's (at the rig's 30 fps they would be 3x off)."""
    star = ROOT / "configs" / "starfield.toml"
    rec = tmp_path / "rec"
    r = run("simulate", "--rig", star, "--out", rec, "--frames", 4, "--case", 1, "--fps", 10)
    assert r.exit_code == 0, r.output
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in rec.glob("*.png"):
        shutil.copy(f, bare / f.name)
    truth = list(csv.DictReader(open(rec / "truth.csv")))
    r = run("rate", bare, "--rig", star, "--fps", 10)
    assert r.exit_code == 0, r.output
    rows = [x for x in csv.DictReader(r.stdout.splitlines()) if x["status"] == "ok"]
    assert rows
    for x in rows:
        t = next(t for t in truth if t["frame"] == x["frame"])
        for k in ("wx_dps", "wy_dps", "wz_dps"):
            assert abs(float(x[k]) - float(t[k])) < 5 * float(x[f"sigma_{k}"]) + 1e-3


def test_a_rig_without_max_tilt_says_the_default(tmp_path):
    text = (ROOT / "configs" / "markers.toml").read_text()
    lines = [x for x in text.splitlines() if not x.startswith("max_tilt_deg")]
    (tmp_path / "rig.toml").write_text("\n".join(lines) + "\n")
    rec = tmp_path / "rec"
    assert (
        run("simulate", "--rig", tmp_path / "rig.toml", "--out", rec, "--frames", 2).exit_code == 0
    )
    r = run("batch", rec, "--rig", tmp_path / "rig.toml")
    assert "no [platform] max_tilt_deg: the default 10 deg applies" in r.stderr
    r = run("batch", rec, "--rig", ROOT / "configs" / "markers.toml")
    assert "max_tilt_deg" not in r.stderr
