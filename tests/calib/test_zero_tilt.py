"""`calibrate_zero_tilt` and `visvec calibrate zero-tilt`: target offset, height and
camera tilt from level frames; the checks of the camera model and of the sigma."""

import re

import numpy as np
import pytest

from visvec.calib.zero_tilt import calibrate_zero_tilt, circle_centre
from visvec.data import Detection, Status
from visvec.errors import InputFileError
from visvec.geometry import lab_to_camera
from visvec.rotations import euler_to_matrix, quat_to_matrix
from visvec.sim.simulate import true_rig

from conftest import CONFIGS, rig_variant, run


def _level_detections(rig, world, yaws, sigma_px=0.03, rng=None):
    dets = []
    for y in yaws:
        p = lab_to_camera(world, euler_to_matrix(y, 0.0, 0.0), world.target.vertices_mm)
        xy = p[:, :2] / p[:, 2:3]
        if rng is not None:
            xy = xy + rng.standard_normal(xy.shape) * sigma_px / rig.camera.fx
        dets.append(
            Detection(
                Status.OK,
                points_px=rig.camera.distort(xy),
                points_n=xy,
                cov_n=np.eye(6) * (sigma_px / rig.camera.fx) ** 2,
            )
        )
    return dets


@pytest.mark.parametrize("height_mm", [0.0, 12.0])
def test_zero_tilt_recovers_target_offset_height_and_camera_tilt(rig640, rng, height_mm):
    # the target also hung 12 mm higher than the rig file says: a ceiling measured wrong
    world = true_rig(rig640, (15.0, -6.0), (0.7, -0.4), height_mm)
    dets = _level_detections(rig640, world, np.radians(np.arange(-180, 180, 30)), rng=rng)
    res = calibrate_zero_tilt(dets, rig640)
    assert res.converged
    np.testing.assert_allclose(
        res.target_offset_mm, [15.0, -6.0], atol=4 * res.sigma_target_offset_mm.max() + 0.05
    )
    np.testing.assert_allclose(
        res.camera_tilt_deg, [0.7, -0.4], atol=4 * res.sigma_camera_tilt_deg.max() + 1e-3
    )
    assert abs(res.height_offset_mm - height_mm) < 4 * res.sigma_height_offset_mm
    assert res.sigma_height_offset_mm < 0.5
    assert res.rms_px < 0.1
    # the height taken up: the vertices' scatter is their noise, not a misfit
    assert res.sigma_scale == 1.0
    # applied, the calibrated rig reproduces the true one
    cal = res.apply(rig640)
    np.testing.assert_allclose(cal.target.vertices_mm, world.target.vertices_mm, atol=0.5)


@pytest.mark.parametrize("fy_scale, dcx", [(1.005, 0.0), (1.0, 10.0), (1.0, 0.0)])
def test_zero_tilt_says_when_the_rig_camera_model_is_wrong(rig640, fy_scale, dcx):
    """The rig file's fy 0.5 % too large, or its cx 10 px off, in a lab whose target is
    15 mm off the axis and whose camera is 0.7 deg askew: the level frames at 12 yaws
    fit only with the camera's aspect and principal point free, and the check gives the
    values that fit (within 3 sigma of the truth) and says the camera model is off (its
    residuals would read as a sigma_scale of several). The right camera: consistent."""
    from dataclasses import replace

    world = true_rig(rig640, (15.0, -6.0), (0.7, -0.4), 0.0)
    cam = rig640.camera
    rig = replace(rig640, camera=replace(cam, fy=cam.fy * fy_scale, cx=cam.cx + dcx))
    yaws = np.radians(np.arange(-180, 180, 30))
    dets = _level_detections(rig640, world, yaws, rng=np.random.default_rng(7))
    # pixels of the true camera, normalised with the rig file's
    true_f, true_c = np.array([cam.fx, cam.fy]), np.array([cam.cx, cam.cy])
    rig_f, rig_c = np.array([rig.camera.fx, rig.camera.fy]), np.array([rig.camera.cx, cam.cy])
    dets = [replace(d, points_n=(d.points_n * true_f + true_c - rig_c) / rig_f) for d in dets]
    res = calibrate_zero_tilt(dets, rig)
    assert res.camera_off == (fy_scale != 1.0 or dcx != 0.0)
    # the true fy is (1 + aspect) times the rig file's; the true cx is the rig's + dx
    assert abs(res.aspect - (1.0 / fy_scale - 1.0)) < 3.0 * res.sigma_aspect
    err = np.abs(res.principal_point_px - [-dcx, 0.0])
    assert np.all(err < 3.0 * res.sigma_principal_point_px), res.principal_point_px
    assert res.sigma_aspect < 2e-4 and np.all(res.sigma_principal_point_px < 1.0)


