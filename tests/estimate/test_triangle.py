"""The full and paper estimators on exact and noisy vertices."""

from dataclasses import replace

import numpy as np
import pytest

from visvec._kernels import jit
from visvec._kernels import readout as KO
from visvec._kernels import rotation as KR
from visvec.data import Detection, Status
from visvec.estimate.rotation import (
    initial_rotation,
    residuals_and_jacobian,
    residuals_and_jacobian_shift,
    shift_jacobian,
)
from visvec.estimate.triangle_full import HeightTrack, solve_full
from visvec.estimate.triangle_paper import solve_paper
from visvec.geometry import camera_offset_c, lab_to_camera
from visvec.rotations import (
    euler_rates_from_body,
    euler_to_matrix,
    expmap,
    logmap,
    matrix_to_euler,
)

ARCSEC = np.radians(1.0 / 3600.0)
EXACT_TOL = 0.01 * ARCSEC


def _detection(rig, R_nb, sigma_px=0.05, rng=None):
    p_c = lab_to_camera(rig, R_nb, rig.target.vertices_mm)
    xy = p_c[:, :2] / p_c[:, 2:3]
    if rng is not None:
        xy = xy + rng.standard_normal(xy.shape) * sigma_px / rig.camera.fx
    cov = np.eye(6) * (sigma_px / rig.camera.fx) ** 2
    return Detection(Status.OK, points_px=rig.camera.distort(xy), points_n=xy, cov_n=cov)


def _angle(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return np.arccos(np.clip(c, -1, 1))


def test_jacobian_matches_central_differences(rig640):
    R_cn = rig640.R_bc.T @ euler_to_matrix(0.4, 0.05, -0.07).T
    t_c = camera_offset_c(rig640)
    xy = np.zeros((3, 2))
    _, J = residuals_and_jacobian(R_cn, t_c, rig640.target.vertices_mm, xy)
    h = 1e-7
    num = np.zeros_like(J)
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        rp, _ = residuals_and_jacobian(expmap(d) @ R_cn, t_c, rig640.target.vertices_mm, xy)
        rm, _ = residuals_and_jacobian(expmap(-d) @ R_cn, t_c, rig640.target.vertices_mm, xy)
        num[:, k] = (rp - rm) / (2 * h)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-10)


def test_height_jacobian_matches_central_differences(rig640):
    R_cn = rig640.R_bc.T @ euler_to_matrix(0.4, 0.05, -0.07).T
    t_c = camera_offset_c(rig640)
    X, up, xy = rig640.target.vertices_mm, np.array([0.0, 0.0, 1.0]), np.zeros((3, 2))
    h = 1e-3  # mm
    rp, _ = residuals_and_jacobian(R_cn, t_c, X + h * up, xy)
    rm, _ = residuals_and_jacobian(R_cn, t_c, X - h * up, xy)
    np.testing.assert_allclose(
        shift_jacobian(R_cn, t_c, X, up), (rp - rm) / (2 * h), rtol=1e-6, atol=1e-13
    )


