"""The edge fit (visvec.detect.edges): profiles, levels, blur widths, robust lines and the
vertices' covariance."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from visvec.data import Status
from visvec.detect import TriangleDetector, edges
from visvec.geometry import project_target
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from conftest import TEST_DATA, attitudes


def test_edge_fit_shutter_gain_is_how_its_vertices_move_with_the_rate(rig640):
    """A frame of a 25 ms rolling shutter turning at 10 deg/s in yaw: its vertices
    detected again with the rate (each edge point taken to the centre row's exposure)
    move by the edge fit's shutter gain times the rate, to a few thousandths of a pixel.
    The vertex-level matrix misses that move by a hundredth or more: a turn about the
    boresight curves the edges, and the lines fitted to them meet elsewhere."""
    from visvec.shutter import shutter_matrix

    rig = replace(rig640, readout_ms=25.0)
    w_b = np.radians([0.0, 0.0, 10.0])
    R = euler_to_matrix(0.4, np.radians(2.0), np.radians(-1.5))
    img = render_frame(rig640, R, Scene(), 31, 25.0, w_b)
    det = TriangleDetector(rig)
    seen = det.detect(img)
    assert seen.status is Status.OK
    omega_c = rig.R_bc.T @ w_b
    fx = rig.camera.fx
    gain = seen.shutter_gain_n  # the gain its covariance used
    moved = (det.redetect(img, omega_c).points_n - seen.points_n).ravel() * fx
    np.testing.assert_allclose(gain @ omega_c * fx, moved, atol=0.004)
    A = shutter_matrix(seen.points_n, seen.points_px[:, 1], rig.camera, 25.0, det.lever_c)
    assert np.abs(A @ omega_c * fx - moved).max() > 0.01


def test_edge_along_a_pixel_row_is_not_biased_by_off_centre_profiles(rig640):
    """A cold frame whose base edge lies along a pixel row (found in the accuracy
    benchmark): the first fine pass was centred on a coarse line 2 px off, its windows
    cut the blur on one side, and the base vertex came out 0.2 px (5 sigma) off. The
    profiles are now centred once more, and the vertices are within their covariance
    (squared Mahalanobis distance below the 99.9 % point of chi-square, 6 dof)."""
    from visvec.bench.triangle import random_cases

    case = random_cases(300, Scene(), 7)[252]
    R = euler_to_matrix(*case.euler)
    d = TriangleDetector(rig640).detect(render_frame(rig640, R, case.scene, case.seed))
    assert d.status is Status.OK
    xy = rig640.camera.undistort(project_target(rig640, R))
    e = (d.points_n - xy).ravel()
    assert e @ np.linalg.solve(d.cov_n, e) < 22.5


def test_defocused_edges_are_fitted_on_windows_that_hold_the_blur(rig640):
    """A soft lens (blur sigma 2 px at 640x480): the profiles were cut at 4 px, 2 blur
    sigmas, and a line the first pass left a fraction of a pixel off gave biased steps:
    noise-free vertex coordinates were 0.057 px RMS off on these frames. With windows
    of 3 blur widths (the sparse pass repeated on a wider window when the blur needs
    it) they are within 0.035 px (0.025 measured) and every frame is found."""
    rng = np.random.default_rng(4)
    errs = []
    for k in range(8):
        eul = [rng.uniform(-np.pi, np.pi), *rng.uniform(-0.08, 0.08, 2)]
        R = euler_to_matrix(*eul)
        img = render_frame(rig640, R, replace(Scene(), blur_sigma_px=2.0, noise_sigma=0.0), rng=k)
        d = TriangleDetector(rig640).detect(img)
        assert d.status is Status.OK, d.reason
        errs.append((d.points_n - rig640.camera.undistort(project_target(rig640, R))).ravel())
    rms_px = np.sqrt(np.mean(np.square(errs))) * rig640.camera.fx
    assert rms_px < 0.035, rms_px


def test_a_common_level_error_shifts_the_step_as_the_covariance_model_says():
    """Both levels of an edge measured 1 grey level high (the error common to its
    profiles, since the levels are lines fitted along it): the erf-step positions move
    by _level_gain * d / h, about 2 sqrt(pi) w d / h, which the line covariance adds."""
    from scipy.special import erf

    from visvec.detect import edges

    half, step, ext, w, lo, hi = 5.5, 0.5, 1.0, 1.5, 40.0, 68.0
    x = np.arange(-half - ext, half + ext + 1e-9, step)
    m = 20
    gid, t = np.repeat(np.arange(3), m), np.tile(np.linspace(-1, 1, m), 3)
    vals = np.tile(lo + (hi - lo) * 0.5 * (1 + erf(x / (np.sqrt(2) * w))), (3 * m, 1))
    width = np.full(3, w)
    e0 = edges._positions(vals, t, gid, half, step, width, ext)[0]
    n_level = int(round(ext / step)) + max(2, int(1.0 / step))  # samples the levels use
    bumped = vals.copy()
    bumped[:, :n_level] += 1.0
    bumped[:, -n_level:] += 1.0
    e1 = edges._positions(bumped, t, gid, half, step, width, ext)[0]
    predicted = edges._level_gain(width, half, step) / (hi - lo)
    assert np.allclose(e1 - e0, predicted[gid], rtol=0.02), (e1 - e0, predicted)
    assert np.allclose(predicted, 2 * np.sqrt(np.pi) * w / (hi - lo), rtol=0.01)


def test_vertex_sigma_covers_the_errors_of_defocused_edges(rig640):
    """At 2 px of defocus the level error (common to an edge, so not in its residuals)
    is a large part of a line's error. With one residual inflation calibrated at the
    default blur, the vertex error/sigma RMS was 1.24 here; with the level error
    modelled it is 1.01."""
    det = TriangleDetector(rig640)
    z = []
    for k, R in enumerate(attitudes(8, 11)):
        for j in range(5):
            img = render_frame(rig640, R, Scene(blur_sigma_px=2.0), rng=900 + 10 * k + j)
            d = det.detect(img)
            assert d.status is Status.OK, d.reason
            e = d.points_n - rig640.camera.undistort(project_target(rig640, R))
            z.append(e.ravel() / np.sqrt(np.diag(d.cov_n)))
    zr = np.sqrt(np.mean(np.square(z)))
    assert 0.85 < zr < 1.15, zr


def test_blur_width_from_coarse_corners_far_off_the_edges(rig640):
    """The coarse corners of a cold frame can be far off: the acute apex found on the
    shrunk image came out 21 px from the true one (a frame of the speed benchmark's
    sweep), so the first pass's profiles crossed one edge 0-5 px from their centres and
    a few found no step at all. The edge's blur width was then measured as 5 px
    (true ~0.8), the fine pass fitted its steps with that width, and the vertices
    came out 1.3 px off (refused as inconsistent geometry). Widths from such corners
    now match those from the true corners within 15 %, and the vertices are good."""
    from visvec.detect import edges

    R = euler_to_matrix(np.radians(2.03), np.radians(0.05), np.radians(0.07))
    img = render_frame(rig640, R, Scene(), rng=3)
    truth = project_target(rig640, R)
    apex_dir = truth[0] - truth[1:].mean(axis=0)
    for shift in (0.0, 21.0):
        coarse = truth.copy()
        coarse[0] += shift * apex_dir / np.linalg.norm(apex_dir)
        coarse[1] += [1.5, -1.0]
        fit = edges.fit_edges(img, coarse, rig640.camera)
        if shift == 0.0:
            reference = fit.width
            continue
        assert np.all(np.abs(fit.width / reference - 1.0) < 0.15), (fit.width, reference)
        xy, cov = edges.intersect(fit)
        e = (xy - rig640.camera.undistort(truth) * rig640.camera.fx).ravel()
        assert e @ np.linalg.solve(cov, e) < 22.5
    assert np.all((reference > 0.6) & (reference < 1.1)), reference


def test_full_hd_webcam_cold_frames_need_two_edge_passes(rig640, monkeypatch):
    """A 1920x1080 webcam (fx 1400 px, barrel distortion): the region search works on the
    frame halved three times (a 10x shrink had no fast path: 340 against 100 us), its
    coarse corners are up to half a shrunk pixel (4 px) off the edges, so the first
    pass's window reaches 8 px: with the usual 4 px, 97 of 150 cold frames needed a
    third pass, and the width measured on a window cutting the step came out short. The
    blur width is measured again within 4 widths of the edge, so the
    wider window adds no noise to it (10-90 % of cold frames' widths 0.54-1.06 px
    before, 0.77-0.89 after; true about 0.8)."""
    from visvec.detect import edges

    cam = replace(
        rig640.camera,
        width=1920,
        height=1080,
        fx=1400.0,
        fy=1400.0,
        cx=955.0,
        cy=545.0,
        dist=np.array([0.1, -0.2, 0.0, 0.0, 0.08]),
    )
    rig = replace(rig640, camera=cam)
    det = TriangleDetector(rig)
    assert det.scale == 8
    passes = []
    sample = edges._sample
    monkeypatch.setattr(edges, "_sample", lambda *a: passes.append(a[3]) or sample(*a))
    for seed in (4, 6):  # with the 4 px window: 3 passes, a width of 0.46 or 0.40 px
        R = attitudes(1, seed)[0]
        img = render_frame(rig, R, Scene(), rng=4)
        det.reset()
        passes.clear()
        d = det.detect(img)
        assert d.status is Status.OK, d.reason
        assert len(passes) == 2, passes
        assert np.all((det._fit_width > 0.65) & (det._fit_width < 1.0)), det._fit_width
        e = (d.points_n - cam.undistort(project_target(rig, R))).ravel()
        assert e @ np.linalg.solve(d.cov_n, e) < 22.5


def test_edge_levels_measured_beyond_the_step_make_the_vertices_more_precise(rig640, monkeypatch):
    """The board and triangle levels of an edge are fitted along it from every profile's
    ends, so their error moves the whole line and does not average out: measured over
    2 px beyond the step window rather than 1 px inside it, the vertices of one frame
    under 30 noise draws scatter at least 5 % less (14 % measured)."""
    from visvec.detect import edges

    R = attitudes(1, 5)[0]
    start = project_target(rig640, R)
    truth = rig640.camera.undistort(start) * rig640.camera.fx
    errs = {0.0: [], edges.LEVEL_EXTENT_PX: []}
    for k in range(30):
        img = render_frame(rig640, R, Scene(), rng=500 + k)
        for ext, out in errs.items():
            monkeypatch.setattr(edges, "LEVEL_EXTENT_PX", ext)
            fit = edges.fit_edges(img, start, rig640.camera, width=np.full(3, 0.9))
            out.append((edges.intersect(fit)[0] - truth).ravel())
    inside, beyond = (np.sqrt(np.mean(np.square(e))) for e in errs.values())
    assert beyond < 0.95 * inside, (beyond, inside)


def test_level_lines_ignore_profiles_with_something_else_in_their_window():
    """Board levels along an edge with a lighting gradient; a dark head lies in the
    windows of 12 of 48 profiles. The level lines follow the board and the triangle, not
    the head; every profile of the head is flagged, and of the others only the odd one
    whose noise draw lies beyond the 3.5-sigma limit. Compiled and on the numpy path
    alike (one function, visvec._kernels.edge_fit._level_lines)."""
    import contextlib

    from visvec._kernels import edge_fit as KE
    from visvec._kernels import jit

    rng = np.random.default_rng(3)
    m = 48
    gid, t = np.repeat(np.arange(3), m), np.tile(np.linspace(-1, 1, m), 3)
    lo_true, hi_true = 70.0 + 3.0 * t, 98.0 + 4.0 * t
    lo_raw = lo_true + rng.normal(0, 1.0, 3 * m)
    hi_raw = hi_true + rng.normal(0, 1.0, 3 * m)
    head = (gid == 0) & (np.abs(t - 0.1) < 0.25)
    lo_raw[head] -= rng.uniform(8.0, 35.0, head.sum())
    starts = np.array([0, m, 2 * m, 3 * m])
    limits = (edges.LEVEL_OUTLIER_SIGMAS, edges.LEVEL_OUTLIER_MIN, edges.LEVEL_SUSPECT_RMS,
              edges.LEVEL_SUSPECT_MAX)  # fmt: skip
    for path in (contextlib.nullcontext(), jit.numpy_path()):
        with path:
            lo, hi, ok = KE._level_lines(t, lo_raw, hi_raw, gid, starts, *limits)
        assert np.all(~ok[head])
        assert np.count_nonzero(~ok & ~head) <= 2
        assert np.abs(lo - lo_true).max() < 1.0
        assert np.abs(hi - hi_true).max() < 1.0


def test_level_lines_take_the_fast_path_only_when_nothing_else_is_in_the_windows():
    """Least-squares level lines are kept as they are when their residuals are the
    profiles' noise (a lighting gradient along the edge included); a dark head over a
    stretch of one edge, or one light in one profile, sends the edge to the robust
    fit. The numpy twins and the loops alike."""
    from visvec._kernels import edge_fit as KE

    rng = np.random.default_rng(5)
    m = 60
    gid, t = np.repeat(np.arange(3), m), np.tile(np.linspace(-1, 1, m), 3)
    starts = np.array([0, m, 2 * m, 3 * m])
    none = np.zeros(0, bool)

    limits = (edges.LEVEL_SUSPECT_RMS, edges.LEVEL_SUSPECT_MAX)

    def suspect(lo_raw, hi_raw):
        got = set()
        for group_linear, levels_suspect in ((KE._group_linear_numpy, KE._levels_suspect_numpy),
                                             (KE._group_linear, KE._levels_suspect)):  # fmt: skip
            lo = group_linear(t, lo_raw, gid, none, False)
            hi = group_linear(t, hi_raw, gid, none, False)
            got.add(bool(levels_suspect(lo_raw - lo, hi_raw - hi, lo_raw, hi_raw, starts,
                                        *limits)))  # fmt: skip
        assert len(got) == 1
        return got.pop()

    clean = [
        (70.0 + 4.0 * t + rng.normal(0, 1.5, 3 * m), 98.0 + 5.0 * t + rng.normal(0, 1.5, 3 * m))
        for _ in range(50)
    ]
    assert sum(suspect(lo, hi) for lo, hi in clean) <= 2
    lo, hi = clean[0]
    head = lo.copy()
    head[(gid == 1) & (np.abs(t) < 0.2)] -= 12.0
    assert suspect(head, hi)
    light = hi.copy()
    light[2 * m + 7] += 40.0
    assert suspect(lo, light)


def test_regression_edge_fit_diverging_on_occluded_frame(rig640):
    # a benchmark frame (occluder over the triangle) whose edge lines once met far away
    # and crashed cv2.remap with a huge profile array
    img = cv2.imread(str(TEST_DATA / "regression_occluder_640.png"), cv2.IMREAD_GRAYSCALE)
    d = TriangleDetector(rig640).detect(img)
    assert d.status in (Status.OK, Status.NO_TARGET, Status.REJECTED)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(1, 40), min_size=3, max_size=3), st.integers(0, 2**31 - 1))
def test_group_median_equals_numpys_per_edge(sizes, seed):
    """The edges' medians, in one sort (numpy) or loops (compiled): each equals
    np.median of that edge's kept values."""
    from visvec._kernels import edge_fit as KE

    r = np.random.default_rng(seed)
    gid = np.repeat(np.arange(3), sizes)
    index = np.concatenate([np.arange(m) for m in sizes])
    a = r.standard_normal(len(gid))
    keep = r.random(len(gid)) < 0.7
    for group_median in (KE._group_median_numpy, KE.group_median):
        med = group_median(a, gid, index, keep)
        for i in range(3):
            sel = a[(gid == i) & keep]
            assert med[i] == (np.median(sel) if sel.size else 0.0)


def test_robust_lines_reject_outliers_and_measure_the_noise():
    """Three noisy lines with gross outliers, fitted at once: each line within its noise,
    the outliers out, sigma the residuals' (inflated) RMS; an edge with fewer than 5
    usable points keeps them all. Compiled and on the numpy path alike (one function,
    visvec._kernels.edge_fit.robust_lines)."""
    import contextlib

    from visvec._kernels import edge_fit as KE
    from visvec._kernels import jit
    from visvec.detect.edges import EDGE_VARIANCE_INFLATION

    for path in (contextlib.nullcontext(), jit.numpy_path()):
        with path:
            _robust_lines_once(KE, EDGE_VARIANCE_INFLATION)


def _robust_lines_once(KE, EDGE_VARIANCE_INFLATION):
    def _robust_lines(*a):
        return KE.robust_lines(*a, EDGE_VARIANCE_INFLATION)

    r = np.random.default_rng(11)
    m = [300, 200, 250]
    gid = np.repeat(np.arange(3), m)
    index = np.concatenate([np.arange(k) for k in m])
    angles = np.radians([10.0, 75.0, -50.0])
    offsets = np.array([40.0, -12.0, 7.5])
    normal = np.column_stack([np.cos(angles), np.sin(angles)])
    along = r.uniform(-100, 100, len(gid))
    noise = 0.05 * r.standard_normal(len(gid))
    bad = r.random(len(gid)) < 0.05
    noise[bad] += r.choice([-1.0, 1.0], bad.sum()) * r.uniform(1.0, 5.0, bad.sum())
    perp = np.column_stack([-normal[gid, 1], normal[gid, 0]])
    p = normal[gid] * (offsets[gid] + noise)[:, None] + perp * along[:, None]
    use = np.ones(len(gid), dtype=bool)
    n, o, c, spread, sigma, keep = _robust_lines(p[:, 0], p[:, 1], gid, index, use, 0.0, 3)
    for i in range(3):
        s = np.sign(n[i] @ normal[i])
        assert abs(s * o[i] - offsets[i]) < 0.02
        assert np.degrees(np.arccos(min(1.0, abs(n[i] @ normal[i])))) < 0.02
        sel = gid == i
        assert not keep[sel & bad].any()  # every gross outlier (>= 1 px = 20 sigma) out
        assert keep[sel & ~bad].mean() > 0.99
        res = (p[sel & keep] - c[i]) @ n[i]
        assert sigma[i] == pytest.approx(
            np.sqrt(res @ res / (keep[sel].sum() - 2) * EDGE_VARIANCE_INFLATION), rel=1e-9
        )
        assert sigma[i] == pytest.approx(0.05 * np.sqrt(EDGE_VARIANCE_INFLATION), rel=0.15)
    # an edge with only 4 usable points: no rejection round for it
    use4 = use.copy()
    use4[gid == 1] = False
    use4[np.nonzero(gid == 1)[0][:4]] = True
    _, _, _, _, _, keep4 = _robust_lines(p[:, 0], p[:, 1], gid, index, use4, 0.0, 3)
    assert keep4[gid == 1].sum() == 4
    np.testing.assert_array_equal(keep4[gid != 1], keep[gid != 1])


def test_fast_erf_is_within_abramowitz_stegun_bound():
    """The edge fit's erf (A&S 7.1.26, sharing exp(-u^2) with its Gauss-Newton) stays
    within the formula's 1.5e-7 of scipy's, odd, and exact at 0 and far out."""
    from scipy.special import erf

    from visvec._kernels.edge_fit import erf_with_bell

    u = np.concatenate([np.linspace(-6.0, 6.0, 20001), [0.0, -0.0, 30.0, -30.0]])
    got = erf_with_bell(u, np.exp(-u * u))
    assert np.max(np.abs(got - erf(u))) < 1.5e-7
    np.testing.assert_allclose(erf_with_bell(-u, np.exp(-u * u)), -got, atol=0)
    assert abs(got[-4]) < 1e-9 and got[-2] == 1.0 and got[-1] == -1.0


def _blurred_profiles(rng, half, step, w_true, per_edge, e_max):
    """Profiles (3 edges x ``per_edge``) across a step of RMS width ``w_true`` at
    positions uniform within +-``e_max``, sampled every ``step`` over +-``half``: the
    offsets, each profile's edge and step position, and the unit step's values."""
    from scipy.special import erf

    offs = np.arange(-half, half + 1e-9, step)
    gid = np.repeat(np.arange(3), per_edge)
    e = rng.uniform(-e_max, e_max, len(gid))
    edge = 0.5 * (1.0 + erf((offs[None, :] - e[:, None]) / (np.sqrt(2.0) * w_true)))
    return offs, gid, e, edge


def test_a_wide_window_measures_the_width_again_near_the_edge():
    """A window wider than WIDTH_REACH_MIN_PX (a large image's first pass): the width is
    measured again within 4 widths of the edge, where its far bins' noise no longer
    moves it; compiled and on the numpy path alike (one function, edge_fit.widths)."""
    import contextlib

    from visvec._kernels import edge_fit as KE
    from visvec._kernels import jit

    rng = np.random.default_rng(8)
    half, step, w_true = 8.0, 0.5, 0.8
    _, gid, e, edge = _blurred_profiles(rng, half, step, w_true, 40, 1.0)
    vals = (60.0 + 40.0 * edge + rng.normal(0.0, 2.0, edge.shape)).astype(np.float32)
    clear = np.ones(len(gid), bool)
    got = []
    for path in (contextlib.nullcontext(), jit.numpy_path()):
        with path:
            again = KE.widths(vals, 0, e, clear, gid, half, step, edges.WIDTH_REACH_MIN_PX)
            once = KE.widths(vals, 0, e, clear, gid, half, step, 2.0 * half)  # one round
        got.append((again, once))
    assert np.abs(got[0][0] - got[1][0]).max() < 1e-12
    assert np.abs(got[0][1] - got[1][1]).max() < 1e-12
    again, once = got[0]
    # (the sampling and the steps' alignment to the nearest sample widen it a little)
    assert np.abs(again - w_true).max() < 0.25
    assert np.abs(once - w_true).max() > 0.3


def test_a_width_is_never_measured_below_a_pixels_box():
    """Noise in a narrow window's far bins can take most of a width's second moment away
    (the moment weighs a bin by its squared distance from the edge): here one edge's
    bright level falls by a grey level a pixel from 2.25 px past its step, and the
    moment reads under a pixel's box. The width returned is the box's (MIN_WIDTH_PX), on
    both paths; the other edges keep their measured width."""
    import contextlib

    from visvec._kernels import edge_fit as KE
    from visvec._kernels import jit

    rng = np.random.default_rng(9)
    half, step, w_true = 4.0, 0.5, 0.8
    offs, gid, e, edge = _blurred_profiles(rng, half, step, w_true, 30, 0.5)
    vals = 60.0 + 30.0 * edge + rng.normal(0.0, 0.3, edge.shape)
    past = np.clip(offs[None, :] - e[:, None] - 2.25, 0.0, None)
    vals = np.where(gid[:, None] == 2, vals - past, vals).astype(np.float32)
    clear = np.ones(len(gid), bool)
    g, x = KE._aligned_slopes_numpy(vals, 0, e, clear, gid, half, step)
    raw = KE._moment_widths_numpy(g, x, np.full(3, np.inf), half)
    assert 0.0 < raw[2] < KE.MIN_WIDTH_PX  # the case the floor is for
    for path in (contextlib.nullcontext(), jit.numpy_path()):
        with path:
            w = KE.widths(vals, 0, e, clear, gid, half, step, edges.WIDTH_REACH_MIN_PX)
        assert w[2] == KE.MIN_WIDTH_PX
        np.testing.assert_allclose(w[:2], raw[:2], atol=1e-12)
        assert np.abs(w[:2] - w_true).max() < 0.25
