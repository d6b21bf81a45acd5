"""`visvec calibrate readout`: a rolling shutter's readout from a turning recording."""

import pytest

from visvec.rig import load_rig

from conftest import CONFIGS, rig_variant, run


def _turning(rig_p, rec, motion, rate_dps, *more):
    """A 40-frame recording (seed 3) of the platform turning, ``more`` options added."""
    r = run("simulate", "--rig", rig_p, "--out", rec, "--frames", 40, "--seed", 3, "--motion",
            motion, "--yaw-rate-dps", rate_dps, *more)  # fmt: skip
    assert r.exit_code == 0, r.output


@pytest.mark.slow  # 6-7 s: the default run stays under 5 minutes
def test_calibrate_readout_measures_a_rolling_shutter_from_a_turning_recording(tmp_path):
    """A 640x480 webcam reading its rows over 25 ms, recorded while the platform swings
    out and back at up to 15 deg/s (the recording the README asks for): the readout
    whose correction leaves the triangle rigid, the camera's principal point and aspect
    estimated beside it, is found within 3 sigma (about 2 ms), written as [camera]
    readout_ms, and the rig takes it."""
    rig_p = CONFIGS / "triangle.toml"
    rec = tmp_path / "turn"
    _turning(rig_p, rec, "swing", 15, "--readout-ms", 25)
    cal = tmp_path / "readout.toml"
    r = run("calibrate", "readout", rec, "--rig", rig_p, "--out", cal)
    assert r.exit_code == 0, r.output
    rig = load_rig(rig_p, cal)
    sigma = float(r.output.split("+- ")[1].split(" ms")[0])
    assert 0.2 < sigma < 3.0
    assert abs(rig.readout_ms - 25.0) < 3.0 * sigma, r.output
    # with its sigma, which the rows' sigma then carries
    assert abs(rig.readout_sigma_ms - sigma) <= 0.006
    assert "put readout_ms = " in r.output and " and readout_sigma_ms = " in r.output
    assert "no zero-tilt calibration given" in r.stderr  # the order the README gives


@pytest.mark.slow  # 7 s on a slow host
def test_calibrate_readout_is_not_fooled_by_a_principal_point_off(tmp_path):
    """A global-shutter camera whose principal point is 4 px right of the rig file's,
    swinging at up to 20 deg/s: the keystone that error leaves turns with the yaw as a
    shear does, and taking the camera model as exact reads a readout more than 2 sigma
    from 0 on this recording (+4.9 +- 1.9 ms); estimated beside the principal point and
    the aspect, the readout is within 2 sigma of 0 and 0 is written."""
    rig_p = CONFIGS / "triangle.toml"
    true_rig = rig_variant(rig_p, "cx", "319.5", "323.5", tmp_path / "true.toml")
    rec = tmp_path / "swing"
    _turning(true_rig, rec, "swing", 20)
    cal = tmp_path / "readout.toml"
    r = run("calibrate", "readout", rec, "--rig", rig_p, "--out", cal)
    assert r.exit_code == 0, r.output
    exact = r.output.split("taking them as exact: ")[1]
    k, sigma = (float(x) for x in exact.split(" ms")[0].split(" +- "))
    assert abs(k) > 2.0 * sigma, r.output  # the confusion is there to be undone
    k, sigma = (float(x) for x in r.output.split("row): ")[1].split(" ms")[0].split(" +- "))
    assert abs(k) < 2.0 * sigma and sigma < 3.0, r.output
    assert "readout_ms = 0 written" in r.output
    # a global shutter: no readout, so no readout sigma either

    rig = load_rig(rig_p, cal)
    assert rig.readout_ms == 0.0 and rig.readout_sigma_ms == 0.0


def test_calibrate_readout_refuses_a_platform_at_rest(tmp_path):
    """Nothing to see without motion: the reason, exit 1, no file."""
    rig_p = CONFIGS / "triangle-320.toml"
    rec = tmp_path / "rest"
    r = run("simulate", "--rig", rig_p, "--out", rec, "--frames", 12, "--motion", "sweep",
                "--yaw-rate-dps", 0.5)  # fmt: skip
    assert r.exit_code == 0, r.output
    cal = tmp_path / "readout.toml"
    zero = tmp_path / "zero.toml"  # given a zero-tilt calibration: no note about it
    zero.write_text("[zero_tilt]\ncentroid_px = [159.5, 119.5]\n")
    r = run("calibrate", "readout", rec, "--rig", rig_p, "--calibration", zero, "--out", cal)
    assert r.exit_code == 1 and "record it turning" in r.output and "nothing written" in r.output
    assert not cal.exists() and "zero-tilt" not in r.stderr


def test_calibrate_readout_says_when_the_readout_is_poorly_determined(tmp_path):
    """A 320x240 camera turning one way at 10 deg/s for 40 frames: the readout is found
    too loosely once the principal point is estimated beside it (sigma over a quarter of
    the frame interval). Refused, exit 1, no file; the library says what would help and
    the command line names its option for it."""
    rig_p = CONFIGS / "triangle-320.toml"
    rec = tmp_path / "sweep"
    _turning(rig_p, rec, "sweep", 10, "--readout-ms", 25)
    cal = tmp_path / "readout.toml"
    r = run("calibrate", "readout", rec, "--rig", rig_p, "--out", cal)
    assert r.exit_code == 1 and not cal.exists(), r.output
    assert "the readout is poorly determined" in r.output
    advice = "a prior on the principal point from a camera calibration (--principal-point-sigma)"
    assert advice in r.output
