"""LED markers: centroids, identification, the constrained solver, PnP baselines."""

from dataclasses import replace

import numpy as np
import pytest

from visvec.data import Frame, Status
from visvec.detect.markers import MarkerIdentifier
from visvec.detect.spots import find_spots
from visvec.estimate.markers import solve_markers
from visvec.estimate.pnp import PNP_FLAGS, solve_pnp
from visvec.geometry import markers_to_camera
from visvec.pipeline import MarkerPipeline
from visvec.rig import Pattern, load_rig
from visvec.rotations import euler_to_matrix, matrix_to_euler
from visvec.sim.markers import SpotScene, add_spot, render_markers
from visvec.sim.simulate import random_attitudes

from conftest import CONFIGS

ARCSEC = np.radians(1 / 3600)
# the requirement on simulated spots
CENTROID_BIAS_TOL_PX = 0.05


@pytest.fixture(scope="module")
def mrig():
    return load_rig(CONFIGS / "markers.toml")


def _angle(Ra, Rb):
    return np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))


def _exact(rig, R, sigma_px=0.0, rng=None, ids=None):
    ids = np.arange(len(rig.target.points_b)) if ids is None else ids
    p = markers_to_camera(rig, R, rig.target.points_b[ids])
    xy = p[:, :2] / p[:, 2:3]
    if sigma_px and rng is not None:
        xy = xy + rng.standard_normal(xy.shape) * sigma_px / rig.camera.fx
    return xy, ids


@pytest.mark.parametrize("psf", [0.7, 1.2, 2.0])
def test_wcom_centroid_bias_below_tolerance(psf):
    r = np.random.default_rng(1)
    errs = []
    for _ in range(200):
        img = np.zeros((40, 40))
        u, v = 20 + r.uniform(-0.5, 0.5, 2)
        add_spot(img, u, v, 2500.0, psf)
        img = np.clip(np.rint(img + 2 + r.standard_normal(img.shape)), 0, 255).astype(np.uint8)
        s = find_spots(img)
        assert len(s) == 1
        errs.append(s.centroids_px[0] - [u, v])
    e = np.array(errs)
    assert np.all(np.abs(e.mean(axis=0)) < CENTROID_BIAS_TOL_PX / 5)
    # the bias at any sub-pixel phase is below the tolerance: so is every single error
    assert np.abs(e).max() < CENTROID_BIAS_TOL_PX


def test_constrained_solver_exact_and_covariance(mrig, rng):
    R = euler_to_matrix(1.1, 0.2, -0.3)
    xy, ids = _exact(mrig, R)
    sol = solve_markers(xy, ids, mrig, 0.12)
    assert sol.status is Status.OK and _angle(sol.R_nb, R) < 0.01 * ARCSEC
    errs = []
    for _ in range(300):
        xy, ids = _exact(mrig, R, 0.12, rng)
        s = solve_markers(xy, ids, mrig, 0.12)
        errs.append(np.array(matrix_to_euler(s.R_nb)) - matrix_to_euler(R))
    emp = np.std(errs, axis=0)
    from visvec.rotations import euler_rates_from_body

    J = euler_rates_from_body(*matrix_to_euler(R))
    pred = np.sqrt(np.diag(J @ s.cov_b @ J.T))
    ratio = pred / emp
    assert np.all(ratio > 0.85) and np.all(ratio < 1.3), ratio


@pytest.mark.parametrize("start_error_rad", [1e-3, 5e-3, 3e-2, 0.2])
def test_equal_weight_solver_matches_the_general_gauss_newton(mrig, rng, start_error_rad):
    """The fast path for equal weights (closed-form 3x3 inverse, Jacobian kept while the
    rotation moves less than 1e-2 rad) lands where full Gauss-Newton does, to a tiny
    fraction of the 1-sigma, with the same covariance and chi-square, whether it starts
    a tracking step away or far off (when it must re-linearise)."""
    from visvec.estimate.rotation import fit_rotation
    from visvec.geometry import lab_camera_offset_c
    from visvec.rotations import expmap, logmap

    R_cb = mrig.R_nc.T @ euler_to_matrix(0.7, 0.17, -0.26)
    xy, ids = _exact(mrig, mrig.R_nc @ R_cb, 0.12, rng)
    X, t_c = mrig.target.points_b, lab_camera_offset_c(mrig)
    W = (mrig.camera.fx / 0.12) ** 2
    R0 = expmap(rng.standard_normal(3) * start_error_rad / np.sqrt(3)) @ R_cb
    fast = fit_rotation(t_c, X, xy, W, R0)
    full = fit_rotation(t_c, X, xy, W * np.eye(2 * len(X)), R0)
    assert fast.converged and full.converged
    z = logmap(fast.R @ full.R.T) / np.sqrt(np.diag(full.cov_d))
    assert np.abs(z).max() < 0.01, z
    # the covariance is the kept Jacobian's, taken within RELINEARISE_RAD = 1e-2 rad
    np.testing.assert_allclose(np.diag(fast.cov_d), np.diag(full.cov_d), rtol=1e-2)
    assert abs(fast.chi2 - full.chi2) < 1e-6 * full.chi2


