"""Star-field angular rate: estimators, the pipeline on rendered frames, bad input, CLI."""

import csv
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.data import Frame, Status
from visvec.detect.stars import find_stars
from visvec.errors import ConfigError
from visvec.estimate.rate import estimate_rate, rate_budget
from visvec.pipeline import RatePipeline, make_pipeline
from visvec.rig import load_rig, rig_from_dict
from visvec.rotations import expmap
from visvec.sim.stars import PAPER_CASES, StarScene, make_sky, random_pointing, star_image

from conftest import CONFIGS

# a half-resolution version of the paper's camera (same field, IFOV 0.034 deg) keeps the
# rendering fast; the full camera is measured in benchmarks/
SMALL = {
    "camera": {
        "width": 640, "height": 512, "fx": 1685.0, "fy": 1685.0, "cx": 319.5, "cy": 255.5,
        "fps": 10.0, "exposure_ms": 50.0,
    },
    "mount": {"on": "platform", "position_mm": [0, 0, 0], "rotation": np.eye(3).tolist()},
    "target": {"kind": "starfield", "max_rate_dps": 6.0},
}  # fmt: skip


@pytest.fixture(scope="module")
def srig():
    return rig_from_dict(SMALL)


def sequence(rig, rate_dps, n, seed=0, scene=None, extra=None):
    """n frames at 10 Hz turning at rate_dps; ``extra(i, sig)`` may add light."""
    rng = np.random.default_rng(seed)
    sky = make_sky(rng)
    R0 = random_pointing(rng)
    w = np.radians(rate_dps)
    scene = scene or StarScene(flux_m6=120.0)
    out = []
    for i in range(n):
        t = i / rig.fps
        add = (lambda s, i=i: extra(i, s)) if extra else None
        out.append(Frame(i, t, star_image(rig, R0 @ expmap(w * t), w, sky, scene, rng, add)))
    return out


def unit(n, rng, half_fov=0.18):
    v = np.column_stack([rng.uniform(-half_fov, half_fov, (n, 2)), np.ones(n)])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ------------------------------------------------------------------ estimators


@pytest.mark.parametrize("method", ["poisson", "crassidis"])
def test_exact_vectors_give_the_rate_and_its_sign(method, rng):
    w = np.radians([1.0, -0.5, 3.0])
    u1 = unit(30, rng)
    u2 = u1 @ expmap(-w * 0.1).T  # stars fixed in space: u_C(t + dt) = exp(-[w]x dt) u_C(t)
    sol = estimate_rate(u1[:, :2] / u1[:, 2:], u2[:, :2] / u2[:, 2:], 0.1, 3370.0, 0.05, method)
    assert sol.ok
    np.testing.assert_allclose(sol.omega, w, atol=1e-6)


def test_crassidis_is_exact_at_large_rotations_where_poisson_is_not(rng):
    w = np.radians([40.0, 0.0, 60.0])  # 7 deg per frame: a tumble at 10 Hz
    u1 = unit(40, rng)
    u2 = u1 @ expmap(-w * 0.1).T
    xy1, xy2 = u1[:, :2] / u1[:, 2:], u2[:, :2] / u2[:, 2:]
    p = estimate_rate(xy1, xy2, 0.1, 3370.0, 0.05, "poisson")
    c = estimate_rate(xy1, xy2, 0.1, 3370.0, 0.05, "crassidis")
    err_p = np.linalg.norm(p.omega - w) / np.linalg.norm(w)
    err_c = np.linalg.norm(c.omega - w) / np.linalg.norm(w)
    assert err_c < 1e-9
    assert 1e-5 < err_p < 1e-2  # the finite difference's second-order error


