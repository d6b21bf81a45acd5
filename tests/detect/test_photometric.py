"""The pixel fit of the triangle's edges (visvec.detect.photometric, `refine = "pixels"`):
more precise than the edge lines, an honest covariance, and refused where it disagrees
with them."""

import contextlib
from dataclasses import replace

import cv2
import numpy as np

from visvec._kernels import jit
from visvec._kernels import pixel_fit as KP
from visvec.data import Status
from visvec.detect import TriangleDetector
from visvec.detect import triangle as tri
from visvec.detect.edges import fit_edges, intersect
from visvec.detect.photometric import _intersections, refine
from visvec.geometry import project_target
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from conftest import attitudes


def _pixels(rig):
    return replace(rig, detect=replace(rig.detect, refine="pixels"))


def _pixels_against_lines(rig, frames):
    """Both fits on ``frames`` ((R, image) pairs): the vertices' error RMS of each
    (normalised image units) and the error-over-sigma RMS of the pixel fit's."""
    dets = {k: TriangleDetector(r) for k, r in (("lines", rig), ("pixels", _pixels(rig)))}
    err = {k: [] for k in dets}
    z = []
    for R, img in frames:
        truth = rig.camera.undistort(project_target(rig, R))
        for name, det in dets.items():
            d = det.detect(img)
            assert d.status is Status.OK, d.reason
            e = (d.points_n - truth).ravel()
            err[name].append(e)
            if name == "pixels":
                z.append(e / np.sqrt(np.diag(d.cov_n)))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    return rms, float(np.sqrt(np.mean(np.square(z))))


def test_pixel_fit_is_more_precise_than_the_lines_and_its_sigma_is_honest(rig320):
    """Ten attitudes, four noise draws each, 320x240: the vertices of the pixel fit err
    about 0.75x as much as the edge lines' (benchmarks/triangle_crb.py: at 1.0-1.25x
    the Cramér-Rao bound against the lines' 1.35-1.9x), and their error over their
    sigma has unit RMS."""
    frames = [
        (R, render_frame(rig320, R, Scene(), rng=700 + 10 * k + j))
        for k, R in enumerate(attitudes(10, 21))
        for j in range(4)
    ]
    rms, zr = _pixels_against_lines(rig320, frames)
    assert rms["pixels"] < 0.85 * rms["lines"], rms
    assert 0.8 < zr < 1.2, zr


def test_a_lens_falloff_is_in_the_level_model(rig320):
    """A lens darkening toward the corners (vignetting: 35 % at the corners, nothing
    else of a webcam's chain): the pixel fit's levels carry its radial term, so its
    vertices stay more precise than the edge lines' and their error over their sigma
    keeps unit RMS (0.67x the lines' error, 0.92 RMS; with the levels only planes, as
    before, 1.0x and 1.16)."""
    from visvec.sim.webcam import WebcamChain

    chain = WebcamChain(vignetting=0.35, gain_sigma=0.0, bayer=False, chromatic_aberration=0.0,
                        hot_pixels=0.0, srgb=False, jpeg_quality=0)  # fmt: skip
    frames = [
        (R, render_frame(rig320, R, Scene(webcam=replace(chain, seed=k)), rng=900 + k))
        for k, R in enumerate(attitudes(12, 23))
    ]
    rms, zr = _pixels_against_lines(rig320, frames)
    assert rms["pixels"] < 0.85 * rms["lines"], rms
    assert 0.7 < zr < 1.3, zr


def test_a_pixel_fit_that_disagrees_with_the_lines_is_not_taken(rig320):
    """The lines are robust, the pixel fit is not: vertices that the pixel fit moved by
    more than the lines' covariance allows are the lines' own, and those that agree are
    the pixel fit's."""
    R = attitudes(1, 5)[0]
    img = render_frame(rig320, R, Scene(), rng=3)
    # the edge fit from the true corners (a detector's coarse corners would do)
    fit = fit_edges(img, project_target(rig320, R), rig320.camera)
    xy, cov = intersect(fit)
    pf = refine(img, fit.normals, fit.offsets, fit.width, rig320.camera)
    assert pf.ok
    got, got_cov, taken = tri._pixel_fit(img, fit, xy, cov, rig320.camera)
    np.testing.assert_array_equal(got, pf.xy)
    np.testing.assert_array_equal(got_cov, pf.cov)
    np.testing.assert_array_equal(taken.width, pf.width)
    # lines 8 sigma away from what the pixels say: the pixel fit is refused
    far = xy + 8.0 * np.sqrt(np.diag(cov)).reshape(3, 2)
    got, got_cov, taken = tri._pixel_fit(img, fit, far, cov, rig320.camera)
    np.testing.assert_array_equal(got, far)
    np.testing.assert_array_equal(got_cov, cov)
    assert taken is False


