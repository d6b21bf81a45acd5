import logging
from pathlib import Path

import numpy as np
import pytest

from visvec.errors import ConfigError, VisvecError
from visvec.rig import load_rig

from conftest import CONFIGS

GOOD = (CONFIGS / "triangle.toml").read_text()
VERTS = "vertices_mm = [[372.5, 0.0, 2150.0], [-186.3, 190.5, 2150.0], [-186.3, -190.5, 2150.0]]"
SWAPPED = "vertices_mm = [[-186.3, 190.5, 2150.0], [372.5, 0.0, 2150.0], [-186.3, -190.5, 2150.0]]"


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_example_configs_load():
    for name in ("triangle.toml", "triangle-320.toml"):
        rig = load_rig(CONFIGS / name)
        assert rig.camera.width in (320, 640)
        assert rig.target.vertices_mm.shape == (3, 3)
        np.testing.assert_allclose(rig.R_bc, np.eye(3))


@pytest.mark.parametrize(
    "old, new, words",
    [
        ("fx = 600.0", "", ["[camera] fx", "missing"]),
        ("fx = 600.0", 'fx = "wide"', ["[camera] fx", "expected a finite number"]),
        ("fx = 600.0", "fx = -5.0", ["[camera] fx", "> 0"]),
        ("width = 640", "width = 640.5", ["[camera] width", "whole number"]),
        ('kind = "triangle"', 'kind = "hexagon"', ["[target] kind", "expected one of"]),
        ('kind = "triangle"', 'kind = "lamps"', ["[target] map", "missing"]),
        ('kind = "triangle"', 'kind = "markers"', ["[mount] on", "fixed in the lab"]),
        ('on = "platform"', 'on = "ceiling"', ["[mount] on", "expected one of"]),
        (
            "rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]",
            "rotation = [[1, 0, 0], [0, 2, 0], [0, 0, 1]]",
            ["[mount] rotation", "rotation"],
        ),
        (
            "rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]",
            "rotation = [[1, 0], [0, 1]]",
            ["[mount] rotation", "3 x 3"],
        ),
        (
            VERTS,
            SWAPPED,
            ["[target] vertices_mm", "most acute"],
        ),
        (
            VERTS,
            "vertices_mm = [[0.0, 0.0, 2150.0], [1.0, 0.0, 2150.0], [2.0, 0.0, 2150.0]]",
            ["[target] vertices_mm", "collinear"],
        ),
        (
            "max_tilt_deg = 10.0",
            "max_tilt_deg = 10.0\nmax_tilt = 3",
            ["[platform]", "unknown key", "max_tilt"],
        ),
        ('refine = "lines"', 'refine = "magic"', ["[detect] refine", "expected one of"]),
        (
            "sigma_scale = 1.0",
            "sigma_scale = 0.0",
            ["[detect] sigma_scale", "expected a number > 0"],
        ),
        ("readout_ms = 0.0", "readout_ms = 40.0", ["[camera] readout_ms", "expected a number in"]),
        ("readout_ms = 0.0", "readout_ms = -34.0", ["[camera] readout_ms", "expected a number in"]),
        (
            "readout_ms = 0.0",
            "readout_ms = 0.0\nreadout_sigma_ms = 2.0",
            ["[camera] readout_sigma_ms = 2.0", "needs a readout_ms"],
        ),
        (
            "readout_ms = 0.0",
            "readout_ms = 20.0\nreadout_sigma_ms = -1.0",
            ["[camera] readout_sigma_ms", "expected a number in"],
        ),
        (
            "max_rate_dps = 10.0",
            "max_rate_dps = -5.0",
            ["[platform] max_rate_dps", "expected a number"],
        ),
        (
            "height_sigma_mm = 20.0",
            "height_sigma_mm = -1.0",
            ["[target] height_sigma_mm", "expected a number in"],
        ),
        ("[platform]", "[plaftorm]", ["unknown section", "plaftorm"]),
        (
            "readout_ms = 0.0",
            'readout_ms = 0.0\ntone_curve = "sRGB2"',
            ["[camera] tone_curve", 'expected "linear"'],
        ),
        (
            "readout_ms = 0.0",
            "readout_ms = 0.0\ntone_curve = 0.0",
            ["[camera] tone_curve", "a gamma from 0.2 to 5"],
        ),
        ("readout_ms = 0.0", "readout_ms = 0.0\ntone_curve = true", ["[camera] tone_curve"]),
        (
            # k1 mistyped tenfold: the polynomial turns back 138 px out
            "dist = [0.0, 0.0, 0.0, 0.0, 0.0]",
            "dist = [-2.8, 0.0, 0.0, 0.0, 0.0]",
            ["[camera] dist", "folds over 138 px", "not a lens", "k1 k2 p1 p2 k3"],
        ),
        (
            "rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]",
            "rotation = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]",
            ["behind the camera"],
        ),
    ],
)
def test_bad_rig_is_refused_with_file_key_and_expectation(tmp_path, old, new, words):
    assert old in GOOD
    p = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    msg = str(exc.value)
    assert str(p) in msg
    for w in words:
        assert w in msg, msg
    assert isinstance(exc.value, VisvecError) and isinstance(exc.value, ValueError)