def test_outliers_are_dropped_and_the_covariance_is_honest(rng):
    w = np.radians([1.0, 0.2, -2.0])
    f, sig_px = 3370.0, 0.1
    z = []
    for _ in range(200):
        u1 = unit(40, rng)
        u2 = u1 @ expmap(-w * 0.1).T
        xy1 = u1[:, :2] / u1[:, 2:] + rng.normal(0, sig_px / f, (40, 2))
        xy2 = u2[:, :2] / u2[:, 2:] + rng.normal(0, sig_px / f, (40, 2))
        xy2[:4] += rng.uniform(5, 20, (4, 2)) / f  # four wrong matches
        sol = estimate_rate(xy1, xy2, 0.1, f, 0.01, "poisson")
        assert sol.ok and not sol.inliers[:4].any() and sol.inliers[4:].mean() > 0.9
        z.append((sol.omega - w) / np.sqrt(np.diag(sol.cov)))
    s = np.std(z, axis=0)
    assert np.all((s > 0.8) & (s < 1.25)), s


@pytest.mark.parametrize("method", ["poisson", "crassidis"])
def test_weighting_stars_by_their_noise_beats_equal_weights_and_stays_honest(method, rng):
    # stars 0.02 to 0.6 px noisy (bright to faint): weights 1 / variance win, and the
    # covariance from the variances matches the scatter
    w = np.radians([0.5, -1.0, 2.0])
    f, n = 3370.0, 40
    sig = np.geomspace(0.02, 0.6, n)
    var = sig**2  # per axis, both centroids together
    err_w, err_u, z = [], [], []
    for _ in range(300):
        u1 = unit(n, rng)
        u2 = u1 @ expmap(-w * 0.1).T
        xy1 = u1[:, :2] / u1[:, 2:] + rng.normal(0, 1, (n, 2)) * sig[:, None] / np.sqrt(2) / f
        xy2 = u2[:, :2] / u2[:, 2:] + rng.normal(0, 1, (n, 2)) * sig[:, None] / np.sqrt(2) / f
        a = estimate_rate(xy1, xy2, 0.1, f, 0.001, method, var)
        b = estimate_rate(xy1, xy2, 0.1, f, 0.001, method)
        assert a.ok and b.ok
        err_w.append(a.omega - w)
        err_u.append(b.omega - w)
        z.append((a.omega - w) / np.sqrt(np.diag(a.cov)))
    assert np.all(np.std(err_w, axis=0) < 0.6 * np.std(err_u, axis=0))
    s = np.std(z, axis=0)
    assert np.all((s > 0.8) & (s < 1.2)), s


def test_window_centroid_variance_matches_the_scatter_of_noisy_stars(rng):
    from visvec.detect.flow import window_centroid

    # a Gaussian star (sigma 1.2 px, flux 400) on noise sigma 2, thresholded at 0 after
    # subtracting 3 sigma, as in the paper's background removal
    yy, xx = np.mgrid[0:21, 0:21]
    star = 400.0 / (2 * np.pi * 1.44) * np.exp(-((xx - 10.3) ** 2 + (yy - 9.8) ** 2) / 2.88)
    cents, pred = [], []
    for _ in range(2000):
        img = star + rng.normal(0, 2.0, star.shape)
        sig = np.clip(img - 6.0, 0, None).astype(np.float32)
        u, v, _, spread = window_centroid(sig, 5, 5, 16, 16)
        cents.append((u, v))
        pred.append(4.0 * spread / 2.0)  # sigma^2 * spread, per axis
    ratio = np.std(cents, axis=0) / np.sqrt(np.mean(pred))
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio  # measured 0.87-0.93


def test_too_few_or_inconsistent_matches_give_no_rate(rng):
    u1 = unit(4, rng)
    sol = estimate_rate(u1[:, :2], u1[:, :2], 0.1, 3370.0, 0.05)
    assert not sol.ok and sol.reason == "too_few_matches"
    xy1 = unit(20, rng)[:, :2]
    xy2 = unit(20, rng)[:, :2]  # random pairs: no common motion
    sol = estimate_rate(xy1, xy2, 0.1, 3370.0, 0.05)
    assert not sol.ok and sol.reason == "no_consistent_motion"