def test_identification_lost_and_tracking(mrig):
    ident = MarkerIdentifier(mrig, 0.12)
    for k, e in enumerate([(2.5, 0.3, -0.2), (-1.0, -0.35, 0.1), (0.2, 0.0, 0.38)]):
        R = euler_to_matrix(*e)
        xy, ids = _exact(mrig, R)
        perm = np.random.default_rng(k).permutation(len(ids))
        res = ident.identify(xy[perm])
        assert res.R_nb is not None, res.reason
        np.testing.assert_array_equal(res.ids, ids[perm])
        # tracking from a nearby attitude
        res2 = ident.identify(xy[perm], euler_to_matrix(e[0] + 0.01, e[1], e[2] - 0.01))
        np.testing.assert_array_equal(res2.ids, ids[perm])


@pytest.mark.parametrize("six_dof", [False, True], ids=["constrained", "free translation"])
def test_a_spot_without_a_ray_is_no_marker(mrig, six_dof):
    """A spot beyond the lens model's field (nan, see CameraModel.undistort) among the
    markers, as `calibrate system` hands them over: no marker, the rest identified (it
    raised in the k-d tree before)."""
    R = euler_to_matrix(0.3, 0.1, -0.1)
    xy, ids = _exact(mrig, R)
    with_nan = np.vstack([xy[:5], [[np.nan, np.nan]], xy[5:]])
    res = MarkerIdentifier(mrig, 0.12, final_gate_px=10.0, six_dof=six_dof).identify(with_nan)
    assert res.R_nb is not None and _angle(res.R_nb, R) < np.radians(0.1)
    np.testing.assert_array_equal(res.ids, np.concatenate([ids[:5], [-1], ids[5:]]))


def test_symmetric_layout_is_refused_not_misidentified(mrig):
    # four identical boards turned 90 deg about the axis, no reference LED: every
    # quarter turn explains the spots equally well
    board = mrig.target.patterns[0].points_mm
    pats = tuple(
        Pattern(
            np.array([np.cos(a) * 100, np.sin(a) * 100, 150.0]), euler_to_matrix(a, 0, 0), board
        )
        for a in np.radians([0, 90, 180, 270])
    )
    rig = replace(mrig, target=replace(mrig.target, patterns=pats, reference_id=None))
    xy, _ = _exact(rig, euler_to_matrix(0.4, 0.05, 0.02))
    res = MarkerIdentifier(rig, 0.12).identify(xy)
    assert res.R_nb is None and res.reason == "ambiguous_layout"


@pytest.mark.parametrize(
    "euler_deg", [(156.72, -16.83, -0.64), (-40.73, -11.95, -10.88), (-97.25, -12.65, -8.76)]
)
def test_the_half_turn_of_a_tilted_layout_is_told_apart_by_its_reference_led(mrig, euler_deg):
    """The example layout is symmetric under a half turn but for its reference LED: at a
    tilt of 12-17 deg the half turn tilted the other way puts all 20 board LEDs on spots
    too, leaving the reference LED's spot unexplained and its own reference LED without
    one. It was refused as ambiguous (20 matches against 21: 5 % of cold frames within
    22 deg, forever for a platform resting tilted); two faults more than an exact match,
    it no longer is. Without the reference LED's spot both explanations leave one fault:
    ambiguous, as it is."""
    R = euler_to_matrix(*np.radians(euler_deg))
    xy, ids = _exact(mrig, R)
    perm = np.random.default_rng(1).permutation(len(ids))
    ident = MarkerIdentifier(mrig, 0.12)
    res = ident.identify(xy[perm])
    assert res.R_nb is not None, res.reason
    np.testing.assert_array_equal(res.ids, ids[perm])
    assert _angle(res.R_nb, R) < np.radians(0.01)
    ref = mrig.target.reference_id
    keep = perm[ids[perm] != ref]
    res = ident.identify(xy[keep])
    assert res.R_nb is None and res.reason == "ambiguous_layout"