def test_the_vertices_gain_is_the_lines_derivative():
    rng = np.random.default_rng(1)
    ang = np.array([0.3, 2.4, 4.4])
    n = np.column_stack([np.cos(ang), np.sin(ang)])
    c = rng.normal(size=(3, 2)) * 5.0
    V, _ = _intersections(n, c)
    found, V_, G = KP._vertices_and_gain(n, c)
    assert found and np.abs(V_ - V).max() < 1e-12
    h = 1e-7
    for i in range(3):
        for k in range(2):
            n2, c2 = n.copy(), c.copy()
            if k == 0:
                cs, sn = np.cos(h), np.sin(h)
                n2[i] = [cs * n[i, 0] - sn * n[i, 1], sn * n[i, 0] + cs * n[i, 1]]
            else:
                c2[i] = c[i] + h * n[i]
            num = (_intersections(n2, c2)[0] - V).ravel() / h
            np.testing.assert_allclose(G[:, 2 * i + k], num, atol=1e-5)
    # two lines parallel: no vertices
    n[1] = -n[0]
    assert KP._vertices_and_gain(n, c)[0] is False


BAND_ROWS = 300  # a band of 300 x 6 px (an edge's band at 640x480 holds ~1300)


def _band_of(noise: np.ndarray):
    """A 6 px wide band down a column of ``noise`` (the residuals), the offset
    derivatives a blurred edge's across it: (uv, r, w) as refine hands them on."""
    rows, cols = np.mgrid[0:BAND_ROWS, 0:6]
    uv = np.column_stack([cols.ravel() + 10, rows.ravel() + 5])
    w = np.exp(-0.5 * ((cols.ravel() - 2.5) / 0.9) ** 2)
    return uv, noise[uv[:, 1], uv[:, 0]], w


def _smoothed(rng, shape):
    """Gaussian noise smoothed by (1, 2, 1) / 4 along both axes: correlated at lags 1-2,
    the 1-D autocorrelation (1, 4, 6, 4, 1) / 6 at lags -2..2."""
    k = np.array([0.25, 0.5, 0.25])
    return cv2.sepFilter2D(rng.normal(size=shape), -1, k, k, borderType=cv2.BORDER_REFLECT)


def test_white_noise_leaves_the_covariance_and_correlated_noise_widens_it():
    """The inflation is about 1 for independent pixels and matches what a codec-like
    smoothing of the noise does to a weighted sum of it (its true variance over the
    white-noise formula)."""
    from visvec.detect import photometric as P

    def _noise_inflation(uv, r, w):
        return KP.noise_inflation(uv, r, w, P._LAGS, P.NOISE_LAG_PX, P.NOISE_MIN_PAIRS)

    rng = np.random.default_rng(4)
    shape = (BAND_ROWS + 20, 30)
    white = [_noise_inflation(*_band_of(rng.normal(size=shape))) for _ in range(20)]
    assert 1.0 <= np.mean(white) < 1.08 and max(white) < 1.2, white
    smooth = [_noise_inflation(*_band_of(_smoothed(rng, shape))) for _ in range(20)]
    # the true ratio: sum over lags of the noise's correlation times the weights'
    # overlap at that lag, over the weights' sum of squares
    rho = np.array([1, 4, 6, 4, 1]) / 6.0
    w = _band_of(np.zeros(shape))[2].reshape(BAND_ROWS, 6)
    num = 0.0
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            a = w[max(dy, 0) : BAND_ROWS + min(dy, 0), max(dx, 0) : 6 + min(dx, 0)]
            b = w[max(-dy, 0) : BAND_ROWS - max(dy, 0), max(-dx, 0) : 6 - max(dx, 0)]
            num += rho[dy + 2] * rho[dx + 2] * np.sum(a * b)
    true = num / np.sum(w * w)
    assert true > 3.0
    assert abs(np.mean(smooth) / true - 1.0) < 0.1, (np.mean(smooth), true)