def test_error_budget_matches_the_paper():
    # Fasano et al. Sec. 2.3: 10 Hz, 10 px per star, 40 stars; Figure 4 spans about
    # 0.0035 to 0.035 deg/s over its IFOV range, and wz is 1/chi times worse
    b = rate_budget(0.017, 10.0, 40, 10, 5.0)
    assert b.cross == pytest.approx(np.sqrt(2) * 0.017 / (0.1 * np.sqrt(400)))
    assert b.boresight == pytest.approx(b.cross / np.radians(5.0))
    assert rate_budget(0.005, 10.0, 40, 10, 5.0).cross == pytest.approx(0.0035, rel=0.05)
    assert b.boresight_full == pytest.approx(b.boresight)
    assert rate_budget(0.017, 10.0, 40, 10, 5.0, 5.0).boresight_full > b.boresight


# ------------------------------------------------------------------ pipeline


@pytest.mark.parametrize("case", [1, 4])
def test_pipeline_measures_the_paper_cases_within_sigma(srig, case):
    frames = sequence(srig, PAPER_CASES[case], 12, seed=case)
    rows = list(make_pipeline(srig).run(frames))
    assert rows[0].status is Status.NO_TARGET and "first_frame" in rows[0].warnings
    ok = [r for r in rows[1:] if r.ok]
    assert len(ok) == 11
    E = np.array([r.w_dps - PAPER_CASES[case] for r in ok])
    S = np.array([r.sigma_dps for r in ok])
    assert np.all(np.abs(E) < 4.5 * S)
    assert np.all(S[:, 2] > 3 * S[:, 0])  # about the boresight is the weak axis


def test_tracking_takes_up_stars_entering_through_the_edges(srig):
    # 4 deg/s about x moves the sky 24 px per frame across the 640 x 512 half-size
    # camera: stars found in the edge bands while tracking must be matched and used
    frames = sequence(srig, (4.0, 0.0, 0.0), 14, seed=3, scene=StarScene(flux_m6=300.0))
    pipe = RatePipeline(srig)
    entered = 0
    for f in frames:
        prev = pipe.prev
        row = pipe.process(f)
        det = pipe.last_detection
        if prev is None or prev.stars.windowed is None or det.matches is None:
            continue
        assert row.ok
        used = det.matches.index[det.inliers]
        entered += int(np.sum(~prev.stars.windowed[used]))
    assert entered >= 3


def test_rows_have_the_spec_columns(srig):
    rows = list(make_pipeline(srig).run(sequence(srig, PAPER_CASES[3], 3)))
    d = rows[2].as_dict()
    assert list(d) == list(RatePipeline.row_type.columns)
    assert d["status"] == "ok" and d["n_points"] >= 10
    assert rows[0].as_dict()["wx_dps"] is None


def test_dark_frame_gives_too_few_stars_and_no_rate(srig):
    dark = np.full((512, 640), 10, np.uint8)
    pipe = make_pipeline(srig)
    frames = sequence(srig, PAPER_CASES[1], 2)
    rows = [pipe.process(f) for f in (frames[0], Frame(1, 0.1, dark), frames[1])]
    assert rows[1].status is Status.NO_TARGET and "too_few_stars" in rows[1].warnings
    # the dark frame broke the pair: the next frame starts again
    assert rows[2].status is Status.NO_TARGET and "first_frame" in rows[2].warnings


def test_frame_jump_gives_no_rate(srig):
    frames = sequence(srig, PAPER_CASES[1], 6)
    pipe = make_pipeline(srig)
    rows = [pipe.process(f) for f in frames[:3]]
    jumped = replace(frames[5], index=3)  # two frames lost: the time jumps 0.3 s
    rows.append(pipe.process(jumped))
    assert rows[2].ok
    assert rows[3].status is Status.REJECTED and "frame_jump" in rows[3].warnings
    back = replace(frames[3], index=4, time_s=0.2)  # time going backwards
    assert pipe.process(back).status is Status.REJECTED


