import numpy as np
import pytest

from visvec.pipeline.noise import NOISE_CAP, NOISE_FLOOR_PX, LearnedNoise


def _frames(noise, sigma, n_frames, n_points, rng, n_params=3):
    """Feed fits of n_points 2-D points whose residuals scatter sigma (px)."""
    dof = 2 * n_points - n_params
    for _ in range(n_frames):
        r2 = sigma**2 * rng.chisquare(dof)
        noise.add(n_points, float(np.sqrt(r2 / (2 * n_points))), n_params)


@pytest.mark.parametrize("prior_px", [0.12, 0.004])
def test_the_noise_is_learned_whatever_the_prior(prior_px, rng):
    """From a prior 10x too wide or 3x too narrow, the noise after 200 frames of 21
    points is the residuals' own, within 5 %."""
    noise = LearnedNoise(prior_px)
    _frames(noise, 0.012, 200, 21, rng)
    assert noise.sigma_px == pytest.approx(0.012, rel=0.05)


def test_a_prior_fades_and_an_outlier_frame_is_capped(rng):
    noise = LearnedNoise(0.1)
    _frames(noise, 0.02, 1, 4, rng)
    # one frame of 5 degrees of freedom barely moves a prior worth 20
    assert 0.08 < noise.sigma_px < 0.1
    _frames(noise, 0.02, 300, 4, rng)
    assert noise.sigma_px == pytest.approx(0.02, rel=0.1)
    before = noise.sigma_px
    noise.add(4, 50.0, 3)  # a stray spot taken for a lamp: 50 px
    # counted at NOISE_CAP times the noise: its share of about 300 forgotten frames
    assert before < noise.sigma_px < before * np.sqrt(1 + NOISE_CAP**2 / 50)
    noise.add(10, 0.0, 3)  # exact points: the floor holds it
    noise.add(10, float("nan"), 3)  # a fit without residuals adds nothing
    assert noise.sigma_px >= NOISE_FLOOR_PX and np.isfinite(noise.sigma_px)
