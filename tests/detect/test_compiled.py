"""The compiled kernels (visvec._kernels, the `fast` extra) against the numpy path:
each algorithm written once, run compiled and as Python on the numpy twins of its
passes over a frame's pixels or profiles (jit.numpy_path), gives the same results to
rounding on the inputs frames of every kind give them (sharp and defocused, both
resolutions, a lens with distortion, a lighting gradient, a light and a head over the
triangle, tracked and cold); each twin gives its loop's results; the loops run as
Python give what Numba compiled."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from dataclasses import fields, replace

import numpy as np
import pytest

from visvec._kernels import edge_fit as KE
from visvec._kernels import jit
from visvec._kernels import pixel_fit as KP
from visvec._kernels import readout as KO
from visvec._kernels import rotation as KR
from visvec.data import Frame
from visvec.detect import edges as E
from visvec.detect import warm as W
from visvec.pipeline import TrianglePipeline
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Light, Occluder, Scene

from conftest import CONFIGS, attitudes

pytestmark = pytest.mark.skipif(not jit.AVAILABLE, reason="Numba (the fast extra)")

# the edge fit's functions whose path the kernels choose: edges' own, and the
# kernels' functions written once that the numpy path calls by name
KERNELS = (
    "_sample",
    "_positions",
    "_widths",
    "robust_lines",
    "group_median",
    "_edge_fit",
    "_level_gain",
    "_lines",
    "lag_sums",
)
IN_KERNELS = ("robust_lines", "group_median")


def _owner(name):
    """The module whose name ``name`` the pipeline calls."""
    return KE if name in IN_KERNELS else E


def _frames():
    """(rig, frame) of each kind, the clean ones at two attitudes."""
    rig640 = load_rig(CONFIGS / "triangle.toml")
    rig320 = load_rig(CONFIGS / "triangle-320.toml")
    cam = rig640.camera
    barrel = replace(rig640, camera=replace(cam, dist=np.array([-0.12, 0.03, 0.0, 0.0, 0.0])))
    out = []
    for k, (rig, scene) in enumerate([
        (rig640, Scene()),
        (rig320, Scene(blur_sigma_px=2.0)),
        (barrel, Scene(gradient_per_m=0.6)),
        (rig640, Scene(lights=(Light(380.0, 120.0, 120.0),))),
    ]):  # fmt: skip
        for j, R in enumerate(attitudes(2, 40 + k)):
            out.append((rig, render_frame(rig, R, scene, rng=100 * k + j)))
    # heads over the triangle (tests/detect/test_triangle.py): a dark one just off the
    # long edge, a dark one over the acute vertex, a bright one over a base edge
    R = euler_to_matrix(-0.2784127, 0.06476841, -0.06955626)
    head = Scene(occluder=Occluder(76.67, -134.70, 1123.48, 85.23, 39.21))
    out += [(rig320, render_frame(rig320, R, head, rng=seed)) for seed in (1, 2)]
    R = euler_to_matrix(0.3, 0.02, -0.01)
    for occ in (
        Occluder(214.0, 0.0, 1300.0, 40.0, 50.0),
        Occluder(-107.0, 0.0, 1300.0, 45.0, 200.0),
    ):
        out.append((rig640, render_frame(rig640, R, Scene(occluder=occ), rng=3)))
    return out


@pytest.fixture(scope="module")
def calls():
    """Every call the pipeline makes on _frames() to the functions whose path the
    kernels choose (on the numpy path, where the kernels' functions written once call
    the others by name): each name, a function that calls it on the path it is on, and
    the calls."""
    got = {n: [] for n in KERNELS}

    def spy(n, f):
        def g(*a, **k):
            got[n].append((a, k))
            return f(*a, **k)

        return g

    with jit.numpy_path(), pytest.MonkeyPatch.context() as mp:
        for n in KERNELS:
            mp.setattr(_owner(n), n, spy(n, getattr(_owner(n), n)))
        for rig, img in _frames():
            pipe = TrianglePipeline(rig)
            pipe.process(Frame(0, 0.0, img))
            pipe.process(Frame(1, 1 / 30, img))  # tracked from the first
    return {n: ((lambda *a, n=n, **k: getattr(_owner(n), n)(*a, **k)), got[n]) for n in KERNELS}


def _diff(a, b) -> float:
    """The largest difference between two outputs (tuples of arrays; a boolean's count
    of disagreements; an EdgeFit's fields)."""
    if isinstance(a, E.EdgeFit):
        a, b = (tuple(getattr(x, f.name) for f in fields(x)) for x in (a, b))
    if a is None or b is None:
        assert a is None and b is None
        return 0.0
    if isinstance(a, tuple):
        return max(_diff(x, y) for x, y in zip(a, b, strict=True))
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype, (a.shape, b.shape, a.dtype, b.dtype)
    if a.dtype == bool:
        return float(np.sum(a != b))
    same_nan = np.isnan(a) == np.isnan(b)
    assert same_nan.all()
    return float(np.max(np.abs(np.nan_to_num(a) - np.nan_to_num(b)), initial=0.0))


@pytest.mark.parametrize("name", KERNELS)
def test_each_kernel_gives_what_numpy_gives(calls, name, monkeypatch):
    """Every output of every call: the same shape and type, the same decisions (inlier
    and level masks), the values within 1e-9 (px, grey levels; the lines' ideal pixels
    are a few hundred)."""
    f, args = calls[name]
    assert len(args) >= 10, len(args)
    worst = 0.0
    for a, k in args:
        with jit.numpy_path():
            pure = f(*a, **k)
        fast = f(*a, **k)
        worst = max(worst, _diff(pure, fast))
    assert worst < 1e-9, worst


def test_the_frames_reach_the_kernels_robust_branches(calls):
    """The light and the head put profiles whose levels disagree into the level lines
    and points off the line into the robust lines: the comparisons above cover the
    branches that leave them out."""
    f, args = calls["_positions"]
    assert sum(not f(*a, **k)[4].all() for a, k in args) >= 3
    f, args = calls["robust_lines"]
    assert sum(not f(*a, **k)[5][a[4]].all() for a, k in args) >= 3


def test_the_fits_name_their_results_alike_compiled_or_not(calls, monkeypatch):
    """The step positions, the lines' scatter and the attitude fit's steps are the same
    NamedTuples from the numpy path and the compiled one, field by field equal."""
    f, args = calls["_positions"]
    a, k = args[0]
    got = []
    for flag in (False, True):
        with _path(flag):
            got.append(f(*a, **k))
    assert type(got[0]) is type(got[1]) is KE.StepPositions
    # the sampling geometry and the lines' statistics, numpy and compiled alike
    for name, kernel, to_args, named in (
        ("_sample", "sample_geometry", _sample_args, KE.SampleGeometry),
        ("_edge_fit", "edge_stats", lambda *a: (a[4], a[5], a[6], *a[9:14]), KE.EdgeStats),
    ):
        a, k = calls[name][1][0]
        compiled = getattr(KE, kernel)(*to_args(*a, **k))
        with jit.numpy_path():
            numpy_ = getattr(KE, kernel)(*to_args(*a, **k))
        assert type(compiled) is type(numpy_) is named and _diff(compiled, numpy_) < 1e-9
    assert np.abs(got[0].e - got[1].e).max() < 1e-9
    rng = np.random.default_rng(3)
    x, y = rng.normal(0.0, 50.0, 90), rng.normal(0.0, 50.0, 90)
    gid, keep = np.repeat(np.arange(3), 30), rng.random(90) > 0.2
    numpy_, compiled = KE._group_tls_numpy(x, y, gid, keep), KE._group_tls(x, y, gid, keep)
    assert type(numpy_) is type(compiled) is KE.LineScatter
    assert np.abs(numpy_.normal - compiled.normal).max() < 1e-12
    X = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]])
    t_c = np.array([5.0, 3.0, 1000.0])
    xy = (X[:, :2] + t_c[:2]) / (X[:, 2:] + t_c[2])
    args = (np.eye(3), t_c, X, xy, np.eye(6), np.array([0.0, 0.0, 1.0]), 0.0, 1.0, 15, 1e-12, 1e-3)
    fits = KR.gn_shift(*args), KR._gn_shift(*args)
    assert type(fits[0]) is type(fits[1]) is KR.ShiftFit and fits[0].converged
    assert fits[0].iterations == fits[1].iterations and abs(fits[0].s - fits[1].s) < 1e-9


