import numpy as np
import pytest

from visvec.noise import (
    CORRELATION_LAGS,
    NOISE_CAP,
    NOISE_FLOOR_PX,
    LearnedCorrelation,
    LearnedNoise,
    bartlett_lag,
)


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


def _series_sums(rho1, n_points, n_series, rng):
    """Lag sums (as edges.lag_sums gives them) of n_series MA(1) series of n_points
    with lag-1 correlation rho1 (others 0)."""
    theta = (1 - np.sqrt(1 - 4 * rho1**2)) / (2 * rho1) if rho1 else 0.0
    sums = np.zeros((2, CORRELATION_LAGS + 1))
    for _ in range(n_series):
        e = rng.standard_normal(n_points + 1)
        z = e[1:] + theta * e[:-1]
        for j in range(CORRELATION_LAGS + 1):
            sums[0, j] += z[: n_points - j] @ z[j:]
            sums[1, j] += n_points - j
    return sums


@pytest.mark.parametrize(("rho1", "lo", "hi"), [(0.0, 1.0, 1.0), (0.5, 1.6, 1.9)])
def test_the_edge_points_correlation_is_learned_over_frames(rho1, lo, hi, rng):
    """Edges of 60 points, 3 a frame: white points leave the covariance as it is (the
    sampling scatter is not taken for a correlation); points correlated at lag 1 by 0.5
    (a codec's) give the Bartlett long-run variance, 1 + 2 (1 - 1/4) 0.5 = 1.75 with
    the bandwidth 3 of 60 points, after 100 frames."""
    assert bartlett_lag(60) == 3
    corr = LearnedCorrelation()
    for _ in range(100):
        s = _series_sums(rho1, 60, 3, rng)
        corr.add(s[0], s[1], 3)
    assert lo <= corr.factor <= hi, corr.factor


def test_one_frame_is_too_few_to_widen_anything(rng):
    corr = LearnedCorrelation()
    s = _series_sums(0.5, 60, 3, rng)
    corr.add(s[0], s[1], 3)
    # 177 pairs at lag 1, under CORRELATION_MIN_PAIRS
    assert corr.factor == 1.0


def test_the_pixel_fits_inflation_is_learned_over_the_run():
    """A run's frames estimate one inflation each, scattering about the camera's: after
    INFLATION_MIN_FRAMES the run's mean is used for a frame whose own estimate is a
    draw of it (one far low or high within the band too), not for one far beyond it (a
    head in a band), which is not learned from either; white sensor noise (every frame
    1.0) keeps 1.0."""
    from visvec.noise import INFLATION_BAND_SIGMAS, INFLATION_MIN_FRAMES, LearnedInflation

    rng = np.random.default_rng(4)
    run = LearnedInflation()
    draws = rng.normal(3.0, 0.3, 200)
    for k, own in enumerate(draws):
        if k < INFLATION_MIN_FRAMES:
            assert run.value is None and not run.within(own)
        run.add(float(own))
    assert run.value == pytest.approx(3.0, abs=0.2)
    assert run.scatter == pytest.approx(0.3, rel=0.35)
    low, high = run.value - 2.5 * run.scatter, run.value + 2.5 * run.scatter
    assert run.within(low) and run.within(high)  # a low and a high draw
    head = run.value + 1.5 * INFLATION_BAND_SIGMAS * run.scatter
    assert not run.within(head)
    before = (run.value, run.scatter)
    run.add(head)
    assert (run.value, run.scatter) == before  # not learned from
    white = LearnedInflation()
    for _ in range(20):
        white.add(1.0)
    assert white.value == 1.0 and white.within(1.0) and not white.within(1.2)
    white.add(float("nan"))
    assert white.value == 1.0
