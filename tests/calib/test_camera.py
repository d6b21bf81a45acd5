"""`visvec calibrate camera`: intrinsics from chessboards against OpenCV's reference."""

import tomllib

import numpy as np

from visvec.calib.camera import calibrate_camera
from visvec.camera import CameraModel
from visvec.rig import load_rig

from conftest import CONFIGS, run, shared


def test_camera_calibration_reproduces_opencv_reference():
    d = shared("opencv_chessboard")
    files = [d / f"left{i:02d}.jpg" for i in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)]
    cal = calibrate_camera(files, (9, 6), 1.0, recipe="opencv-test")
    # reference_values.json, reference A: fx 532.80992189, rms 0.196334638 (tol 0.01)
    assert abs(cal.K[0, 0] - 532.80992189) < 0.5
    assert abs(cal.rms_px - 0.196334638) < 0.01
    ref = np.array([[532.80992189, 0.0, 342.4952186], [0.0, 532.93346422, 233.8879292], [0, 0, 1]])
    assert np.abs(cal.K - ref).sum() < 10.0
    # OpenCV's standard deviations of fx, fy, cx, cy: 0.44-0.51 px on these 13 views
    # (what --principal-point-sigma of `calibrate readout` takes)
    assert np.all((0.2 < cal.sigma_px) & (cal.sigma_px < 1.0)), cal.sigma_px


def test_camera_calibration_cli_names_outlier_view(tmp_path):
    d = shared("opencv_chessboard")
    out = tmp_path / "cam.toml"
    r = run("calibrate", "camera", d / "left*.jpg", "--pattern", "9x6", "--square-mm", "25",
            "--out", out)  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "left02.jpg" in r.output and "outlier" in r.output
    assert "  cx 342." in r.output and " +- 0." in r.output.split("  cx 342.")[1][:12]
    # the focal length written: OpenCV's own reference for these photos (532.81 px,
    # reference_values.json) to 1 %, as the outlier view left out and the default
    # recipe's distortion model allow
    written = tomllib.loads(out.read_text())["camera"]
    assert abs(written["fx"] - 532.80992189) < 0.01 * 532.8
    # how far the photos reached (the left views: 278 px of the 421 px to the corners)
    reach = float(r.output.split("the photos' corners reach ")[1].split(" px")[0])
    assert 250.0 < reach < 421.0
    cam = load_rig(CONFIGS / "triangle.toml", calibration=out).camera
    corners = f"the image's corners {cam.corner_radius_px:.0f} px"
    assert f"{corners}; the lens model holds to the image's corners" in r.output
    r = run("calibrate", "camera", str(d), "--pattern", "nine", "--square-mm", "25")
    assert r.exit_code == 2 and "COLSxROWS" in r.output


def test_camera_calibration_warns_when_its_lens_model_folds_short_of_the_corners():
    from visvec.cli.calibrate import _coverage

    # a barrel lens fitted from photos that stayed 300 px from the centre, whose k3
    # turns the polynomial back 345 px out, short of the 400 px corners
    cam = CameraModel(640, 480, 340.0, 340.0, 319.5, 239.5, np.array([-0.32, 0.12, 0, 0, -0.02]))
    text = _coverage(cam, 300.0)
    assert "reach 300 px from the principal point, the image's corners 400 px" in text
    assert "warning: the lens model folds over 345 px out" in text
    assert "chessboard in the corners" in text