def test_joint_jacobian_is_the_rotation_and_height_jacobians(rig640, rng):
    """The Gauss-Newton's one-pass (2N, 4) Jacobian equals the two tested above."""
    R_cn = rig640.R_bc.T @ euler_to_matrix(2.1, -0.06, 0.08).T
    t_c = camera_offset_c(rig640)
    X, up = rig640.target.vertices_mm + [0.0, 0.0, 12.0], np.array([0.0, 0.0, 1.0])
    xy = rng.normal(size=(3, 2)) * 0.1
    r3, J3 = residuals_and_jacobian(R_cn, t_c, X, xy)
    r, J = residuals_and_jacobian_shift(R_cn, t_c, X, xy, up)
    assert J.shape == (6, 4)
    np.testing.assert_allclose(r, r3, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(J[:, :3], J3, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(J[:, 3], shift_jacobian(R_cn, t_c, X, up), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("height_mm", [-25.0, 6.0, 40.0])
def test_full_takes_a_wrong_target_height_in_its_stride(rig640, rng, height_mm):
    """The ceiling measured wrong by a few mm (0.3 % of the distance) was enough for the
    chi-square test to refuse every frame while the height was held fixed; with the
    height estimated under its prior (20 mm) the attitude is ok and within its sigma."""
    world = replace(
        rig640,
        target=replace(
            rig640.target, vertices_mm=rig640.target.vertices_mm + [0.0, 0.0, height_mm]
        ),
    )
    fixed = replace(rig640, target=replace(rig640.target, height_sigma_mm=0.0))
    z = []
    for _ in range(30):
        R = euler_to_matrix(rng.uniform(-np.pi, np.pi), *rng.uniform(-0.08, 0.08, 2))
        det = _detection(world, R, 0.03, rng)
        if abs(height_mm) > 5:
            sol = solve_full(det, fixed)
            assert sol.status is Status.REJECTED and "inconsistent_geometry" in sol.warnings
        sol = solve_full(det, rig640)
        assert sol.status is Status.OK
        e = np.array(matrix_to_euler(sol.R_nb)) - np.array(matrix_to_euler(R))
        e[0] = (e[0] + np.pi) % (2 * np.pi) - np.pi
        J = euler_rates_from_body(*matrix_to_euler(sol.R_nb))
        z.append(e / np.sqrt(np.diag(J @ sol.cov_b @ J.T)))
    assert np.abs(z).max() < 4.0
    assert 0.6 < np.sqrt(np.mean(np.square(z))) < 1.4


def test_a_height_far_beyond_its_prior_is_refused(rig640, rng):
    """A triangle 150 mm (7.5 prior sigmas) higher than the rig says is not the rig's
    target as described: refused, while 60 mm (3 sigmas) passes."""
    R = euler_to_matrix(0.7, 0.03, -0.02)
    for dz, ok in ((60.0, True), (150.0, False)):
        v = rig640.target.vertices_mm + [0.0, 0.0, dz]
        world = replace(rig640, target=replace(rig640.target, vertices_mm=v))
        sol = solve_full(_detection(world, R, 0.03, rng), rig640)
        assert (sol.status is Status.OK) is ok, (dz, sol.warnings)
        if not ok:
            assert "inconsistent_geometry" in sol.warnings


def test_a_tight_height_prior_holds_the_height(rig640, rng):
    """A lab that measured its height (prior 0.5 mm, under HELD_HEIGHT_SIGMA_MM): the
    prior's term is part of a 3-dof chi-square, so a height 0.3 mm off passes and one
    3 mm off (6 prior sigmas) is refused, where the default 20 mm prior takes it."""
    R = euler_to_matrix(-0.9, 0.02, 0.04)
    tight = replace(rig640, target=replace(rig640.target, height_sigma_mm=0.5))
    for dz, ok in ((0.3, True), (3.0, False)):
        v = rig640.target.vertices_mm + [0.0, 0.0, dz]
        world = replace(rig640, target=replace(rig640.target, vertices_mm=v))
        det = _detection(world, R, 0.02, rng)
        sol = solve_full(det, tight)
        assert (sol.status is Status.OK) is ok, (dz, sol.chi2)
        assert solve_full(det, rig640).status is Status.OK
        assert abs(solve_full(det, rig640).height_mm - dz) < 1.0


def test_the_height_known_over_frames_gives_an_off_axis_camera_its_tilts_back(rig640, rng):
    """A camera 250 mm off the rotation axis sees the target away from the point about
    which a height change scales the image: a frame's own height costs its tilts 1.4-1.7x.
    With the height carried from frame to frame (HeightTrack) the tilt sigma falls back
    near that of a known height, and the errors stay within it."""
    rig = replace(rig640, mount=replace(rig640.mount, position_mm=np.array([250.0, 0, 150])))
    held = replace(rig, target=replace(rig.target, height_sigma_mm=0.0))
    track = HeightTrack(rig.target.height_sigma_mm)
    z = []
    for k in range(40):
        R = euler_to_matrix(rng.uniform(-np.pi, np.pi), *rng.uniform(-0.08, 0.08, 2))
        det = _detection(rig, R, 0.03, rng)
        alone, sol = solve_full(det, rig), solve_full(det, rig, None, track.prior())
        assert sol.status is Status.OK and sol.dof == (3 if k else 2)
        track.update(sol)
        e = np.array(matrix_to_euler(sol.R_nb)) - np.array(matrix_to_euler(R))
        e[0] = (e[0] + np.pi) % (2 * np.pi) - np.pi
        J = euler_rates_from_body(*matrix_to_euler(sol.R_nb))
        z.append(e / np.sqrt(np.diag(J @ sol.cov_b @ J.T)))
    # the tilt about b2 (the camera is off the axis along b1): 1.3x with the frame's own
    # height at this offset, against a known one
    tilt = [np.sqrt(s.cov_b[1, 1]) for s in (alone, sol, solve_full(det, held))]
    assert tilt[1] < 0.85 * tilt[0] and tilt[1] < 1.05 * tilt[2], tilt
    assert abs(track.mean_mm) < 4 * np.sqrt(track.var_mm2) and np.sqrt(track.var_mm2) < 0.2
    assert np.abs(z).max() < 4.0


@pytest.mark.slow  # 6 s: the default run stays under 5 minutes
def test_the_running_height_learns_the_lab_and_restarts_when_it_changes(rig640):
    """Frames of a lab whose ceiling is 5 mm higher than the rig file says: the pipeline's
    height track finds it and the run's closing note says so. When the lab changes under
    it (7 mm more: a lens refocused), the frames that the track's prior would refuse are
    judged against the rig's prior, stay ok, and restart the track."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline
    from visvec.sim.render import render_frame
    from visvec.sim.scene import Scene
    from visvec.sim.simulate import true_rig

    pipe = TrianglePipeline(rig640)
    k = 0
    for height_mm in (5.0, 12.0):
        world = true_rig(rig640, height_offset_mm=height_mm)
        for j in range(12):
            R = euler_to_matrix(np.radians(20 + 0.3 * k), np.radians(1 - 0.1 * j), 0.02)
            prior = pipe.height.prior()
            row = pipe.process(Frame(k, k / 30, render_frame(world, R, Scene(), rng=k)))
            assert row.ok, (height_mm, j, row.warnings)
            if height_mm == 12.0 and j == 0:
                # the track's prior alone would have refused it: the fallback was used
                refused = solve_full(pipe.last_detection, rig640, None, prior)
                assert refused.status is Status.REJECTED
                assert pipe.height.n == 1
            k += 1
        h, sigma = pipe.height.mean_mm, np.sqrt(pipe.height.var_mm2)
        assert abs(h - height_mm) < 4 * sigma and sigma < 0.3, (h, sigma)
        note = pipe.notes()
        assert len(note) == 1 and f"{h:.2f} +- {sigma:.2f} mm higher" in note[0]
    # a lab as the rig file says has nothing to note
    pipe = TrianglePipeline(rig640)
    for j in range(12):
        R = euler_to_matrix(0.3, 0.01 * j, 0.0)
        assert pipe.process(Frame(j, j / 30, render_frame(rig640, R, Scene(), rng=j))).ok
    assert pipe.notes() == []


def test_the_residuals_measure_a_shear_no_attitude_explains(rig640):
    """Vertices seen shifted by k g, for a rolling shutter's pattern g: the fit takes up
    what an attitude and a height can, and VertexResidual.explain recovers k from the
    rest (the readout evidence of an undeclared rolling shutter); a frame with no shear
    gives 0."""
    from visvec.shutter import shutter_matrix

    R = euler_to_matrix(0.6, 0.04, -0.03)
    exact = _detection(rig640, R)
    xy, rows = exact.points_n, exact.points_px[:, 1]
    g = -shutter_matrix(xy, rows, rig640.camera, 1000.0) @ np.radians([2.0, -1.0, 20.0])
    for k in (0.0, 0.025):
        det = replace(exact, points_n=xy + k * g.reshape(3, 2))
        a, b = solve_full(det, rig640).residual.explain(g)
        assert abs(a / b - k) < 1e-3 * 0.025, (k, a / b)
        assert 1.0 / np.sqrt(b) < 0.01  # one frame pins k to 10 ms at 0.05 px


@pytest.mark.parametrize("compiled", [False, True])
def test_readout_evidence_update_is_the_free_fits_explain(rig640, compiled, monkeypatch, request):
    """ReadoutEvidence.add, written for speed (and compiled with the fast extra),
    accumulates what the frame's residual freed of its prior (VertexResidual.
    unconstrained) explains of the design [-A omega of a 1 s readout,
    model_error_design] (VertexResidual.explain), and that free residual's chi-square:
    the same numbers (1e-12), with a lever arm, a correction already applied, and a
    height carried as a prior; the compiled kernel gives what its Python source does
    (to rounding: 1e-12)."""
    from visvec.estimate.shear import ReadoutEvidence, model_error_design
    from visvec.shutter import shutter_shift

    if compiled and not jit.AVAILABLE:
        pytest.skip("Numba (the fast extra)")
    if not compiled:  # the numpy path, where the kernels are on too
        path = jit.numpy_path()
        path.__enter__()
        request.addfinalizer(lambda: path.__exit__(None, None, None))
    if compiled:  # its Python source (py_func, which coverage follows), checked below
        kernel = KO.readout_frame
        monkeypatch.setattr(KO, "readout_frame", kernel.py_func)

    cam = rig640.camera
    rng = np.random.default_rng(5)
    ev = ReadoutEvidence.for_camera(cam, 30.0)
    info, rhs, chi2, added = np.zeros((10, 10)), np.zeros(10), 0.0, []
    for k in range(6):
        exact = _detection(rig640, euler_to_matrix(*rng.normal(0.0, 0.1, 3)))
        seen = exact.points_n + rng.normal(0.0, 0.3 / cam.fx, (3, 2))
        residual = solve_full(replace(exact, points_n=seen), rig640, height_prior=(1.0, 2.0))
        xy, rows = exact.points_n, exact.points_px[:, 1]
        omega, lever = rng.normal(0.0, 0.3, 3), rng.normal(0.0, 0.1, 3)
        design = np.column_stack(
            [-shutter_shift(xy, rows, cam, 1000.0, omega, lever), model_error_design(xy, cam)]
        )
        applied = 5.0 * k
        added.append((residual.residual, xy, rows, cam, omega, lever, applied))
        ev.add(*added[-1])
        free = residual.residual.unconstrained()
        a, b = free.explain(design)
        info += b
        ka = applied / 1000.0
        rhs += a + b[:, 0] * ka
        chi2 += free.r @ free.W @ free.r + 2.0 * ka * a[0] + ka**2 * b[0, 0]
    scale = np.abs(info).max()
    np.testing.assert_allclose(ev.info, info, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(ev.rhs, rhs, rtol=1e-9, atol=1e-12 * np.abs(rhs).max())
    assert ev.chi2 == pytest.approx(chi2, rel=1e-9) and ev.n == 6 and ev.dof == 6 * 2
    if compiled:  # and the compiled kernel gives what its source does
        monkeypatch.setattr(KO, "readout_frame", kernel)
        again = ReadoutEvidence.for_camera(cam, 30.0)
        for args in added:
            again.add(*args)
        np.testing.assert_allclose(again.info, ev.info, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(again.rhs, ev.rhs, rtol=1e-12, atol=1e-12 * np.abs(rhs).max())
        assert again.chi2 == pytest.approx(ev.chi2, rel=1e-12)
        # the posterior (ReadoutEvidence._posterior): compiled, its source, numpy
        got = []
        for solve in (KO.readout_solve, KO.readout_solve.py_func):
            with monkeypatch.context() as mp:
                mp.setattr(KO, "readout_solve", solve)
                ev._cached = None
                got.append(ev._posterior())
        with jit.numpy_path():
            ev._cached = None
            got.append(ev._posterior())
        for cov, theta, fit in got[1:]:
            np.testing.assert_allclose(cov, got[0][0], rtol=1e-9)
            np.testing.assert_allclose(theta, got[0][1], rtol=1e-9)
            assert fit == pytest.approx(got[0][2], rel=1e-9)


def test_readout_evidence_counts_what_a_correction_took_out(rig640):
    """Frames already taken out with a running readout estimate k0 show only k - k0 in
    their residuals; ReadoutEvidence adds k0 back, so its estimate stays the camera's
    whatever the pipeline applied. Over a turn out and back, a model error fixed in the
    triangle's frame (0.1 px, the target off where the rig file puts it) is told apart
    from a shear: alone it reads as no shutter. On a one-way turn at a steady rate a
    principal point 4 px off shears the residuals as a 15 ms shutter would: estimated
    beside the readout, it reads as none. An aspect error is estimated too, also from
    frames at rest (which measure no readout); vertices scattered wider than their sigma
    leave the residuals unexplained: not believed."""
    from visvec.estimate.shear import MAX_FIT_CHI2_DOF, ReadoutEvidence, _triangle_frame
    from visvec.shutter import shutter_shift

    cam = rig640.camera
    rate = np.radians([2.0, -1.0, 20.0])

    def frames(yaws_deg, rates):
        out = []
        for yaw, omega in zip(np.radians(yaws_deg), rates, strict=True):
            exact = _detection(rig640, euler_to_matrix(yaw, 0.04, -0.03))
            xy, rows = exact.points_n, exact.points_px[:, 1]
            g = -shutter_shift(xy, rows, cam, 1000.0, omega)  # a 1 s readout
            out.append((exact, xy, rows, omega, g))
        return out

    def evidence(frames, k, applied_ms=0.0, static=None, cx_px=0.0, aspect=0.0):
        ev = ReadoutEvidence.for_camera(cam, 30.0)
        for exact, xy, rows, omega, g in frames:
            seen = exact.points_n + ((k - applied_ms / 1000.0) * g).reshape(3, 2)
            if static is not None:
                seen = seen + (_triangle_frame(xy) @ static).reshape(3, 2)
            seen = seen + [cx_px / cam.fx, 0.0]
            seen[:, 1] *= 1.0 + aspect
            residual = solve_full(replace(exact, points_n=seen), rig640).residual
            ev.add(residual, xy, rows, cam, omega, None, applied_ms)
        return ev

    out = np.arange(0.0, 60.0, 3.0)
    back_and_forth = frames(np.r_[out, out[::-1]], [rate] * len(out) + [-rate] * len(out))
    # the worst static error: the first frame's shear pattern, 0.1 px at most
    _, xy, _, _, g = back_and_forth[0]
    static = _triangle_frame(xy).T @ g
    static *= 0.1 / cam.fx / np.abs(static).max()
    for k, applied_ms, m in (
        (0.025, 0.0, 1.0),
        (0.025, 10.0, 1.0),
        (0.025, 40.0, 0.0),
        (0.0, 0.0, 1.0),
    ):
        ev = evidence(back_and_forth, k, applied_ms, m * static)
        est, sigma = ev.readout_ms()
        assert abs(est - 1000.0 * k) < 2.0 * sigma, (k, applied_ms, m, est, sigma)
        assert ev.suspected() == (k > 0), (k, est, sigma)
        assert ev.fit_chi2_per_dof() < 0.1  # noise-free: the model explains them
    one_way = frames(np.arange(0.0, 120.0, 3.0), [rate] * 40)
    ev = evidence(one_way, 0.0, cx_px=4.0)
    est, sigma = ev.readout_ms()
    assert not ev.suspected() and abs(est) < 3.0 * sigma, (est, sigma)
    (cx, cy, _), (s_cx, s_cy, _) = ev.camera_errors()
    assert abs(cx - 4.0) < 3.0 * s_cx and abs(cy) < 3.0 * s_cy, (cx, s_cx, cy, s_cy)
    # the aspect is one of the model errors: estimated, the shear still shows
    ev = evidence(back_and_forth, 0.025, aspect=0.015)
    assert ev.suspected() and ev.fit_chi2_per_dof() < 0.5, ev.readout_ms()
    (_, _, e), (_, _, s) = ev.camera_errors()
    assert abs(e - 0.015) < max(3.0 * s, 1e-4), (e, s)
    # frames at rest: no readout to measure (no rate), the camera's aspect still is
    still = frames(out, [np.zeros(3)] * len(out))
    ev = evidence(still, 0.0, aspect=0.004)
    assert np.isnan(ev.readout_ms()[0]) and not ev.suspected()
    (_, _, e), (_, _, s) = ev.camera_errors()
    assert abs(e - 0.004) < max(3.0 * s, 1e-4) and np.isfinite(ev.fit_chi2_per_dof()), (e, s)
    # vertices scattered 4x wider than their sigma: no model explains that
    rng = np.random.default_rng(3)
    noisy = [
        (replace(d, points_n=d.points_n + rng.normal(0, 0.2 / cam.fx, (3, 2))), *rest)
        for d, *rest in back_and_forth
    ]
    ev = evidence(noisy, 0.025)
    assert ev.fit_chi2_per_dof() > MAX_FIT_CHI2_DOF and not ev.suspected(), ev.readout_ms()


def test_a_residual_without_its_prior_keeps_only_what_no_parameter_explains(rig640):
    """Exact vertices fitted under a tight height prior 1.5 mm off (the height carried
    from earlier frames, lagging): the prior pulls the fit and its pull is left in the
    residuals; taken without the prior (first order), they vanish, and the fit's
    parameters then take up a height-like pattern entirely."""
    det = _detection(rig640, euler_to_matrix(0.7, 0.04, -0.03))
    held = solve_full(det, rig640, height_prior=(1.5, 0.05)).residual
    pull = np.abs(held.r).max() * rig640.camera.fx
    assert pull > 0.05, pull  # px: the prior's pull is there
    free = held.unconstrained()
    assert np.abs(free.r).max() * rig640.camera.fx < 1e-3 * pull
    # a change of height is a parameter: nothing of it is left to explain
    height_like = held.J[:, -1]
    _, b = free.explain(height_like)
    assert abs(b) < 1e-9 * float(height_like @ held.W @ height_like)


@pytest.mark.parametrize("yaw_deg", [-179.0, -90.0, 0.0, 45.0, 180.0])
def test_closed_form_start_is_exact_on_exact_points(rig640, yaw_deg):
    R = euler_to_matrix(np.radians(yaw_deg), np.radians(4.0), np.radians(-6.0))
    det = _detection(rig640, R)
    R_cn = initial_rotation(camera_offset_c(rig640), rig640.target.vertices_mm, det.points_n)
    assert _angle(R_cn.T @ rig640.R_bc.T, R) < EXACT_TOL


def test_closed_form_start_compiled_or_not():
    """The closed-form start (visvec._kernels.rotation, one implementation for both
    paths): from exact bearings of 3 to 8 points beyond the centre of rotation, seen
    from near it (a ceiling target: one branch in front) it gives the true rotation
    (1e-9); of points around the centre seen from afar (markers: both branches in
    front) a start (a rough one where a point needs its far root: Gauss-Newton
    finishes); none where no depth is in front; and on
    noisy bearings the compiled kernel gives what its Python source does (1e-12)."""
    from visvec.estimate.rotation import initial_rotation

    rng = np.random.default_rng(1)
    kinds = {"beyond": 0, "around": 0}
    for k in range(400):
        n = int(rng.integers(3, 9))
        beyond = k % 2 == 0
        if beyond:
            t_c = rng.normal(0.0, 50.0, 3)
            X = rng.normal(0.0, 400.0, (n, 3)) + [0.0, 0.0, 2000.0]
        else:
            t_c = rng.normal(0.0, 100.0, 3) + [0.0, 0.0, 3000.0]
            X = rng.normal(0.0, 150.0, (n, 3))
        R_true = euler_to_matrix(*rng.normal(0.0, 0.3, 3))
        p = X @ R_true.T + t_c
        assert p[:, 2].min() > 0
        xy = p[:, :2] / p[:, 2:3]
        R = initial_rotation(t_c, X, xy)
        assert R is not None
        if beyond:
            np.testing.assert_allclose(R, R_true, rtol=0, atol=1e-9)
        kinds["beyond" if beyond else "around"] += 1
        if jit.AVAILABLE and k < 60:
            noisy = xy + rng.normal(0.0, 1e-2, xy.shape)
            got = [f(t_c, X, noisy) for f in (KR.closed_form, KR._closed_form)]
            assert got[0][0] == got[1][0]
            assert np.abs(got[0][1] - got[1][1]).max() < 1e-12
    assert min(kinds.values()) == 200, kinds
    # no depth in front: points within 100 mm of a centre of rotation 5 m behind the
    # camera cannot lie on its bearings
    X = np.array([[0.0, 0.0, 100.0], [60.0, 0.0, 80.0], [0.0, 60.0, 80.0]])
    xy = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]])
    assert initial_rotation(np.array([0.0, 0.0, -5000.0]), X, xy) is None


def test_full_recovers_attitude_with_lever_arm_and_tilted_mount(rig640):
    rig = replace(
        rig640,
        mount=replace(
            rig640.mount,
            position_mm=np.array([80.0, -40.0, 300.0]),
            rotation=euler_to_matrix(0.3, 0.05, 0.02),
        ),
    )
    for e in ([1.0, 0.1, -0.12], [-2.5, -0.15, 0.0], [3.1, 0.0, 0.17]):
        R = euler_to_matrix(*e)
        sol = solve_full(_detection(rig, R), rig)
        assert sol.status is Status.OK
        assert _angle(sol.R_nb, R) < EXACT_TOL
        assert sol.iterations <= 5


def test_full_covariance_matches_monte_carlo(rig640, rng):
    R = euler_to_matrix(0.8, 0.04, -0.03)
    errs, covs = [], []
    for _ in range(400):
        sol = solve_full(_detection(rig640, R, 0.1, rng), rig640)
        e = np.array(matrix_to_euler(sol.R_nb)) - np.array(matrix_to_euler(R))
        errs.append(e)
        J = euler_rates_from_body(*matrix_to_euler(sol.R_nb))
        covs.append(np.diag(J @ sol.cov_b @ J.T))
    emp = np.std(errs, axis=0)
    pred = np.sqrt(np.mean(covs, axis=0))
    # sigma is scaled up by sqrt(chi2 / dof) when the residuals exceed the model's
    # noise, never down: on average it is a little conservative, never optimistic
    ratio = pred / emp
    assert np.all(ratio > 0.92) and np.all(ratio < 1.35), ratio


def test_wrong_shape_is_rejected_not_reported(rig640):
    det = _detection(rig640, np.eye(3))
    xy = det.points_n.copy()
    xy[1] += 8.0 / rig640.camera.fx  # one vertex 8 px off: no attitude explains it
    sol = solve_full(replace(det, points_n=xy), rig640)
    assert sol.status is Status.REJECTED
    assert "inconsistent_geometry" in sol.warnings


def test_paper_estimator_yaw_and_tilt_signs(rig640):
    for yaw in (-2.0, 0.0, 1.0, 3.0):
        R = euler_to_matrix(yaw, 0.0, 0.0)
        sol = solve_paper(_detection(rig640, R), rig640)
        y, p, r = matrix_to_euler(sol.R_nb)
        assert abs((y - yaw + np.pi) % (2 * np.pi) - np.pi) < 1e-9
        # the example triangle's centroid is 0.03 mm off the axis (rounded vertices):
        # the paper's method cannot model that and reads ~2e-5 rad of tilt
        assert abs(p) < 1e-4 and abs(r) < 1e-4
    # a small tilt is seen with the right sign and roughly the right size
    R = euler_to_matrix(0.0, np.radians(2.0), np.radians(-1.0))
    y, p, r = np.degrees(matrix_to_euler(solve_paper(_detection(rig640, R), rig640).R_nb))
    assert abs(p - 2.0) < 0.2 and abs(r + 1.0) < 0.2


def test_tracking_starts_from_the_last_attitude_and_finds_the_same_one(rig640):
    """While the detector tracks, Gauss-Newton starts from the last frame's attitude
    turned on at the last rate instead of the closed form: same minimum, and the start
    is really used."""
    from visvec.data import Frame
    from visvec.pipeline import TrianglePipeline
    from visvec.sim.render import render_frame
    from visvec.sim.scene import Scene

    def angle_deg(A, B):
        return np.degrees(np.linalg.norm(logmap(A.T @ B)))

    pipe = TrianglePipeline(rig640)
    used = 0
    for k in range(6):
        # a steady turn: 9 deg/s in yaw, 3 deg/s in pitch
        R = euler_to_matrix(np.radians(10 + 0.3 * k), np.radians(1 - 0.1 * k), np.radians(2))
        if k >= 2:
            # the last attitude is a frame's turn (0.32 deg) from this one; turned on at
            # the rate between the last two, it is within their noise (yaw sigma 0.01 deg
            # a frame: the extrapolation's sqrt(5) x that)
            assert angle_deg(pipe.R_last, R) > 0.3
            assert angle_deg(pipe._predicted(k / 30), R) < 0.1
        prior = pipe.height.prior()  # the running height, the same for both fits
        row = pipe.process(Frame(k, k / 30, render_frame(rig640, R, Scene(), rng=k)))
        assert row.ok
        tracked = pipe.detector.last_was_tracked
        assert tracked == (k > 0)
        closed = solve_full(pipe.last_detection, rig640, None, prior)
        np.testing.assert_allclose(pipe.last_solution.R_nb, closed.R_nb, atol=1e-8)
        used += tracked and pipe.last_solution.iterations != closed.iterations
        if k >= 2:
            # from the predicted start, no more iterations than from the closed form
            # (3 from the last attitude alone)
            assert pipe.last_solution.iterations <= closed.iterations
    assert used >= 1  # the start differed from the closed form's