def test_the_kernels_run_as_python_give_what_compiled_gives(calls):
    """Each kernel's Python source (Numba's py_func, which coverage can follow) gives
    the compiled kernel's result: what the tests above check is the code here."""
    kernels = {
        "_positions": (KE.positions, lambda a, k: _positions_args(*a, **k)),
        "_widths": (KE.widths, lambda a, k: _widths_args(*a, **k)),
        "robust_lines": (KE.robust_lines, lambda a, k: a),
        "_sample": (KE.sample_geometry, lambda a, k: _sample_args(*a, **k)),
        "group_median": (KE.group_median, lambda a, k: a),
        "_edge_fit": (KE.edge_stats, lambda a, k: (a[4], a[5], a[6], *a[9:14])),
        "_level_gain": (KE.level_gain, lambda a, k: (np.asarray(a[0], float), *a[1:])),
        "_lines": (KE.inward_lines, lambda a, k: _inward_args(*a)),
        "lag_sums": (KE.edge_lag_sums, lambda a, k: (*a, E.CORRELATION_LAGS)),
    }
    # to the bit, but for the step positions and the level gain: written once for the
    # numpy path too (edge_fit.step_residual, _level_gain), they take numpy's exp and
    # sums, which may differ from the C library's exp and the loop's sums that Numba
    # makes in the last bit of a value
    exact = {"_positions": 1e-15, "_level_gain": 1e-14}
    for name, (kernel, to_args) in kernels.items():
        for a, k in calls[name][1][:2]:
            args = to_args(a, k)
            assert _diff(kernel(*args), _as_python(kernel)(*args)) <= exact.get(name, 0.0), name


