"""Noise learned from the fits at run time.

The centroid noise of a spot target (lamps, LED markers; :class:`LearnedNoise`): a rig
file's ``[detect] centroid_sigma_px`` is a guess: 0.1 px where simulated lamps
scatter 0.02 px and simulated LEDs 0.012, and on a real rig whatever its optics and
exposure make it. A row's sigma computed from the guess alone is then several times its
error (or, for a guess too small, too narrow; a frame's own chi-square only ever widens
it). The fits themselves measure the noise: the pooled a-posteriori variance factor of
least squares, the sum of the squared residuals over their degrees of freedom.

The correlation of the triangle's edge points along its edges
(:class:`LearnedCorrelation`): a video codec's errors, or a camera's smoothed noise,
are shared by neighbouring profiles, and a line through them is less precise than
their scatter says. The same for the pixel fit's pixels (:class:`LearnedInflation`):
each frame estimates it, the run averages the frames' estimates.
"""

from __future__ import annotations

import math

# old frames forgotten by this factor per frame (about the last 100), the rig's value
# worth this many degrees of freedom at the start (forgotten as a frame is), and never
# below NOISE_FLOOR_PX; a frame scattering more than NOISE_CAP times the noise so far
# counts as if at that cap
NOISE_FORGET = 0.99
NOISE_PRIOR_DOF = 20.0
NOISE_FLOOR_PX = 0.005
NOISE_CAP = 3.0


class LearnedNoise:
    """The centroid noise (px) the next frame's covariance uses: the pooled residual
    variance of the fits so far (sum of squared residuals over their degrees of
    freedom; the a-posteriori variance factor of least squares), forgetting old frames
    (NOISE_FORGET), with the rig's value ``prior_px`` as a prior worth NOISE_PRIOR_DOF
    degrees of freedom at the start, forgotten as the frames are. The prior must fade:
    frames of three to five lamps bring only 3 to 7 degrees of freedom each, so a prior
    that never faded would keep their sigma half again too wide (error/sigma RMS 0.56
    at 90 % of the lamps dark; benchmarks/lamps_few_lit.py). A frame scattering more
    than NOISE_CAP times the noise so far counts as if at that cap (a stray spot taken
    for a spot of the target, a smeared frame: the pooled variance is not an
    outlier's). A frame's own chi-square still widens its own covariance when it
    scatters more (the solvers' max(1, chi2 / dof))."""

    def __init__(self, prior_px: float):
        self.prior_px = float(prior_px)
        self.r2 = 0.0  # forgetting sums of the squared residuals (px^2) ...
        self.dof = 0.0  # ... and of their degrees of freedom
        self.prior_dof = NOISE_PRIOR_DOF  # the prior's weight, forgotten alike
        self.sigma_px = self.prior_px

    def add(self, n_points: int, rms_px: float, n_params: int) -> None:
        """A fit of ``n_points`` 2-D points with ``n_params`` parameters whose residuals'
        RMS per coordinate is ``rms_px`` (its squared residuals sum to 2 n rms^2)."""
        dof = 2 * n_points - n_params
        if dof <= 0 or not math.isfinite(rms_px):
            return
        r2 = min(2 * n_points * rms_px**2, dof * (NOISE_CAP * self.sigma_px) ** 2)
        self.r2 = NOISE_FORGET * self.r2 + r2
        self.dof = NOISE_FORGET * self.dof + dof
        self.prior_dof *= NOISE_FORGET
        var = (self.prior_dof * self.prior_px**2 + self.r2) / (self.prior_dof + self.dof)
        self.sigma_px = max(math.sqrt(var), NOISE_FLOOR_PX)


# the edge points' correlation: lags kept (profiles), the pooled sums' forgetting per
# frame (about the last 100 frames), and the fewest pooled pairs a lag needs to count
CORRELATION_LAGS = 4
CORRELATION_FORGET = 0.99
CORRELATION_MIN_PAIRS = 200


def bartlett_lag(n: float) -> int:
    """The Bartlett kernel's bandwidth for a series of ``n`` points: Newey & West's
    (Rev. Econ. Stud. 61 (1994), Sec. 3) plug-in rule floor(4 (n / 100)^(2/9)), at
    least 1 and at most CORRELATION_LAGS."""
    lag = math.floor(4.0 * (max(n, 1.0) / 100.0) ** (2.0 / 9.0))
    return int(min(max(lag, 1), CORRELATION_LAGS))