def test_the_pixel_fit_is_taken_with_or_without_a_rolling_shutter(tmp_path):
    """refine = "pixels" models a rolling shutter too (the pixels taken to the centre
    row's exposure): a rig with a readout time and the pixel fit loads."""
    pixels = GOOD.replace('refine = "lines"', 'refine = "pixels"')
    assert load_rig(write(tmp_path, pixels)).detect.refine == "pixels"
    rolling = load_rig(write(tmp_path, pixels.replace("readout_ms = 0.0", "readout_ms = 20.0")))
    assert rolling.detect.refine == "pixels" and rolling.readout_ms == 20.0


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_rig(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_rig(write(tmp_path, "[camera\nwidth = 3"))


def test_calibration_file_overrides_named_keys(tmp_path):
    rig_p = write(tmp_path, GOOD)
    cal = tmp_path / "cal.toml"
    cal.write_text("[zero_tilt]\ncentroid_px = [321.0, 240.5]\n[camera]\nfx = 612.0\n")
    rig = load_rig(rig_p, cal)
    assert rig.camera.fx == 612.0 and rig.camera.fy == 600.0
    np.testing.assert_allclose(rig.zero_tilt.centroid_px, [321.0, 240.5])
    cal.write_text("[bogus]\nx = 1\n")
    with pytest.raises(ConfigError, match=r"cal.toml: unknown section"):
        load_rig(rig_p, cal)


def test_calibration_files_apply_in_order(tmp_path):
    # camera, then zero-tilt, then readout: each overrides the keys it names, a later
    # file wins, and a bad key in any of them is refused naming the rig and the files
    rig_p = write(tmp_path, GOOD)
    cam, readout, bad = tmp_path / "cam.toml", tmp_path / "readout.toml", tmp_path / "bad.toml"
    cam.write_text("[camera]\nfx = 612.0\nfy = 611.0\n")
    readout.write_text("[camera]\nreadout_ms = 21.5\nfy = 613.0\n")
    rig = load_rig(rig_p, [cam, readout])
    assert (rig.camera.fx, rig.camera.fy, rig.readout_ms) == (612.0, 613.0, 21.5)
    rig = load_rig(rig_p, [readout, cam])
    assert (rig.camera.fy, rig.readout_ms) == (611.0, 21.5)
    # a bad key is named with the file it came from
    bad.write_text("[camera]\nfx = -1.0\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[camera\] fx = -1.0: expected"):
        load_rig(rig_p, (cam, bad))
    bad.write_text("[camera]\nfz = 600.0\n")
    with pytest.raises(ConfigError, match=r"bad.toml: \[camera\] unknown key\(s\) \['fz'\]"):
        load_rig(rig_p, (cam, bad))
    # a key from the rig file is named with the rig file
    with pytest.raises(ConfigError, match=r"rig.toml: \[camera\] fx = -1.0"):
        load_rig(write(tmp_path, GOOD.replace("fx = 600.0", "fx = -1.0")), readout)


MARKERS = (CONFIGS / "markers.toml").read_text()


def test_markers_rig_loads():
    rig = load_rig(CONFIGS / "markers.toml")
    assert rig.kind == "markers" and rig.target.points_b.shape == (21, 3)
    assert rig.target.reference_id == 20
    assert rig.target.placement_sigma_mm == 0.05
    # marker 6 is pattern 1's second LED, (40, 0, 0) in the board turned 35 deg about b3
    pat = rig.target.patterns[1]
    c, s = np.cos(np.radians(35.0)), np.sin(np.radians(35.0))
    np.testing.assert_allclose(
        rig.target.points_b[6], pat.position_mm + [40.0 * c, 40.0 * s, 0.0], atol=1e-4
    )


@pytest.mark.parametrize(
    "old, new, words",
    [
        ("reference_id = 20", "reference_id = 21", ["[target] reference_id", "0..20"]),
        ("reference_id = 20", 'reference_id = "top"', ["[target] reference_id"]),
        (
            "points_mm = [[0.0, 0.0, 0.0]]",
            "points_mm = [[0.0, 0.0]]",
            ["[target.patterns[4]] points_mm", "[x, y, z]"],
        ),
        (
            "points_mm = [[0.0, 0.0, 0.0]]",
            "points_mm = [[0.0, 0.0, 0.0]]\ncolour = 'green'",
            ["[target.patterns[4]]", "unknown key", "colour"],
        ),
        (
            "position_mm = [-80.0, -200.0, 150.0]",
            "position_mm = [103.21, 96.68, 150.0]",
            ["markers 0 and 20 are at the same place"],
        ),
        ('on = "lab"', 'on = "platform"', ["[mount] on", "fixed in the lab"]),
        (
            "placement_sigma_mm = 0.05",
            "placement_sigma_mm = -0.05",
            ["[target] placement_sigma_mm", "[0.0, 10.0]"],
        ),
    ],
)
def test_bad_markers_rig(tmp_path, old, new, words):
    assert old in MARKERS
    p = write(tmp_path, MARKERS.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    for w in words:
        assert w in str(exc.value), str(exc.value)


# a strong barrel lens at fx 340 whose k3 turns the polynomial back 345 px out, short of
# the 400 px corners of a 640x480 image
FOLDING = (
    GOOD.replace("fx = 600.0", "fx = 340.0")
    .replace("fy = 600.0", "fy = 340.0")
    .replace("dist = [0.0, 0.0, 0.0, 0.0, 0.0]", "dist = [-0.32, 0.12, 0.0, 0.0, -0.02]")
)


def test_a_lens_model_folding_short_of_the_corners_is_loaded_with_a_warning(
    tmp_path, caplog, monkeypatch
):
    # (a CLI test run before may have routed the visvec logger to stderr, unpropagated)
    monkeypatch.setattr(logging.getLogger("visvec"), "propagate", True)
    p = write(tmp_path, FOLDING)
    with caplog.at_level("WARNING", logger="visvec"):
        rig = load_rig(p)
    assert rig.camera.field_radius_px == pytest.approx(344.8, abs=0.1)
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "[camera] dist" in msg and "folds over 345 px" in msg and "corners (400 px)" in msg
    assert str(p) in msg


def test_a_target_beyond_the_lens_models_field_is_refused(tmp_path):
    # the triangle 3.5 m off the axis: its rays 60 deg out, beyond the fold at 59 deg
    far = (
        "vertices_mm = [[2972.5, 1900.0, 2150.0], [2413.7, 2090.5, 2150.0], "
        "[2413.7, 1709.5, 2150.0]]"
    )
    p = write(tmp_path, FOLDING.replace(VERTS, far))
    with pytest.raises(ConfigError) as exc:
        load_rig(p)
    msg = str(exc.value)
    assert str(p) in msg and "[target] vertices_mm" in msg
    assert "beyond the lens model's field" in msg


def test_the_imu_section_declares_the_gyro_range(tmp_path):
    """[imu] gyro_range_dps: the gyro's range, from its datasheet; absent: None (learned
    only from the evidence); not a positive finite number, or an unknown key: refused
    naming the file and key."""
    assert load_rig(write(tmp_path, GOOD)).imu.gyro_range_dps is None
    rig = load_rig(write(tmp_path, GOOD + "\n[imu]\ngyro_range_dps = 2000\n"))
    assert rig.imu.gyro_range_dps == 2000.0
    bad_values = (("0", "expected a number > 0"), ("-5", "expected a number > 0"),
                  ('"fast"', "expected a finite number"), ("nan", "finite number"))  # fmt: skip
    for bad, words in bad_values:
        with pytest.raises(ConfigError, match=rf"\[imu\] gyro_range_dps = .*{words}"):
            load_rig(write(tmp_path, GOOD + f"\n[imu]\ngyro_range_dps = {bad}\n"))
    with pytest.raises(ConfigError, match=r"\[imu\] unknown key\(s\) \['gyro_rang'\]"):
        load_rig(write(tmp_path, GOOD + "\n[imu]\ngyro_rang = 2000\n"))