def _home(name):
    """The kernels' module that holds ``name``."""
    return next(m for m in (KE, KP, KR, KO) if name in vars(m))


def _path(compiled):
    """The compiled kernels, or the numpy path (jit.numpy_path: a kernel written once
    runs as Python with its numpy twins)."""
    return contextlib.nullcontext() if compiled else jit.numpy_path()


def _as_python(kernel):
    """The kernel and the kernels it calls as plain Python."""
    inner = {n: getattr(_home(n), n) for n in ("_group_linear", "_levels_suspect",
                                                 "_resistant_residuals", "_level_inliers",
                                                 "_edge_starts", "_end_levels", "_area_positions",
                                                 "_position_sums", "_level_stats",
                                                 "_aligned_slopes", "_moment_widths",
                                                 "_level_lines", "_group_tls",
                                                 "group_median", "_lag_sums", "_erf_with_bell",
                                                 "_step_residual", "_position_step",
                                                 "_phi_of", "_across_edge", "_pixel_residual",
                                                 "_pixel_gn", "_strided",
                                                 "noise_inflation", "cover",
                                                 "band_pixels", "_edge_jacobian",
                                                 "_board_columns", "_step_columns",
                                                 "_residual_columns", "_add_edge",
                                                 "_vertices_and_gain", "_distances",
                                                 "_inliers", "_kept_where", "_line_sums",
                                                 "_usable", "robust_lines")}  # fmt: skip

    def run(*args):
        mp = pytest.MonkeyPatch()
        try:
            for n, f in inner.items():
                mp.setattr(_home(n), n, f.py_func)
            return kernel.py_func(*args)
        finally:
            mp.undo()

    return run


def _positions_args(vals, t, gid, half, step, width, ext=0.0):
    n_ext = int(round(ext / step))
    w = E._NO_WIDTH if width is None else np.asarray(width, float)
    return (vals, t, gid, float(half), float(step), w, n_ext, max(2, int(1.0 / step)) + n_ext,
            E.GN_STEPS, E.LEVEL_OUTLIER_SIGMAS, E.LEVEL_OUTLIER_MIN, E.LEVEL_SUSPECT_RMS,
            E.LEVEL_SUSPECT_MAX)  # fmt: skip


def _widths_args(vals, e, clear, gid, half, step):
    return vals, 0, e, clear, gid, float(half), float(step), E.WIDTH_REACH_MIN_PX


def _inward_args(raw, pts_px, pr, camera, shutter, rate_c, sigma_floor, rounds):
    ideal = raw * camera.fx  # (the test frames' rigs have no rolling shutter)
    return (ideal[:, 0], ideal[:, 1], pr.gid, pr.index, pr.clear, float(sigma_floor),
            int(rounds), E.EDGE_VARIANCE_INFLATION)  # fmt: skip


def _sample_args(roi, corners, off, half, step, trims, spacing):
    offs = np.arange(-half, half + 1e-9, step)
    return corners, off, offs, trims, float(spacing), E.MAX_PROFILES_PER_EDGE


def test_a_cold_frame_gives_the_same_vertices_compiled_or_not(monkeypatch):
    """End to end, a cold frame's vertices and covariance agree to 1e-9 px (tracked
    frames start from the frames before, where the two paths' last digits part: they
    agree to the estimator's own 1e-5 px)."""
    got = {}
    for flag in (False, True):
        out = []
        with _path(flag):
            for rig, img in _frames():
                pipe = TrianglePipeline(rig)
                pipe.process(Frame(0, 0.0, img))
                d = pipe.last_detection
                out.append((d.status, d.points_px, d.cov_n))
        got[flag] = out
    for (s0, p0, c0), (s1, p1, c1) in zip(got[False], got[True], strict=True):
        assert s0 is s1
        if p0 is not None and np.all(np.isfinite(p0)):
            assert np.abs(p0 - p1).max() < 1e-9
            assert np.abs(c0 - c1).max() <= 1e-9 * np.abs(c0).max()