def test_pixel_fit_sigma_is_honest_under_correlated_noise(rig320, monkeypatch):
    """Frames whose noise is shared between neighbouring pixels (as a codec's is): the
    pixel fit's error over its sigma keeps a unit RMS; taken as white, it was 1.5-2x."""
    from visvec.sim.render import render_clean

    rng = np.random.default_rng(9)
    cases = []
    for R in attitudes(8, 77):
        clean = cv2.GaussianBlur(render_clean(rig320, R, Scene()), (0, 0), 0.6)
        truth = rig320.camera.undistort(project_target(rig320, R))
        for _ in range(2):
            z = _smoothed(rng, clean.shape)
            img = np.clip(np.rint(clean + 2.0 * z / z.std()), 0, 255).astype(np.uint8)
            cases.append((img, truth))

    def z_rms():
        det = TriangleDetector(_pixels(rig320))
        z = []
        for img, truth in cases:
            det.reset()
            d = det.detect(img)
            assert d.status is Status.OK, d.reason
            z.append((d.points_n - truth).ravel() / np.sqrt(np.diag(d.cov_n)))
        return float(np.sqrt(np.mean(np.square(z))))

    honest = z_rms()
    # the noise taken as white: the solve run as Python (the compiled one, tested equal
    # to it in tests/detect/test_compiled.py, is compiled against the kernel) without
    # the inflation
    with jit.numpy_path(), monkeypatch.context() as mp:
        mp.setattr(KP, "noise_inflation", lambda *a: 1.0)
        white = z_rms()
    assert 0.75 < honest < 1.3, honest
    assert white > 1.3 * honest, (white, honest)


def test_a_run_takes_its_learned_noise_inflation(rig320, monkeypatch):
    """Frames through the same correlated noise: once INFLATION_MIN_FRAMES pixel fits
    have been taken, a fit whose own inflation is a draw of the run's carries the run's
    in its covariance (its own scaled by their ratio), learned from the taken fits'
    own estimates and kept through a reset; a fit whose own estimate lies far beyond
    the run's (residuals with a structure of their own) keeps its own."""
    from visvec.noise import INFLATION_MIN_FRAMES
    from visvec.sim.render import render_clean

    rng = np.random.default_rng(12)
    det = TriangleDetector(_pixels(rig320))
    seen = []
    real = tri.refine

    def spy(*a):
        pf = real(*a)
        seen.append(pf)
        return pf

    monkeypatch.setattr(tri, "refine", spy)
    for R in attitudes(10, 31):
        clean = cv2.GaussianBlur(render_clean(rig320, R, Scene()), (0, 0), 0.6)
        z = _smoothed(rng, clean.shape)
        det.reset()
        seen.clear()
        d = det.detect(np.clip(np.rint(clean + 2.0 * z / z.std()), 0, 255).astype(np.uint8))
        assert d.status is Status.OK, d.reason
        own, taken = seen[-1], det._pixel
        assert taken is not False and taken.inflation == own.inflation
        if det.inflation.frames <= INFLATION_MIN_FRAMES:  # (this frame's fit learned)
            assert taken.run_inflation is None
            np.testing.assert_array_equal(taken.cov, own.cov)
        else:
            run = taken.run_inflation
            assert run is not None and run != own.inflation
            np.testing.assert_allclose(taken.cov, own.cov * run / own.inflation, rtol=1e-12)
    assert det.inflation.frames == 10 and 1.5 < det.inflation.value < 5.0
    # a fit whose own estimate is far beyond the run's keeps its own
    far = det.inflation.value + 10.0 * det.inflation.scatter + 1.0
    pf = replace(seen[-1], inflation=far, cov=seen[-1].cov * far / seen[-1].inflation)
    monkeypatch.setattr(tri, "refine", lambda *a: pf)
    out = tri._pixel_fit(None, _FitStub(), pf.xy, 100.0 * pf.cov, rig320.camera,
                         inflation=det.inflation)  # fmt: skip
    assert out[2] is pf and out[2].run_inflation is None


class _FitStub:
    """The edge fit's fields _pixel_fit hands to refine (stubbed in the test above)."""

    normals = offsets = width = None