@pytest.mark.parametrize(
    "euler_deg",
    [(38.39, 7.89, 1.5), (-116.76, 12.49, 1.43), (-135.26, 5.87, 5.06), (79.74, 0.87, -6.52)],
)
def test_a_reference_led_out_of_view_leaves_a_symmetric_layout_ambiguous(mrig, euler_deg):
    """The reference LED hung where the camera never sees it: the four boards are
    symmetric under a half turn, so the spots fit two attitudes equally. The reference
    scheme's yaw windows, meaningless without it, found one of them alone and gave it
    (6 of 30 random attitudes, 4 of them a half turn off; 3 of these 4); now only the
    whole grid is trusted then, and it finds both."""
    pats = list(mrig.target.patterns)
    pats[-1] = replace(pats[-1], position_mm=np.array([-80.0, -1200.0, 150.0]))
    rig = replace(mrig, target=replace(mrig.target, patterns=tuple(pats)))
    ref = rig.target.reference_id
    R = euler_to_matrix(*np.radians(euler_deg))
    xy, _ = _exact(rig, R, ids=np.delete(np.arange(len(rig.target.points_b)), ref))
    res = MarkerIdentifier(rig, 0.12).identify(xy)
    assert res.R_nb is None and res.reason == "ambiguous_layout"


def test_pipeline_rendered_frames_with_reflection_and_hidden_led(mrig):
    pipe = MarkerPipeline(mrig)
    R = euler_to_matrix(-0.7, 0.15, 0.1)
    img = render_markers(mrig, R, SpotScene(reflections=2, hidden=(3,)), rng=5)
    row = pipe.process(Frame(0, 0.0, img))
    assert row.ok, row.warnings
    assert row.n_points == 20
    assert "missing_markers" in row.warnings and "extra_spots" in row.warnings
    err = np.abs(row.euler_deg - np.degrees(matrix_to_euler(R)))
    assert np.all(err < 3 * row.sigma_deg + 1e-4)


def test_a_spot_beyond_the_lens_models_field_is_left_out_and_named(mrig):
    """A lens model (k1 = -1.36) turning back 1148 px out, short of the 1280 px corners:
    a reflection in a corner, beyond that fold, has no ray; it is left out with
    ``beyond_lens_model``, the markers inside are solved as before."""
    rig = replace(mrig, camera=replace(mrig.camera, dist=np.array([-1.36, 0.0, 0.0, 0.0, 0.0])))
    assert rig.camera.field_radius_px < 1150.0 < rig.camera.corner_radius_px
    R = euler_to_matrix(-0.7, 0.15, 0.1)
    sc = SpotScene()
    img = render_markers(rig, R, sc, rng=5).astype(float)
    add_spot(img, 40.0, 30.0, sc.flux, sc.psf_sigma_px)
    row = MarkerPipeline(rig).process(Frame(0, 0.0, np.clip(img, 0, 255).astype(np.uint8)))
    assert row.ok and row.n_points == len(rig.target.points_b), row.warnings
    assert "beyond_lens_model" in row.warnings and "extra_spots" not in row.warnings
    err = np.abs(row.euler_deg - np.degrees(matrix_to_euler(R)))
    assert np.all(err < 3 * row.sigma_deg + 1e-4)


@pytest.mark.parametrize(
    ("euler_deg", "scene", "seed"),
    [
        ((-63.13, -4.13, -7.82), SpotScene(reflections=2), 199),
        ((2.51, -0.27, 12.71), SpotScene(hidden=(5, 0)), 45),
        ((44.56, 4.4, -18.02), SpotScene(reflections=3), 219),
    ],
    ids=["2 reflections", "2 LEDs hidden", "3 reflections"],
)
def test_stray_spots_or_hidden_leds_never_give_the_half_turn(mrig, euler_deg, scene, seed):
    """Cold frames where the reference scheme's yaw windows (about the three spots
    farthest out) held only the half-turned layout: it matched all but the reference LED
    and, nothing else found, was an ok row 180 deg off in yaw and 8-36 deg in tilt. The
    whole grid is now searched unless an explanation leaves no fault."""
    R = euler_to_matrix(*np.radians(euler_deg))
    row = MarkerPipeline(mrig).process(Frame(0, 0.0, render_markers(mrig, R, scene, seed)))
    assert row.ok, row.warnings
    err = row.euler_deg - np.asarray(euler_deg)
    err[0] = (err[0] + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(err) < 3 * row.sigma_deg + 1e-4), err