def test_the_attitude_fit_compiled_or_not(monkeypatch):
    """The triangle's attitude fit with its height (estimate.rotation._fit_with_shift):
    its compiled Gauss-Newton (gn_shift) gives numpy's rotation, height, residuals and
    covariance (1e-12) in as many iterations, on the fits the test frames make, cold and
    tracked; and its Python source the compiled result."""
    from visvec.estimate import rotation

    calls = []
    real = rotation._fit_with_shift

    def record(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(rotation, "_fit_with_shift", record)
    for rig, img in _frames():
        pipe = TrianglePipeline(rig)
        for k in range(2):
            pipe.process(Frame(k, k / rig.fps, img))
    monkeypatch.undo()
    assert len(calls) >= 12  # (the heads' frames are refused before)
    for args in calls:
        fits = []
        for flag in (False, True):
            with _path(flag):
                fits.append(rotation._fit_with_shift(*args))
        a, b = fits
        assert a.iterations == b.iterations and a.converged == b.converged
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-12)
        assert abs(b.shift - a.shift) < 1e-9  # mm
        np.testing.assert_allclose(b.r, a.r, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.cov_p, a.cov_p, rtol=1e-9, atol=0)
        assert b.chi2 == pytest.approx(a.chi2, rel=1e-9, abs=1e-12)
    t_c, X, xy, W, R, prior = calls[0]
    tols = (rotation.MAX_ITERATIONS, rotation.STEP_TOL_RAD**2, rotation.STEP_TOL_SHIFT)
    kargs = (R, t_c, X, xy, W, prior.axis, float(prior.mean), 1.0 / prior.sigma**2, *tols)
    monkeypatch.setattr(KR, "_expmap", KR._expmap.py_func)
    assert _diff(KR.gn_shift(*kargs), KR.gn_shift.py_func(*kargs)) == 0.0


def test_visvec_pure_turns_the_kernels_off():
    """VISVEC_PURE=1 runs the numpy functions (a lab can compare, or rule Numba out)."""
    code = "from visvec._kernels import jit; print(jit.ON)"
    for value, expected in (("1", "False"), ("0", "True")):
        env = {**os.environ, "VISVEC_PURE": value}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, check=True).stdout.strip()  # fmt: skip
        assert out == expected


def test_numba_is_loaded_by_the_first_kernel_called():
    """Importing visvec does not import Numba; the first kernel called loads all of them
    at once (a kernel taken before then runs compiled too), and a Numba that does not
    import leaves the plain functions in place, the kernels off, with a line on
    stderr."""
    code = """if True:
        import sys
        import numpy as np
        from visvec._kernels import edge_fit as C, jit
        held = C.group_median
        print(type(C.positions).__name__, "numba" in sys.modules)
        if sys.argv[1] == "broken":
            sys.modules["numba"] = None  # an import that fails
        x = np.array([3.0, 1.0, 2.0, 5.0])
        out = held(x, np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), np.ones(4, np.bool_))
        plain = getattr(C.group_median, "py_func", C.group_median).__name__
        print(out.tolist(), type(C.positions).__name__, jit.ON, plain,
              held.dispatcher is (C.group_median if jit.ON else None))
    """
    outs = {}
    for case in ("numba", "broken"):
        r = subprocess.run([sys.executable, "-c", code, case], capture_output=True, text=True,
                           check=True)  # fmt: skip
        outs[case] = (r.stdout.splitlines(), r.stderr)
    lines, err = outs["numba"]
    assert lines[0] == "_Lazy False"
    assert lines[1] == "[2.0, 3.5, 0.0] CPUDispatcher True _group_median True"
    assert "did not import" not in err
    lines, err = outs["broken"]
    assert lines[0] == "_Lazy False"
    assert lines[1] == "[2.0, 3.5, 0.0] function False _group_median_numpy True"
    assert "Numba did not import" in err


@pytest.fixture
def unloadable(monkeypatch):
    """Nothing loaded yet and the kernels on; ``unloadable(name)`` makes that kernel
    fail as a Numba that cannot compile or cache here does. Every kernel's name is
    restored after (jit.off puts the plain functions in their places)."""

    def broken(*a, **k):
        raise RuntimeError("cannot cache function: no locator available")

    for names, name, _ in jit._KERNELS:
        monkeypatch.setitem(names, name, names[name])
    monkeypatch.setattr(W, "_warm", set())
    monkeypatch.setattr(jit, "ON", True)
    return lambda name: monkeypatch.setattr(_home(name), name, broken)