def test_saturated_frame_gives_no_rate(srig):
    frames = sequence(srig, PAPER_CASES[1], 2)
    pipe = make_pipeline(srig)
    pipe.process(frames[0])
    flare = frames[1].image.copy()
    flare[:, :100] = 255  # the sun or the moon in the field
    row = pipe.process(replace(frames[1], image=flare))
    assert row.status is Status.REJECTED and "saturated" in row.warnings
    assert row.as_dict()["wx_dps"] is None


def test_hot_pixels_and_a_satellite_streak_never_become_a_rate(srig):
    rng = np.random.default_rng(5)
    hot = rng.integers(0, [512, 640], (40, 2))

    def extra(i, sig):
        sig[hot[:, 0], hot[:, 1]] += 250.0  # hot pixels: fixed on the sensor
        if i % 2 == 0:  # a satellite crossing, at a different place each time
            y = 100 + 40 * i
            sig[y : y + 3, 50:400] += 120.0

    frames = sequence(srig, PAPER_CASES[1], 8, seed=2, extra=extra)
    rows = list(make_pipeline(srig).run(frames))
    ok = [r for r in rows if r.ok]
    assert len(ok) >= 6
    for r in ok:
        err = r.w_dps - PAPER_CASES[1]
        assert np.all(np.abs(err) < 4.5 * r.sigma_dps), (r.frame, err, r.sigma_dps)
    # a frame of hot pixels only: no stars, no rate
    only_hot = np.full((512, 640), 10, np.uint8)
    only_hot[hot[:, 0], hot[:, 1]] = 255
    assert find_stars(only_hot, 10.0).reason == "too_few_stars"
    pipe = make_pipeline(srig)
    rows = [pipe.process(Frame(i, i / 10, only_hot)) for i in range(3)]
    assert not any(r.ok for r in rows)


def test_stars_beyond_the_lens_models_field_are_left_out():
    """A lens model (k1 = -4) turning back 325 px out, short of the 410 px corners: the
    sky renders inside that fold only; a light moving in a corner beyond it has no ray
    and is left out of the matches (before, it was matched with a ray from the
    polynomial's far branch), and the rates stay within their sigma."""
    raw = {**SMALL, "camera": {**SMALL["camera"], "dist": [-4.0, 0.0, 0.0, 0.0, 0.0]}}
    rig = rig_from_dict(raw)
    assert rig.camera.field_radius_px < 330.0

    def extra(i, sig):
        y, x = np.mgrid[0:64, 0:64]
        sig[:64, :64] += 200.0 * np.exp(-((x - 40 - 2.0 * i) ** 2 + (y - 40) ** 2) / 4.0)

    frames = sequence(rig, PAPER_CASES[1], 8, seed=4, extra=extra)
    pipe = make_pipeline(rig)
    rows, beyond = [], 0
    for f in frames:
        rows.append(pipe.process(f))
        m = pipe.last_detection.matches
        if m is not None and len(m):
            assert rig.camera.in_field(m.uv1, 1.0).all() and rig.camera.in_field(m.uv2, 1.0).all()
        stars = pipe.last_detection.stars
        beyond += int(np.sum(~rig.camera.in_field(stars.centroids_px)))
    assert beyond >= 4  # the corner light was found, as a star, each frame
    ok = [r for r in rows if r.ok]
    assert len(ok) >= 6
    for r in ok:
        err = r.w_dps - PAPER_CASES[1]
        assert np.all(np.abs(err) < 4.5 * r.sigma_dps), (r.frame, err, r.sigma_dps)


# ------------------------------------------------------------------ rig and CLI