@pytest.mark.slow  # 18 s on a slow host
def test_the_rows_sigma_is_learned_from_the_spots_scatter_and_follows_it(mrig):
    """The shipped rig's centroid_sigma_px (0.12) is a guess: the simulator's LEDs scatter
    about 0.012 px. Taken as it is, every row's sigma was about 9x its error (error over
    sigma RMS 0.1); learned from the fits, the noise narrows to the spots' own and the
    rows' error over sigma has an RMS near 1 on every axis. Then the frames get noisier
    (read noise 1 -> 8 grey levels: a higher gain, a dimmer LED). Refused by the learned
    noise they were, 27 of 30, and the noise never learned it; refused only by what the
    rig's noise allows (or the learned, when wider), they are ok and their sigma
    follows."""
    eul = random_attitudes(75, mrig.max_tilt_deg / np.sqrt(2.0), np.random.default_rng(3), "sweep")
    pipe = MarkerPipeline(mrig)
    z = {False: [], True: []}
    narrow = None
    for k, e in enumerate(eul):
        R = euler_to_matrix(*e)
        noisy = k >= 60
        scene = SpotScene(noise_sigma=8.0) if noisy else SpotScene()
        row = pipe.process(Frame(k, k / mrig.fps, render_markers(mrig, R, scene, 100 + k)))
        assert row.ok, (k, row.warnings)
        if k == 59:
            narrow = pipe.sigma_px
        if k >= 20:
            err = row.euler_deg - np.degrees(matrix_to_euler(R))
            err[0] = (err[0] + 180.0) % 360.0 - 180.0
            z[noisy].append(err / row.sigma_deg)
    assert narrow < 0.03 and pipe.sigma_px > 1.2 * narrow, (narrow, pipe.sigma_px)
    clean = np.sqrt(np.mean(np.square(z[False]), axis=0))
    assert np.all((clean > 0.5) & (clean < 1.5)), clean
    assert np.abs(z[False]).max() < 5.0
    rms = np.sqrt(np.mean(np.square(z[True]), axis=0))
    assert np.all(rms < 1.5), rms


def test_pipeline_refuses_frames_without_enough_markers(mrig):
    pipe = MarkerPipeline(mrig)
    img = render_markers(mrig, np.eye(3), SpotScene(hidden=tuple(range(18))), rng=1)
    row = pipe.process(Frame(0, 0.0, img))
    assert not row.ok
    dark = np.full((1536, 2048), 2, np.uint8)
    row = pipe.process(Frame(1, 0.0, dark))
    assert row.status is Status.NO_TARGET


@pytest.mark.parametrize("method", list(PNP_FLAGS))
def test_pnp_baselines_agree_on_exact_points(mrig, method):
    R = euler_to_matrix(0.8, 0.1, -0.12)
    xy, ids = _exact(mrig, R)
    uv = mrig.camera.distort(xy)
    sol = solve_pnp(uv, ids, mrig, method, 0.12)
    assert sol.status is Status.OK
    assert _angle(sol.R_nb, R) < 5 * ARCSEC
    assert np.all(np.isfinite(sol.cov_b))


def test_ippe_takes_a_calibrated_layout_slightly_off_its_plane(mrig, rng):
    """A calibrated layout carries each LED's estimated offset, a few hundredths of a mm
    off the boards' plane: IPPE (planar only) still solves, from the plane's points."""
    R = euler_to_matrix(0.8, 0.1, -0.12)
    xy, ids = _exact(mrig, R)
    X = mrig.target.points_b + rng.standard_normal((len(ids), 3)) * 0.03
    layout = replace(
        mrig, target=replace(mrig.target, patterns=(Pattern(np.zeros(3), np.eye(3), X),))
    )
    sol = solve_pnp(mrig.camera.distort(xy), ids, layout, "pnp-ippe", 0.12)
    assert sol.status is Status.OK
    # within IPPE's own sensitivity to the offsets (the 0.05 mm benchmark: 210 arcsec
    # 1-sigma in tilt), not a failed or flipped solution (degrees off)
    assert _angle(sol.R_nb, R) < np.radians(0.2)


def test_markers_cli_batch(tmp_path):
    from click.testing import CliRunner

    from visvec.cli.main import cli

    rig = str(CONFIGS / "markers.toml")
    out = tmp_path / "sim"
    r = CliRunner().invoke(
        cli,
        [
            "simulate",
            "--rig",
            rig,
            "--out",
            str(out),
            "--frames",
            "3",
            "--motion",
            "sweep",
            "--max-tilt-deg",
            "15",
        ],
    )
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(
        cli,
        [
            "batch",
            str(out),
            "--rig",
            rig,
            "--truth",
            str(out / "truth.csv"),
            "--method",
            "pnp-sqpnp",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "frames 3, ok 3" in r.output
    r = CliRunner().invoke(cli, ["batch", str(out), "--rig", rig, "--method", "paper"])
    assert r.exit_code == 2 and "expected one of" in r.output