def test_kernels_that_do_not_load_leave_the_numpy_path_on(unloadable, capsys):
    """A Numba that cannot compile or cache here: the detector is made, says so once on
    stderr, and runs on numpy: the kernels written once for both paths (the attitude
    fit's) then run as Python, calling the plain functions they call."""
    from visvec.rotations import expmap_xyz

    unloadable("sample_geometry")
    rig = load_rig(CONFIGS / "triangle.toml")
    pipe = TrianglePipeline(rig)
    assert jit.ON is False
    assert (
        KR._expmap is expmap_xyz
        and KR._residuals_and_jacobian_shift is KR.residuals_and_jacobian_shift
    )
    err = capsys.readouterr().err
    assert "compiled edge fit did not load" in err and "no locator" in err
    rig_img = _frames()[0][1]
    assert pipe.process(Frame(0, 0.0, rig_img)).ok


def test_a_first_compilation_is_announced(monkeypatch, capsys):
    """Loading the kernels from the cache says nothing; compiling them (a first run on
    a machine, about half a minute) says so on stderr while it runs, once."""
    import time

    monkeypatch.setattr(W, "_warm", set())
    monkeypatch.setattr(jit, "ON", True)
    monkeypatch.setattr(W, "COMPILE_NOTICE_S", 0.05)
    W.warm_up()  # loaded (or compiled, on a first run): what it says is not checked here
    capsys.readouterr()
    slow = KO.readout_solve

    def compiling(*a):
        time.sleep(0.3)
        return slow(*a)

    monkeypatch.setattr(W, "_warm", set())
    monkeypatch.setattr(KO, "readout_solve", compiling)
    W.warm_up()
    err = capsys.readouterr().err
    assert err.count("compiling the triangle's kernels") == 1 and jit.ON
    monkeypatch.setattr(W, "_warm", set())
    monkeypatch.setattr(KO, "readout_solve", slow)
    monkeypatch.setattr(W, "COMPILE_NOTICE_S", 5.0)
    W.warm_up()
    assert "compiling" not in capsys.readouterr().err


def test_the_compilation_notice_is_said_only_without_a_cache(monkeypatch, capsys):
    """With Numba's cache of the kernels there, a load however slow within
    COMPILE_NOTICE_S (10 s: a busy machine loads in seconds) says nothing, as every
    later `check` and `batch` is; without it, the notice comes at once (issue 59)."""
    import time

    monkeypatch.setattr(jit, "ON", True)
    monkeypatch.setattr(W, "_warm", set())
    W.warm_up()
    capsys.readouterr()
    assert W._kernels_cached()  # the cache the first warm_up left (or found)
    slow = KO.readout_solve

    def loading(*a):
        time.sleep(2.0)  # longer than the old 1.5 s threshold
        return slow(*a)

    monkeypatch.setattr(KO, "readout_solve", loading)
    monkeypatch.setattr(W, "_warm", set())
    W.warm_up()
    assert "compiling" not in capsys.readouterr().err
    monkeypatch.setattr(KO, "readout_solve", slow)
    monkeypatch.setattr(W, "_kernels_cached", lambda *modules: False)
    monkeypatch.setattr(W, "_warm", set())
    W.warm_up()
    assert capsys.readouterr().err.count("compiling the triangle's kernels") == 1


def test_the_pixel_fits_kernels_load_with_a_rig_that_uses_it(unloadable, capsys):
    """A rig on the edge lines loads the edge fit's kernels only (a first run does not
    wait for the pixel fit's compilation); one with refine = "pixels" loads the pixel
    fit's too, and when those do not load the numpy path runs, said once."""
    unloadable("band_lines")
    rig = load_rig(CONFIGS / "triangle.toml")
    TrianglePipeline(rig)
    assert W._warm == {"edges"} and jit.ON is True
    TrianglePipeline(replace(rig, detect=replace(rig.detect, refine="pixels")))
    assert W._warm == {"edges", "pixels"} and jit.ON is False
    assert "did not load" in capsys.readouterr().err
    # the solve, written once, now runs as Python on the numpy twins of its loops
    assert KP.pixel_solve is KP._pixel_solve and KP._pixel_gn.__name__ == "_pixel_gn"
    assert KP._step_columns is KP._step_columns_numpy
    assert KP.noise_inflation is KP._noise_inflation_numpy
    pipe = TrianglePipeline(replace(rig, detect=replace(rig.detect, refine="pixels")))
    assert pipe.process(Frame(0, 0.0, _frames()[0][1])).ok


