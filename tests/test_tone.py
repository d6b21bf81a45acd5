"""A camera's tone curve (visvec.tone): the table the triangle's fits read linear light
through, the rig's key, and what declaring it does to frames through a webcam's chain."""

from dataclasses import replace

import numpy as np
import pytest

from visvec.bench.triangle import evaluate, random_cases, render_cases
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.webcam import WebcamChain, srgb_decode, srgb_encode
from visvec.tone import check_tone_curve, tone_lut

from conftest import CONFIGS


def test_the_srgb_table_inverts_the_simulator_s_encoding():
    """Each code's linear level is the IEC 61966-2-1 decoding (the simulator's own,
    written apart), white stays 255, and encoding it again gives the code back."""
    lut = tone_lut("srgb")
    assert lut.shape == (256,) and lut.dtype == np.float32
    for code in (0, 1, 10, 11, 50, 128, 200, 255):
        assert lut[code] == pytest.approx(255.0 * srgb_decode(code / 255.0), rel=1e-6, abs=1e-6)
    back = np.rint(255.0 * srgb_encode(lut / 255.0))
    assert np.array_equal(back, np.arange(256))
    assert np.all(np.diff(lut) > 0)


def test_a_gamma_and_linear():
    assert tone_lut("linear") is None and tone_lut(1.0) is None
    lut = tone_lut(2.2)
    assert lut[128] == pytest.approx(255.0 * (128 / 255) ** 2.2, rel=1e-6)
    assert check_tone_curve(2, "x") == 2.0 and check_tone_curve("srgb", "x") == "srgb"
    for bad in ("SRGB", 0.1, 6.0, True, None):
        with pytest.raises(ValueError, match="x = "):
            check_tone_curve(bad, "x")


def test_the_rig_declares_it(tmp_path):
    text = (
        (CONFIGS / "triangle.toml")
        .read_text()
        .replace("readout_ms = 0.0", 'readout_ms = 0.0\ntone_curve = "srgb"', 1)
    )
    p = tmp_path / "rig.toml"
    p.write_text(text)
    assert load_rig(p).tone_curve == "srgb"
    assert load_rig(CONFIGS / "triangle.toml").tone_curve == "linear"


@pytest.mark.parametrize("refine", ["lines", "pixels"])
def test_declared_the_fits_through_a_webcam_are_honest_uncalibrated(refine):
    """Frames through a webcam's chain (sRGB among its steps), no calibration: with the
    rig's tone curve left linear the blurred edges move toward their dark sides and the
    tilts lie well beyond their sigma; declared, the fits read linear light and the
    tilts' errors are what their sigma says (RMS of error / sigma near 1)."""
    rig = load_rig(CONFIGS / "triangle.toml")
    rig = replace(rig, detect=replace(rig.detect, refine=refine))
    cases = random_cases(16, Scene(webcam=WebcamChain()), seed=5)
    imgs = render_cases(rig, cases, workers=1)
    z = {}
    for tone in ("linear", "srgb"):
        out = evaluate(replace(rig, tone_curve=tone), imgs, cases, "full")
        assert len(out.err_deg) >= 15
        zz = np.abs(np.array(out.err_deg) / np.array(out.sigma_deg))[:, 1:]  # the tilts
        z[tone] = float(np.sqrt(np.mean(zz**2)))
        if tone == "srgb":
            assert zz.max() < 4.0
    # (16 frames at 640x480, seed 5: lines 1.66 -> 0.87, pixels 2.31 -> 1.00)
    assert z["srgb"] < 1.3 < 1.5 < z["linear"], z