def test_a_pixel_fit_wider_than_the_lines_is_not_taken(rig320, monkeypatch):
    """A pixel fit that agrees with the lines but whose covariance is the wider (its
    residuals' own structure inflated it): the lines stand."""
    R = attitudes(1, 5)[0]
    img = render_frame(rig320, R, Scene(), rng=3)
    fit = fit_edges(img, project_target(rig320, R), rig320.camera)
    xy, cov = intersect(fit)
    pf = refine(img, fit.normals, fit.offsets, fit.width, rig320.camera)
    wide = replace(pf, cov=pf.cov * 4.0 * np.trace(cov) / np.trace(pf.cov))
    monkeypatch.setattr(tri, "refine", lambda *a: wide)
    got, got_cov, taken = tri._pixel_fit(img, fit, xy, cov, rig320.camera)
    np.testing.assert_array_equal(got, xy)
    np.testing.assert_array_equal(got_cov, cov)
    assert taken is False  # nothing for the run's blur to learn from


def test_the_runs_blur_starts_the_fit_and_follows_a_refocus(rig640, monkeypatch):
    """After a run's first pixel fit each fit starts from the run's blur width (the
    fits' widths averaged), kept through a reset (a property of the lens), and takes one
    step on every pixel where that width holds; a lens refocused from a blur of 0.6 px
    to 1.5 px: the first fit after it takes more steps, the run's blur is then its, and
    the next fits take one step again; every row within its sigma. A lines rig learns
    none."""
    starts = []
    refine_ = tri.refine

    def spy(*a):
        pf = refine_(*a)
        starts.append((a[7], pf.steps))
        return pf

    monkeypatch.setattr(tri, "refine", spy)
    det = TriangleDetector(_pixels(rig640))
    z, blurs, steps = [], [], []
    for k, R in enumerate(attitudes(8, 31)):
        scene = Scene(blur_sigma_px=0.6 if k < 4 else 1.5)
        det.reset()
        d = det.detect(render_frame(rig640, R, scene, rng=900 + k))
        assert d.status is Status.OK, d.reason
        truth = rig640.camera.undistort(project_target(rig640, R))
        z.append((d.points_n - truth).ravel() / np.sqrt(np.diag(d.cov_n)))
        blurs.append(det._blur)
        assert starts[-1][0] == (blurs[-2] if k else None)
        steps.append(starts[-1][1])
    # the first fit: a strided step and one on every pixel; then one from the run's blur
    # (a second where an edge's own width is more than 10 % off the three's median);
    # the refocus: three
    assert steps[0] == 1 and steps[1] == 1 and steps[4] == 3, steps
    assert sum(s == 1 for s in steps[5:]) >= 2, steps
    # the model's width of a 0.6 px blur: sqrt(0.6^2 + 1/12) = 0.67 px
    assert 0.6 < blurs[3] < 0.75
    assert 1.4 < blurs[4] < 1.6
    assert np.abs(z).max() < 4.5
    # a pixel fit not taken (the lines stand) clears the run's blur: the next fit starts
    # from the lines' widths
    monkeypatch.setattr(tri, "_pixel_fit", lambda *a: (a[2], a[3], False))
    det.reset()
    assert det.detect(render_frame(rig640, attitudes(1, 31)[0], Scene(), rng=2)).status is Status.OK
    assert det._blur is None
    lines = TriangleDetector(rig640)
    img = render_frame(rig640, attitudes(1, 31)[0], Scene(), rng=1)
    assert lines.detect(img).status is Status.OK
    assert lines._blur is None


def test_a_band_with_something_else_in_it_is_not_fitted(rig320):
    """A head just off the base edge (benchmarks/triangle_robustness.py's 320x240
    occluder frame 4): the lines carry it as a wider scatter, the pixel fit's residuals
    there are three times the other bands' and it is not taken; the row is the lines'."""
    from visvec.sim.scene import Occluder

    R = euler_to_matrix(*np.radians([-81.15372407, 1.56117027, -4.8532397]))
    sc = Scene(occluder=Occluder(-199.67, 11.26, 1484.17, 105.59, 73.18))
    found = []
    for seed in (100004, 1, 2, 3):
        img = render_frame(rig320, R, sc, rng=seed)
        det = TriangleDetector(rig320)
        d = det.detect(img)
        if d.status is not Status.OK:
            continue
        fit = fit_edges(img, d.points_px, rig320.camera)
        pf = refine(img, fit.normals, fit.offsets, fit.width, rig320.camera)
        assert not pf.ok
        found.append(seed)
    assert 100004 in found  # the benchmark's frame