def test_the_numpy_path_for_a_while():
    """jit.numpy_path: the kernels off and every name its plain function (a loop's
    numpy twin where it has one) while it lasts; the compiled kernels back after."""
    KE.group_median(np.array([1.0]), np.array([0]), np.array([0]), np.ones(1, np.bool_))  # loaded
    compiled = (KP.pixel_solve, KP._residual_columns, KE.positions)
    with jit.numpy_path():
        assert jit.ON is False
        assert KP.pixel_solve is KP._pixel_solve
        assert KP._residual_columns is KP._residual_columns_numpy
        assert KE.positions is KE._positions
    assert jit.ON is True
    assert (KP.pixel_solve, KP._residual_columns, KE.positions) == compiled
    assert type(KP._residual_columns).__name__ == "CPUDispatcher"


def test_the_pixel_fits_noise_correlation_compiled_or_not():
    """The pixel fit's noise inflation (visvec._kernels.pixel_fit.noise_inflation)
    compiled and its numpy twin: the same, on white and on correlated noise, a pixel in
    two bands too; and the kernels run as Python give the compiled results."""
    import cv2

    from visvec.detect import photometric

    rng = np.random.default_rng(2)
    rows, cols = np.mgrid[0:200, 0:7]
    uv = np.column_stack([cols.ravel() + 3, rows.ravel() + 4]).astype(np.int64)
    uv = np.vstack([uv, uv[:30]])  # the first 30 pixels in a second band
    w = np.exp(-0.5 * ((uv[:, 0] - 6.0) / 1.1) ** 2)
    k = np.array([0.25, 0.5, 0.25])
    for noise in (
        rng.normal(size=(210, 14)),
        cv2.sepFilter2D(rng.normal(size=(210, 14)), -1, k, k),
    ):
        r = noise[uv[:, 1], uv[:, 0]]
        args = (uv, r, w, photometric._LAGS, photometric.NOISE_LAG_PX,
                photometric.NOISE_MIN_PAIRS)  # fmt: skip
        got = {}
        for flag in (False, True):
            with _path(flag):
                got[flag] = KP.noise_inflation(*args)
        assert got[True] == pytest.approx(got[False], rel=1e-12, abs=1e-12)
        assert got[False] == KP._noise_inflation_numpy(*args)
        assert _as_python(KP.noise_inflation)(*args) == pytest.approx(got[True], rel=1e-12)
    assert got[True] > 1.5  # the smoothed noise's
    index = np.full(40, 3, np.int32)
    index[[5, 6, 12]] = [0, 1, 2]
    args = (index, np.array([5, 6, 12]), np.array([1, 7]), np.array([1.0, 2.0, 3.0]),
            np.array([0.5, 1.0, 2.0]))  # fmt: skip
    pairs, rr, ww = KP._lag_sums(*args)
    assert pairs.tolist() == [1.0, 1.0] and rr.tolist() == [2.0, 3.0]
    assert _diff((pairs, rr, ww), KP._lag_sums.py_func(*args)) == 0.0


@pytest.fixture(scope="module")
def pixel_fits():
    """Every call the pipeline makes to the pixel fit (photometric.refine) on _frames()
    with refine = "pixels", cold and tracked (the numpy path's)."""
    from visvec.detect import photometric
    from visvec.detect import triangle as T

    got = []

    def spy(*a):
        got.append(a)
        return photometric.refine(*a)

    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(T, "refine", spy)
        for rig, img in _frames():
            rig = replace(rig, detect=replace(rig.detect, refine="pixels"))
            pipe = TrianglePipeline(rig)
            pipe.process(Frame(0, 0.0, img))
            pipe.process(Frame(1, 1 / 30, img))
    finally:
        mp.undo()
    return got


