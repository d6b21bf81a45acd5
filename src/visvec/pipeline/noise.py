"""The centroid noise of a spot target (lamps, LED markers), learned from its fits.

A rig file's ``[detect] centroid_sigma_px`` is a guess: 0.1 px where simulated lamps
scatter 0.02 px and simulated LEDs 0.012, and on a real rig whatever its optics and
exposure make it. A row's sigma computed from the guess alone is then several times its
error (or, for a guess too small, too narrow; a frame's own chi-square only ever widens
it). The fits themselves measure the noise: the pooled a-posteriori variance factor of
least squares, the sum of the squared residuals over their degrees of freedom.
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