def _band_by_rule(image, n, c, reach, clear, camera):
    """photometric._band's pixels by its rule alone, every pixel of the frame checked:
    within an edge's reach and clear inside the other two, edge after edge, each edge's
    in raster order (their places (column, row) and counts)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    x = camera.undistort(uv) * camera.fx
    d = x @ n.T - np.einsum("ij,ij->i", n, c)
    keeps = [(np.abs(d[:, i]) < reach[i]) & (d[:, (i + 1) % 3] > clear[(i + 1) % 3])
             & (d[:, (i + 2) % 3] > clear[(i + 2) % 3]) for i in range(3)]  # fmt: skip
    return np.concatenate([uv[k] for k in keeps]), [int(k.sum()) for k in keeps]


def test_the_bands_are_every_pixel_the_rule_takes(rig320, monkeypatch):
    """The pixels each edge's band fits are exactly those its rule takes anywhere in the
    frame (the quadrilaterals only narrow the search: none is missed at their sides),
    through a pinhole and through a strong barrel distortion, compiled and from numpy;
    the ideal coordinates are the lens model's."""
    from visvec.detect import photometric as P

    cams = [rig320.camera, replace(rig320.camera, dist=np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))]
    tried = []
    for cam, R in zip(cams * 3, attitudes(6, 8, 4.0), strict=True):
        xy = project_target(rig320, R)
        if not np.all(cam.in_image(cam.distort(cam.undistort(xy)), 5.0)):
            continue
        V = cam.undistort(xy) * cam.fx  # the ideal vertices: lines through their pairs
        t = V[[2, 0, 1]] - V[[1, 2, 0]]
        n = np.column_stack([-t[:, 1], t[:, 0]]) / np.linalg.norm(t, axis=1)[:, None]
        n *= np.sign(np.einsum("ij,ij->i", n, V - V[[1, 2, 0]]))[:, None]  # inward
        c = 0.5 * (V[[1, 2, 0]] + V[[2, 0, 1]])
        w = np.array([0.7, 0.9, 1.4])
        reach, clear = P.REACH_WIDTHS * w + P.REACH_PX, P.CLEAR_WIDTHS * w
        image = np.arange(cam.width * cam.height, dtype=np.uint32).reshape(cam.height, -1)
        image = (image % 251).astype(np.uint8)
        want, counts = _band_by_rule(image, n, c, reach, clear, cam)
        for path in (jit.numpy_path(), contextlib.nullcontext()):
            with path:
                x, grey, uv, got_counts = P._band(image, n, c, reach, clear, cam)
            assert got_counts.tolist() == counts and sum(counts) > 300
            assert np.array_equal(uv, want)
            assert np.array_equal(grey, image[uv[:, 1], uv[:, 0]].astype(float))
            assert np.abs(x - cam.undistort(uv.astype(float)) * cam.fx).max() < 1e-3
        tried.append(cam.has_distortion)
    assert tried.count(True) >= 2 and tried.count(False) >= 2


def test_the_step_and_its_slope_from_the_table_are_the_normal_cdf_and_density():
    """The pixel fit's Phi and phi (cubic Hermite between table nodes 1/16 apart) are
    the standard normal CDF and density to 1e-7 everywhere, beyond the table's range
    too; the compiled kernel's are the same numbers."""
    from scipy.special import ndtr

    from visvec.detect import photometric as P

    u = np.concatenate([np.linspace(-12.0, 12.0, 20001), [-8.0, 8.0, 0.0]])
    step, slope = P._phi_of(u)
    assert np.abs(step - ndtr(u)).max() < 1e-7
    assert np.abs(slope - np.exp(-0.5 * u * u) / np.sqrt(2.0 * np.pi)).max() < 1e-7
    # between the nodes the error is not zero: the table is interpolated, not looked up
    assert np.abs(step - ndtr(u)).max() > 1e-10
    kernel = getattr(KP._phi_of, "py_func", KP._phi_of)
    for k in range(0, len(u), 997):
        got = kernel(float(u[k]), P._PHI, P.PHI_RANGE, 1.0 / P.PHI_STEP)
        assert got == (step[k], slope[k])