def test_calibrate_zero_tilt_cli_refuses_a_wrong_camera_model(tmp_path):
    """A rig file whose fy is 1 % too large: the level frames say so, give the fy that
    fits, and nothing is written (exit 1)."""
    rig_p = CONFIGS / "triangle-320.toml"
    wrong = rig_variant(rig_p, "fy", "300.0", "303.0", tmp_path / "wrong.toml")
    frames = tmp_path / "level"
    sim = ["simulate", "--rig", rig_p, "--out", frames, "--frames", 12, "--motion", "level"]
    assert run(*sim).exit_code == 0
    cal = tmp_path / "cal.toml"
    args = ["calibrate", "zero-tilt", str(frames), "--rig", str(wrong), "--out", str(cal)]
    r = run(*args)
    assert r.exit_code == 1 and not cal.exists(), r.output
    assert "camera check: aspect fy / fx" in r.output and ": off" in r.output
    fy = float(r.output.split("it fits with fy = ")[1].split(",")[0])
    assert abs(fy - 300.0) < 0.5, r.output
    assert "nothing written" in r.output


@pytest.mark.parametrize(
    "scale_in_rig",
    [1.0, pytest.param(1.5, marks=pytest.mark.slow)],  # 4 s each
)
def test_zero_tilt_measures_how_much_wider_the_vertices_scatter_than_their_sigma(
    rig640, scale_in_rig
):
    """The a-posteriori variance factor: vertices with 0.03 px of noise whose covariance
    says 0.02 px scatter 1.5x their sigma; the check is against the detector's own
    covariance whatever sigma_scale the rig already applies."""
    from dataclasses import replace

    world = true_rig(rig640, (15.0, -6.0), (0.7, -0.4))
    rig = replace(rig640, detect=replace(rig640.detect, sigma_scale=scale_in_rig))
    yaws = np.radians(np.arange(-180, 180, 3.0))  # 120 frames: 596 degrees of freedom
    dets = _level_detections(rig, world, yaws, 0.03, np.random.default_rng(5))
    own = (0.02 / rig.camera.fx) ** 2  # what the edge model says
    dets = [replace(d, cov_n=np.eye(6) * own * scale_in_rig**2) for d in dets]
    res = calibrate_zero_tilt(dets, rig)
    assert res.dof == 5 * len(dets) - 5  # 5 offsets: dx, dy, dh and the two tilts
    lo, hi = res.sigma_ratio_95
    assert lo < 1.5 < hi and hi - lo < 0.2
    assert res.sigma_scale == res.sigma_ratio
    assert res.apply(rig).detect.sigma_scale == res.sigma_ratio
    # an honest covariance passes the check and leaves the scale at 1
    dets = _level_detections(rig640, world, yaws, 0.02, np.random.default_rng(5))
    res = calibrate_zero_tilt(dets, rig640)
    lo, hi = res.sigma_ratio_95
    assert lo < 1.0 < hi
    assert res.sigma_scale == 1.0


def test_zero_tilt_names_a_frame_that_was_not_level(rig640):
    """One frame of 24 taken with the platform nudged (its vertices 0.3 px off, ten times
    their sigma) is named; the others are not."""
    from dataclasses import replace

    world = true_rig(rig640, (15.0, -6.0), (0.7, -0.4))
    dets = _level_detections(
        rig640, world, np.radians(np.arange(-180, 180, 15.0)), 0.03, np.random.default_rng(8)
    )
    dets[7] = replace(dets[7], points_n=dets[7].points_n + 0.3 / rig640.camera.fx)
    res = calibrate_zero_tilt(dets, rig640)
    # named alone (it pulled the common offsets, and its neighbours in yaw with them,
    # until it was left out), and the offsets are those of the level frames
    assert np.flatnonzero(res.outliers).tolist() == [7]
    np.testing.assert_allclose(
        res.target_offset_mm, [15.0, -6.0], atol=4 * res.sigma_target_offset_mm.max()
    )
    assert res.residual_px[7] > 0.2 > res.residual_px[~res.outliers].max()
    assert res.dof == 5 * 23 - 5
    # noise uniformly wider than the sigma (a codec) leaves every frame in
    wide = _level_detections(
        rig640, world, np.radians(np.arange(-180, 180, 15.0)), 0.09, np.random.default_rng(8)
    )
    wide = [replace(d, cov_n=np.eye(6) * (0.03 / rig640.camera.fx) ** 2) for d in wide]
    res = calibrate_zero_tilt(wide, rig640)
    assert not res.outliers.any() and res.sigma_scale > 2.0


def test_zero_tilt_needs_spread_yaws(rig640):
    dets = _level_detections(rig640, rig640, np.radians([0.0, 5.0, 10.0, 15.0]))
    with pytest.raises(InputFileError, match="spread over at least 60 deg"):
        calibrate_zero_tilt(dets, rig640)
    with pytest.raises(InputFileError, match="at least 3 frames"):
        calibrate_zero_tilt(dets[:2], rig640)