def test_starfield_rig_is_checked():
    rig = load_rig(CONFIGS / "starfield.toml")
    assert rig.kind == "starfield" and rig.target.max_rate_dps == 6.0
    assert rig.exposure_ms == 50.0
    bad = {**SMALL, "mount": {**SMALL["mount"], "on": "lab"}}
    with pytest.raises(ConfigError, match="on = 'lab'"):
        rig_from_dict(bad)
    bad = {**SMALL, "camera": {**SMALL["camera"], "exposure_ms": 150.0}}
    with pytest.raises(ConfigError, match="exposure_ms"):
        rig_from_dict(bad)
    bad = {**SMALL, "target": {"kind": "starfield", "max_rate_dps": -1}}
    with pytest.raises(ConfigError, match="max_rate_dps"):
        rig_from_dict(bad)
    with pytest.raises(ConfigError, match="method"):
        RatePipeline(rig, "full")


def test_cli_simulate_then_rate_with_truth(tmp_path):
    rig = tmp_path / "small.toml"
    rig.write_text(
        "[camera]\nwidth = 640\nheight = 512\nfx = 1685.0\nfy = 1685.0\ncx = 319.5\n"
        'cy = 255.5\nfps = 10.0\nexposure_ms = 50.0\n[mount]\non = "platform"\n'
        "position_mm = [0, 0, 0]\nrotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n"
        '[target]\nkind = "starfield"\n'
    )
    r = CliRunner()
    rig = str(rig)
    tmp_path = str(tmp_path)
    res = r.invoke(cli, ["simulate", "--rig", rig, "--out", f"{tmp_path}/s", "--frames", "5",
                         "--case", "3"])  # fmt: skip
    assert res.exit_code == 0, res.output
    out = f"{tmp_path}/rate.csv"
    res = r.invoke(cli, ["rate", f"{tmp_path}/s", "--rig", rig, "--out", out,
                         "--truth", f"{tmp_path}/s/truth.csv"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "wz: rms" in res.output
    rows = list(csv.DictReader(open(out)))
    assert [r["status"] for r in rows] == ["no_target"] + ["ok"] * 4
    assert abs(float(rows[2]["wz_dps"]) + 1.0) < 0.2
    # `batch` does the same for a starfield rig
    res = r.invoke(cli, ["batch", f"{tmp_path}/s", "--rig", rig, "--method", "crassidis"])
    assert res.exit_code == 0 and res.output.count(",ok,") == 4


def test_cli_budget_and_wrong_kind():
    r = CliRunner()
    res = r.invoke(cli, ["rate", "--budget"])
    assert res.exit_code == 0 and "0.012 deg/s" in res.output and "(Eq. 28)" in res.output
    res = r.invoke(cli, ["rate", "x", "--rig", str(CONFIGS / "triangle.toml")])
    assert res.exit_code == 2 and "starfield" in res.output
    res = r.invoke(cli, ["rate"])
    assert res.exit_code == 2


def test_edge_bands_find_the_stars_a_full_search_finds_there(srig):
    from visvec.detect.stars import residual, segment, segment_edges

    img = sequence(srig, PAPER_CASES[1], 1, seed=7, scene=StarScene(flux_m6=300.0))[0].image
    res = residual(img)
    full = segment(res, 10.0)
    b = full.boxes
    h, w = img.shape
    # a bottom band that ends across a star of the left band
    low = (b[:, 0] + b[:, 2] < 60) & (b[:, 1] > h - h // 3) & (b[:, 3] >= 3)
    cut = h - int(b[low, 1].max()) - 2
    for bands in ((60, 60, 60, 60), (90, 25, 40, 120), (60, cut, 60, 60)):
        top, bottom, left, right = bands
        edge = segment_edges(res, bands, 10.0)
        # every star lying whole in a band, corners included, is found exactly once
        inside = (b[:, 1] + b[:, 3] < top) | (b[:, 1] > h - bottom)
        inside |= (b[:, 0] + b[:, 2] < left) | (b[:, 0] > w - right)
        ref = full.cents[inside]
        assert len(ref) >= 5
        d = np.linalg.norm(ref[:, None] - edge.cents[None], axis=2)
        assert np.all(d.min(axis=1) < 1e-3)
        assert np.all(np.sum(d < 1e-3, axis=1) == 1)
        # and nothing else but stars cut by a band's inner edge is left out
        assert len(edge.cents) == len(ref)