class LearnedCorrelation:
    """How much wider a line's error is than its points' scatter says, when neighbouring
    points' errors are correlated (a video codec's 8 x 8 blocks span several edge
    profiles; a camera's demosaicing or denoising smooths its noise over a pixel or
    two): the long-run variance of the points' mean over their variance,

        F = 1 + 2 sum_(j = 1..L) (1 - j / (L + 1)) rho_j,

    rho_j the correlation of the normalised residuals j points apart along an edge, L
    the Bartlett bandwidth (:func:`bartlett_lag`): the Newey-West HAC estimate
    (Econometrica 55 (1987), Eq. 2). One frame's edges give too few pairs for it (its
    10-90 % range at 320x240 spans -1.1 to 0.7), so the sums are pooled over the frames
    of a run (forgetting CORRELATION_FORGET per frame): a codec is a property of the
    recording, not of a frame. Only the part of F - 1 beyond twice its own sampling
    scatter counts (each rho_j scatters by 1 / sqrt(pairs)), and never below 1: white
    sensor noise gives rho_1 of -0.02 to 0.02 (the line fit's own residuals correlate by
    about -2 / n at every lag, and the profiles' shared pixels by a little more than
    that; EDGE_VARIANCE_INFLATION holds both), noise smoothed by (1, 2, 1) / 4 about
    0.35, mp4v 0.34-0.56."""

    def __init__(self):
        # sum_k z_k z_(k + j) and the pairs, j = 0..CORRELATION_LAGS, and the edges
        # pooled, each forgetting alike (plain floats: a frame's update is a few us)
        self.sums = [0.0] * (CORRELATION_LAGS + 1)
        self.pairs = [0.0] * (CORRELATION_LAGS + 1)
        self.series = 0.0
        self.factor = 1.0

    def add(self, sums, pairs, series: int) -> None:
        """One frame's sums and pair counts per lag (CORRELATION_LAGS + 1,) over its
        ``series`` edges; the factor the next frame's covariance takes."""
        a = CORRELATION_FORGET
        self.sums = [a * x + y for x, y in zip(self.sums, sums, strict=True)]
        self.pairs = [a * x + y for x, y in zip(self.pairs, pairs, strict=True)]
        self.series = a * self.series + series
        if not (self.pairs[0] > 0 and self.sums[0] > 0):
            return
        lag = bartlett_lag(self.pairs[0] / max(self.series, 1.0))
        var = self.sums[0] / self.pairs[0]
        excess, spread = 0.0, 0.0
        for j in range(1, lag + 1):
            p = self.pairs[j]
            if p >= CORRELATION_MIN_PAIRS:
                w = 1.0 - j / (lag + 1.0)
                excess += 2.0 * w * self.sums[j] / p / var
                spread += w * w / p
        # each rho_j scatters by 1 / sqrt(pairs): the excess's scatter is 2 sqrt(spread)
        self.factor = 1.0 + max(excess - 4.0 * math.sqrt(spread), 0.0)


# the pixel fit's noise inflation learned over the run: the frames' forgetting (about
# the last 20), the frames it takes before it is used, and the band (in the frames' own
# scatter) within which a frame's estimate is taken for a draw of the run's
INFLATION_FORGET = 0.95
INFLATION_MIN_FRAMES = 5
INFLATION_BAND_SIGMAS = 3.0


class LearnedInflation:
    """The pixel fit's covariance inflation for its noise's correlation, learned over a
    run (visvec._kernels.pixel_fit.noise_inflation estimates it from one frame's
    residuals). A camera's demosaicing and codec are properties of the camera, not of a
    frame, and one frame's estimate scatters: through a simulated webcam at 320x240
    about 3.0 with a standard deviation of 0.3, 10 % of the covariance from frame to
    frame, which puts frames whose estimate came out low beyond their sigma (a row at
    5.1 sigma of 2,682). So the frames' estimates are averaged over the run (forgetting
    INFLATION_FORGET per frame, with their scatter), and a frame whose own estimate lies
    within INFLATION_BAND_SIGMAS of that scatter about the run's takes the run's: the
    same quantity, better measured. A frame beyond the band (a head or a light in a
    band: residuals with a structure of their own) keeps its own and is not learned
    from. Until INFLATION_MIN_FRAMES frames have come, every frame keeps its own."""

    def __init__(self):
        self.weight = 0.0  # the forgetting sums of the frames' weights, estimates ...
        self.total = 0.0
        self.total2 = 0.0  # ... and squared estimates
        self.frames = 0

    @property
    def value(self) -> float | None:
        """The run's inflation, or None while it is not yet used."""
        if self.frames < INFLATION_MIN_FRAMES or self.weight <= 0.0:
            return None
        return self.total / self.weight

    @property
    def scatter(self) -> float:
        """The frames' estimates' standard deviation about the run's."""
        if self.weight <= 0.0:
            return math.inf
        mean = self.total / self.weight
        return math.sqrt(max(self.total2 / self.weight - mean * mean, 0.0))

    def within(self, own: float) -> bool:
        """Whether a frame's own estimate is a draw of the run's (within the band)."""
        run = self.value
        return run is not None and abs(own - run) <= INFLATION_BAND_SIGMAS * self.scatter

    def add(self, own: float) -> None:
        """A frame's own estimate, learned from while the run is still starting or when
        it lies within the band."""
        if not math.isfinite(own) or (self.value is not None and not self.within(own)):
            return
        a = INFLATION_FORGET
        self.weight = a * self.weight + 1.0
        self.total = a * self.total + own
        self.total2 = a * self.total2 + own * own
        self.frames += 1