def test_circle_centre():
    a = np.linspace(0, 2 * np.pi, 9)[:-1]
    pts = np.column_stack([3.0 + 2.0 * np.cos(a), -1.0 + 2.0 * np.sin(a)])
    c, s = circle_centre(pts)
    np.testing.assert_allclose(c, [3.0, -1.0], atol=1e-12)


def test_zero_tilt_says_when_the_vertices_scatter_less_than_their_sigma(tmp_path):
    """Noise-free frames: the vertices scatter well under the edge model's sigma (its
    floor), significantly; the report says the sigma errs on the safe side, rather than
    calling it consistent, and keeps sigma_scale 1."""
    rig_p = CONFIGS / "triangle-320.toml"
    frames = tmp_path / "level"
    args = ["--out", frames, "--frames", 8, "--motion", "level", "--noise", 0]
    r = run("simulate", "--rig", rig_p, *args)
    assert r.exit_code == 0, r.output
    cal = tmp_path / "cal.toml"
    r = run("calibrate", "zero-tilt", str(frames), "--rig", str(rig_p), "--out", str(cal))
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if "sigma check" in x)
    hi = float(line.split("interval ")[1].split("-")[1].split(",")[0])
    assert hi < 1.0 and "narrower than it: the sigma is on the safe side" in line
    assert "sigma_scale = 1.0" in cal.read_text()


def test_calibrate_zero_tilt_cli_end_to_end(tmp_path):
    rig_p = CONFIGS / "triangle-320.toml"
    frames = tmp_path / "level"
    r = run("simulate", "--rig", rig_p, "--out", frames, "--frames", "8", "--motion",
            "level", "--target-offset-mm", "15", "0",
            "--camera-askew-deg", "0.5", "0.5")  # fmt: skip
    assert r.exit_code == 0, r.output
    # an earlier calibration (as a readout's would be) applied first
    pre = tmp_path / "pre.toml"
    pre.write_text("[platform]\nmax_tilt_deg = 8.0\n")
    cal = tmp_path / "cal.toml"
    r = run("calibrate", "zero-tilt", frames, "--rig", rig_p, "--calibration", pre, "--out", cal)
    assert r.exit_code == 0, r.output
    assert "target offset from the axis: dx +1" in r.output
    assert "sigma check: the vertices scatter" in r.output
    # how later runs apply it: after the calibration it was made on
    assert f"later runs take --calibration {pre} --calibration {cal}" in r.output
    text = cal.read_text()
    assert f"+ calibration {pre}, frames" in text.splitlines()[1]
    assert "[mount]" in text and "[target]" in text and "[zero_tilt]" in text
    # clean frames: the edge model's sigma holds, and the file says so
    assert "[detect]" in text and "sigma_scale = 1.0" in text
    r = run("batch", frames, "--rig", rig_p, "--calibration", pre, "--calibration", cal,
            "--truth", frames / "truth.csv")  # fmt: skip
    assert r.exit_code == 0
    # level frames read level after calibration
    import csv
    import io

    rows = list(csv.DictReader(io.StringIO(r.stdout)))
    assert all(abs(float(x["roll_deg"])) < 0.05 and abs(float(x["pitch_deg"])) < 0.05 for x in rows)
    # the calibration's own error is in every row's sigma: the file holds its covariance,
    # and the rows' tilt sigma is the detection's and the calibration's in quadrature
    from visvec.rig import load_rig

    calibrated = load_rig(rig_p, [pre, cal])
    C = calibrated.zero_tilt.offsets_cov
    assert C.shape == (4, 4) and np.all(np.diag(C) > 0)
    bare = tmp_path / "cal-bare.toml"
    bare.write_text("".join(x for x in text.splitlines(True) if not x.startswith("offsets_cov")))
    r = run("batch", frames, "--rig", rig_p, "--calibration", pre, "--calibration", bare)
    assert r.exit_code == 0
    for x, y in zip(rows, csv.DictReader(io.StringIO(r.stdout)), strict=True):
        R = quat_to_matrix(np.array([float(x[k]) for k in ("qw", "qx", "qy", "qz")]))
        body = calibrated.zero_tilt.cov_body(
            R, float(calibrated.target.vertices_mm[:, 2].mean()), float(calibrated.t_b[2])
        )
        added = sum(float(x[k]) ** 2 - float(y[k]) ** 2 for k in ("sigma_roll_deg",
                                                                  "sigma_pitch_deg"))  # fmt: skip
        # level: roll and pitch are the body's b1 and b2 tilts
        assert added == pytest.approx(np.degrees(np.sqrt(body[0, 0] + body[1, 1])) ** 2, rel=0.05)