def test_the_pixel_fit_compiled_or_not(pixel_fits, monkeypatch):
    """The pixel fit on every call the frames make, compiled and on the numpy path: the
    same pixels, the same decisions, vertices within 1e-9 px, covariances within 1e-9
    of their size; its kernels run as Python give the compiled results; the parts
    written twice (loops and numpy twins) agree."""
    from visvec.detect import photometric as P

    assert len(pixel_fits) >= 10
    # the second frame of each pair starts from the run's blur the first one learned
    assert sum(a[7] is not None for a in pixel_fits) >= 5
    taken = 0
    for a in pixel_fits:
        got = {}
        for flag in (False, True):
            with _path(flag):
                got[flag] = P.refine(*a)
        pure, fast = got[False], got[True]
        assert pure.ok == fast.ok and pure.n_pixels == fast.n_pixels
        assert np.abs(pure.xy - fast.xy).max() < 1e-9
        if pure.ok:
            taken += 1
            assert np.abs(pure.cov - fast.cov).max() <= 1e-9 * np.abs(pure.cov).max()
            assert fast.inflation == pytest.approx(pure.inflation, rel=1e-9)
            assert fast.rms == pytest.approx(pure.rms, rel=1e-9)
    assert taken >= 8
    # under a rolling shutter (the pixels' coordinates unrolled, then the kernel's rule)
    from visvec.shutter import RollingShutter

    roll = (RollingShutter(25.0), np.radians([1.0, -2.0, 20.0]))
    got = {}
    for flag in (False, True):
        with _path(flag):
            got[flag] = P.refine(*pixel_fits[0][:5], *roll)
    assert got[True].ok and got[True].n_pixels == got[False].n_pixels
    assert np.abs(got[True].xy - got[False].xy).max() < 1e-9
    assert np.abs(got[True].xy - P.refine(*pixel_fits[0][:5]).xy).max() > 0.01  # unrolled
    # the kernels as Python, on the first call's bands
    image, normals, offsets, width, camera = pixel_fits[0][:5]
    n, V, c, w, _ = P._lines_and_bands(image, normals, offsets, width, camera)
    reach, clear = P.REACH_WIDTHS * w + P.REACH_PX, P.CLEAR_WIDTHS * w
    bands = P._band(image, n, c, reach, clear, camera)
    with _path(False):
        assert _diff(bands, P._band(image, n, c, reach, clear, camera)) == 0.0
    with monkeypatch.context() as mp:
        mp.setattr(KP, "band_lines", _as_python(KP.band_lines))
        assert _diff(bands, P._band(image, n, c, reach, clear, camera)) == 0.0
    # and through a lens with distortion (the bands' corners through its polynomial)
    lens = replace(camera, dist=np.array([-0.12, 0.03, 0.001, -0.002, 0.0]))
    got = {}
    for flag in (False, True):
        with _path(flag):
            got[flag] = P._band(image, n, c, reach, clear, lens)
    assert len(got[True][1]) > 1000 and _diff(got[True], got[False]) == 0.0
    assert type(got[True]) is type(got[False]) is KP.BandPixels
    x, y, _, counts = bands
    table = (P._PHI, P.PHI_RANGE, 1.0 / P.PHI_STEP)
    args = (x, y, counts, n, c, w, V.mean(axis=0), 50.0, P.GN_STEPS, *table)
    fast = KP._pixel_gn(*args)
    # the same named result from both (a NamedTuple Numba builds as a tuple)
    assert type(fast).__name__ == "GaussNewtonSteps" and fast.ok is True
    with _path(False):
        pure = KP._pixel_gn(*args)
    assert type(pure) is type(fast)
    for as_python, numpy_, compiled in zip(_as_python(KP._pixel_gn)(*args), pure, fast,
                                           strict=True):  # fmt: skip
        size = max(np.abs(np.asarray(numpy_, float)).max(), 1.0)
        assert np.abs(np.asarray(compiled, float) - np.asarray(numpy_, float)).max() <= 1e-9 * size
        # the loops run as Python are what Numba compiled (to rounding: the systems are
        # solved by numpy's LAPACK there, by the one Numba links here)
        assert _diff(as_python, compiled) <= 1e-12 * size
    # each per-pixel part against its numpy twin, on the buffers of a step
    m = len(y)
    outs = []
    for f in (KP._board_columns, KP._board_columns_numpy):
        buf = np.full(KP.N_EDGE * m, np.nan)
        f(x, counts, V.mean(axis=0), 50.0, buf)
        cols = [np.full(m, np.nan) for _ in range(5)]
        step = (KP._step_columns, KP._step_columns_numpy)[len(outs)]
        step(x, counts, n, c, w, buf, *cols[:3], *table)
        resid = (KP._residual_columns, KP._residual_columns_numpy)[len(outs)]
        rss = resid(y, counts, buf, *cols[:3], fast.level, w, *cols[3:])
        outs.append((buf, *cols, rss))
    assert np.isfinite(outs[0][0]).all() and _diff(outs[0][:-1], outs[1][:-1]) == 0.0
    assert outs[1][-1] == pytest.approx(outs[0][-1], rel=1e-12)
    # the whole solve: the first step on every other pixel of each band, then the checks,
    # the inflation and the vertices' covariance
    assert P.FIRST_STRIDE == 2 and P.GN_STEPS == 2
    xs, ys, cs = KP._strided_numpy(x, y, counts, 2)
    assert cs.tolist() == [(k + 1) // 2 for k in counts.tolist()] and len(ys) == cs.sum()
    assert _diff((xs, ys, cs), KP._strided(x, y, counts, 2)) == 0.0
    # and from a run's blur: one step on every pixel; from a blur 30 % off, more
    args = (x, y, bands[2], counts, n, c, w, V, V.mean(axis=0), 50.0)
    with _path(False):
        cold_start = KP.pixel_solve(*args, False, P.SETTINGS)
    steps = []
    for start, warm in ((w, False), (cold_start[3], True), (1.3 * cold_start[3], True)):
        args = (x, y, bands[2], counts, n, c, start, V, V.mean(axis=0), 50.0)
        steps.clear()
        with _path(False), monkeypatch.context() as mp:
            mp.setattr(KP, "_pixel_gn",
                       lambda *a, gn=KP._pixel_gn: steps.append(a[8]) or gn(*a))  # fmt: skip
            pure = KP.pixel_solve(*args, warm, P.SETTINGS)
        # (the first fit: a step on every other pixel, then one on every pixel)
        assert steps == ([1] * pure[6] if warm else [1, 1])
        assert pure[6] == (1 if start is cold_start[3] else 2 if warm else 1)
        for got in (KP.pixel_solve, _as_python(KP.pixel_solve)):
            fast = got(*args, warm, P.SETTINGS)
            assert type(fast) is type(pure) and type(pure).__name__ == "PixelSolve"
            assert fast.ok is True and pure.ok is True
            assert np.abs(fast[1] - pure[1]).max() < 1e-9
            assert np.abs(fast[2] - pure[2]).max() <= 1e-9 * np.abs(pure[2]).max()
            assert fast[4:] == pytest.approx(pure[4:], rel=1e-9)
        # each start reaches the same vertices, well within their sigma
        sd = np.sqrt(np.diag(pure[2]))
        assert np.abs((pure[1] - cold_start[1]).ravel() / sd).max() < 0.3
    # a band whose residuals are three times the others' is not taken, on either path
    y3 = y.copy()
    y3[: counts[0]] += np.random.default_rng(1).normal(0.0, 6.0, counts[0])
    args = (x, y3, bands[2], counts, n, c, w, V, V.mean(axis=0), 50.0, False, P.SETTINGS)
    for flag in (False, True):
        with _path(flag):
            fit = KP.pixel_solve(*args)
        assert bool(fit.ok) is False and np.array_equal(fit[1], V)


def test_the_bands_cover_compiled_or_not():
    """The pixels the pixel fit's quadrilaterals cover (visvec._kernels.pixel_fit.cover),
    compiled and its numpy twin: the same, in raster order, each once; quadrilaterals that overlap,
    a side along a row, one outside the box (none of it covered); and every pixel whose
    centre a quadrilateral holds is among them."""

    rng = np.random.default_rng(5)
    shapes = 0
    for trial in range(40):
        centre = rng.uniform(20, 60, (3, 1, 2))
        q = centre + rng.uniform(-15, 15, (3, 4, 2))
        # convex: the corners in angle order about their mean
        for i in range(3):
            d = q[i] - q[i].mean(axis=0)
            q[i] = q[i][np.argsort(np.arctan2(d[:, 1], d[:, 0]))]
        if trial % 4 == 1:
            q[0, 1, 1] = q[0, 0, 1]  # a side along a row
        if trial % 4 == 2:
            q[2] += 500.0  # outside the box
        q = q.reshape(12, 2)
        box = (0, 0, 99, 89)
        fast = KP.cover(q, *box)
        assert np.array_equal(fast, KP._cover_numpy(q, *box))
        assert np.array_equal(fast, KP.cover.py_func(q, *box))
        assert len(np.unique(fast, axis=0)) == len(fast)
        assert np.array_equal(fast, fast[np.lexsort((fast[:, 0], fast[:, 1]))])
        assert fast[:, 0].min() >= 0 and fast[:, 0].max() <= 99 and fast[:, 1].max() <= 89
        covered = np.zeros((90, 100), bool)
        covered[fast[:, 1], fast[:, 0]] = True
        v, u = np.mgrid[0:90, 0:100]
        for quad in q.reshape(3, 4, 2):
            # inside a convex quadrilateral: on the same side of its four sides
            side = [(b[0] - a[0]) * (v - a[1]) - (b[1] - a[1]) * (u - a[0])
                    for a, b in zip(quad, np.roll(quad, -1, axis=0), strict=True)]  # fmt: skip
            inside = np.all(np.array(side) >= 0, axis=0) | np.all(np.array(side) <= 0, axis=0)
            assert covered[inside].all()
            shapes += int(inside.sum())
    assert shapes > 1000
