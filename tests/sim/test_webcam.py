"""A webcam's image chain in the simulator: each step does what it says, and each can be
set or switched off."""

import numpy as np
import pytest

from visvec.sim.webcam import WebcamChain, srgb_decode, srgb_encode, through_webcam

OFF = WebcamChain(vignetting=0.0, gain_sigma=0.0, electrons_at_white=0.0, read_noise_e=0.0,
                  bayer=False, chromatic_aberration=0.0, hot_pixels=0.0, srgb=False,
                  jpeg_quality=0)  # fmt: skip


def _flat(level: float, shape=(120, 160)) -> np.ndarray:
    return np.full(shape, level)


def test_every_step_off_is_the_exposure_itself():
    E = np.random.default_rng(0).uniform(0, 255, (60, 80))
    out = through_webcam(E, OFF, np.random.default_rng(1))
    assert np.abs(out.astype(float) - np.rint(E)).max() <= 1.0


def test_the_tone_curve_is_srgb_and_its_inverse_holds():
    x = np.linspace(0, 1, 101)
    assert np.allclose([srgb_decode(float(v)) for v in srgb_encode(x)], x, atol=1e-12)
    out = through_webcam(_flat(0.2 * 255), WebcamChain(**{**OFF.__dict__, "srgb": True}),
                         np.random.default_rng(0))  # fmt: skip
    assert abs(out.mean() - 255 * srgb_encode(np.array(0.2))) < 1.0  # 0.2 linear -> 124


def test_shot_noise_grows_with_the_signal():
    """Photo-electrons are Poisson: the linear variance is proportional to the signal.
    Each colour channel has its own electrons (its sensitivity s_c, taken back by the
    white balance) and the grey is 0.299 R + 0.587 G + 0.114 B of independent noises:
    sigma^2 = sum_c w_c^2 E 255 / (6000 s_c), 2.1 grey levels at E = 200."""
    chain = WebcamChain(**{**OFF.__dict__, "electrons_at_white": 6000.0})
    rng = np.random.default_rng(2)
    s_dark = through_webcam(_flat(20.0), chain, rng).astype(float).std()
    s_bright = through_webcam(_flat(200.0), chain, rng).astype(float).std()
    assert s_bright > 2.0 * s_dark
    w, sens = np.array([0.299, 0.587, 0.114]), np.array([0.55, 1.0, 0.75])
    assert abs(s_bright - np.sqrt(np.sum(w**2 / sens) * 200.0 * 255.0 / 6000.0)) < 0.15


def test_vignetting_darkens_the_corners_by_its_share():
    chain = WebcamChain(**{**OFF.__dict__, "vignetting": 0.25})
    out = through_webcam(_flat(200.0), chain, np.random.default_rng(0)).astype(float)
    assert abs(out[60, 80] - 200.0) <= 1.0 and abs(out[0, 0] - 150.0) <= 1.5


def test_hot_pixels_are_the_camera_s_own_every_frame():
    chain = WebcamChain(**{**OFF.__dict__, "hot_pixels": 0.001})
    a = through_webcam(_flat(50.0), chain, np.random.default_rng(0))
    b = through_webcam(_flat(50.0), chain, np.random.default_rng(9))
    hot_a, hot_b = np.argwhere(a == 255), np.argwhere(b == 255)
    assert len(hot_a) >= 10 and np.array_equal(hot_a, hot_b)


def test_a_bayer_mosaic_of_grey_light_comes_back_grey_and_a_gain_breathes():
    chain = WebcamChain(**{**OFF.__dict__, "bayer": True})
    out = through_webcam(_flat(100.0), chain, np.random.default_rng(0)).astype(float)
    assert abs(out[4:-4, 4:-4].mean() - 100.0) < 1.0  # white balance takes it back
    breathing = WebcamChain(**{**OFF.__dict__, "gain_sigma": 0.05})
    means = [through_webcam(_flat(100.0), breathing, np.random.default_rng(k)).mean()
             for k in range(8)]  # fmt: skip
    assert np.std(means) > 1.0


def test_chromatic_aberration_and_jpeg_change_an_edge():
    E = _flat(40.0)
    E[:, 150:] = 160.0  # an edge near the right side: the aberration moves it there
    base = through_webcam(E, OFF, np.random.default_rng(0)).astype(float)
    ca = through_webcam(E, WebcamChain(**{**OFF.__dict__, "chromatic_aberration": 0.01}),
                        np.random.default_rng(0)).astype(float)  # fmt: skip
    jpg = through_webcam(E, WebcamChain(**{**OFF.__dict__, "jpeg_quality": 60}),
                         np.random.default_rng(0)).astype(float)  # fmt: skip
    assert np.abs(ca - base)[:, 145:155].max() >= 5.0 and np.abs(ca - base)[:, :80].max() <= 1.0
    assert 0.0 < np.abs(jpg - base).mean() < 5.0


def test_settings_are_set_switched_off_or_refused():
    c = WebcamChain().with_settings({"jpeg_quality": "95", "bayer": "off", "vignetting": "0"})
    assert c.jpeg_quality == 95 and c.bayer is False and c.vignetting == 0.0
    for key, value, words in (("jpg", "9", "expected one of"), ("jpeg_quality", "200", "0..100"),
                              ("bayer", "maybe", "expected a bool"),
                              ("vignetting", "nan", "expected a float")):  # fmt: skip
        with pytest.raises(ValueError, match=words):
            WebcamChain().with_settings({key: value})


def test_simulate_renders_through_a_webcam(tmp_path):
    """`simulate --webcam` frames differ from the plain render of the same seed, and the
    triangle is still found in them; a bad --webcam-set or a rig of another kind is
    refused before any frame."""
    from visvec.imageio import read_image

    from conftest import CONFIGS, run

    rig = CONFIGS / "triangle.toml"
    a, b = tmp_path / "plain", tmp_path / "webcam"
    assert run("simulate", "--rig", rig, "--out", a, "--frames", "2").exit_code == 0
    r = run("simulate", "--rig", rig, "--out", b, "--frames", "2", "--webcam",
            "--webcam-set", "jpeg_quality=90")  # fmt: skip
    assert r.exit_code == 0, r.output
    fa, fb = (read_image(p / "frame_0000.png", 0).astype(float) for p in (a, b))
    assert np.abs(fa - fb).mean() > 3.0
    r = run("batch", b, "--rig", rig)
    assert r.exit_code == 0 and r.output.count(",ok,") == 2, r.output
    r = run("simulate", "--rig", rig, "--out", tmp_path / "x", "--webcam-set", "jpg=9")
    assert r.exit_code == 2 and not (tmp_path / "x").exists()
    r = run("simulate", "--rig", CONFIGS / "lamps.toml", "--out", tmp_path / "y", "--webcam")
    assert r.exit_code == 2 and "triangle rigs only" in r.output