def test_calibrate_zero_tilt_takes_one_recording_per_yaw(tmp_path):
    """Level frames recorded one folder per yaw stop (the platform is handled between
    them): the same calibration as from one folder of the same frames; a missing folder
    is refused before any work."""
    import shutil

    rig_p = CONFIGS / "triangle-320.toml"
    frames = tmp_path / "level"
    sim = ["simulate", "--rig", rig_p, "--out", frames, "--frames", 6, "--motion", "level"]
    assert run(*sim, "--target-offset-mm", 10, 5).exit_code == 0
    stops = [tmp_path / "yaw-a", tmp_path / "yaw-b", tmp_path / "yaw-c"]
    for k, png in enumerate(sorted(frames.glob("frame_*.png"))):
        stops[k // 2].mkdir(exist_ok=True)
        shutil.copy(png, stops[k // 2])
    one = run("calibrate", "zero-tilt", frames, "--rig", rig_p, "--out", tmp_path / "1.toml")
    assert one.exit_code == 0, one.output
    many = run("calibrate", "zero-tilt", *stops, "--rig", rig_p, "--out", tmp_path / "3.toml")
    assert many.exit_code == 0, many.output
    # the same offsets within a fifth of their sigma and the printed 0.01 mm (each
    # recording starts its region search afresh, one folder carries its threshold from
    # frame to frame: vertices from other starting corners differ by a fraction of their
    # sigma)
    pat = r"target offset from the axis: dx (\S+) \+- (\S+) mm, dy (\S+) \+- (\S+) mm"
    a = [float(x) for x in re.search(pat, one.output).groups()]
    b = [float(x) for x in re.search(pat, many.output).groups()]
    assert abs(a[0] - b[0]) <= 0.2 * a[1] + 0.01 and abs(a[2] - b[2]) <= 0.2 * a[3] + 0.01
    assert a[1] == b[1] and a[3] == b[3]
    assert f"{stops[2]}: frame_0005.png: yaw" in many.output
    assert f"frames {stops[0]} {stops[1]} {stops[2]} (6 used)" in (tmp_path / "3.toml").read_text()
    gone = run(
        "calibrate", "zero-tilt", *stops, tmp_path / "nope", "--rig", rig_p, "--out", tmp_path / "x"
    )
    assert gone.exit_code == 3 and "nope" in gone.output and "yaw-a" not in gone.output


@pytest.mark.parametrize("yaw_deg, tilt_deg", [(0.0, 0.0), (70.0, 2.0), (-135.0, -3.0)])
def test_a_calibration_s_error_reaches_the_rows_as_its_covariance_says(rig640, yaw_deg, tilt_deg):
    """The rig calibrated with its offsets off by dp (target dx, dy mm; camera tilt
    about b1, b2 deg): the triangle's attitude at R is then off by e, and cov_body(R) for
    offsets_cov = dp dp^T is e e^T: the mapping Rig.ZeroTilt.cov_body carries into every
    row's sigma, its signs and its turn with the platform's yaw included."""
    from visvec.estimate.triangle_full import solve_full
    from visvec.rig import ZeroTilt
    from visvec.rotations import logmap

    dp = np.array([0.8, -0.5, 0.02, 0.015])
    world = true_rig(rig640, (dp[0], dp[1]), (dp[2], dp[3]))
    R = euler_to_matrix(*np.radians([yaw_deg, tilt_deg, -0.5 * tilt_deg]))
    det = _level_detections(rig640, world, [0.0])[0]
    p = lab_to_camera(world, R, world.target.vertices_mm)
    xy = p[:, :2] / p[:, 2:3]
    det = Detection(Status.OK, points_px=rig640.camera.distort(xy), points_n=xy,
                    cov_n=det.cov_n)  # fmt: skip
    sol = solve_full(det, rig640, R)
    e = logmap(R.T @ sol.R_nb)  # the attitude error about the body axes (rad)
    C = ZeroTilt(offsets_cov=np.outer(dp, dp)).cov_body(
        sol.R_nb, float(rig640.target.vertices_mm[:, 2].mean()), float(rig640.t_b[2])
    )
    lam, vec = np.linalg.eigh(C)
    j = np.sqrt(lam[-1]) * vec[:, -1]  # +- J dp
    assert np.linalg.norm(e) > 1e-4  # at yaw 0 the two parts partly cancel
    # within 3 % of each part's size (the offset's is 1-2 % off: the triangle's extent)
    tol = 0.03 * (np.linalg.norm(dp[:2]) / 2150.0 + np.radians(np.linalg.norm(dp[2:])))
    assert min(np.linalg.norm(e - j), np.linalg.norm(e + j)) < tol
    # the offset's and the tilt's parts are of one size: a wrong sign between them
    # would fail the sum above
    assert 0.5 < np.radians(np.linalg.norm(dp[2:])) * 2150.0 / np.linalg.norm(dp[:2]) < 2.0
