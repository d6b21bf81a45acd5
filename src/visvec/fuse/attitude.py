"""The 3-D filter of `visvec fuse`: inertial propagation and fix updates on the
attitude, with the gyro's calibration.

3-D: a multiplicative extended Kalman filter (Markley & Crassidis, Fundamentals of
Spacecraft Attitude Determination and Control, 2014, Sec. 6.2, Eqs. 6.60-6.63) on the
attitude error, the gyro bias and, beyond the usual filter, the gyro's misalignment to
the fixes' body frame, its scale factors and its time offset to the fixes:
omega_B(t) = R_m (1 + k) (omega_g(t + tau) - b), k diagonal, omega_g(t + tau) taken as
omega_g + tau d(omega_g)/dt. With R_true = R exp([dth]x), b = b^ + db,
R_m = exp([dphi]x) R_m^, k = k^ + dk and tau = tau^ + dtau, the error obeys (to first
order; dth' = -[w]x dth + (w_true - w^))
    dth' = -[w]x dth - R_m^ (1 + k^) db - [w]x dphi + R_m^ diag(omega_g - b^) dk
           + R_m^ (1 + k^) d(omega_g)/dt dtau,
    w = R_m^ (1 + k^) (omega_g + tau^ d(omega_g)/dt - b^),
so misalignment, scale and time offset show whenever the body turns; they are
estimated from the data. The time offset drifts, tau' = rho, as two free-running clocks
do (their rate difference rho, a state too: the two-state clock model, Brown & Hwang,
Introduction to Random Signals and Applied Kalman Filtering, 4th ed., 2012, Sec. 9.3).
A zero prior sigma keeps a parameter fixed. The clock jitter between the gyro and the
fixes is a considered state (AttitudeModel.jitter). After an interval whose reading was
reconstructed from a clipped one, the calibration is considered for that fix: the
reconstruction's error would otherwise be read as bias, scale or clock.

The process noise is learned from the fixes' innovations (covariance matching, Mehra,
"Approaches to adaptive filtering", IEEE TAC 17(5), 1972, Sec. IV; Myers & Tapley,
IEEE TAC 21(4), 1976). The attitude's process noise has two parts: a white rate noise
(variance q_a per second) and a rate-proportional error held through each interval
between fixes (what scale, misalignment and timing leave: an angle error of variance
q_w (integral of |w| dt)^2 since the last fix, so that it grows with the turn, not its
square root). After each fix, y = |r|^2 - tr(R_fix) - tr(P^-) + tr(Q used since the
last fix) is an unbiased sample of tr(Q true) over the interval, whose regressors are
3 T and 3 A^2 (T the interval, A its turn); (q_a, q_w) follow by least squares over the
recent fixes (forgetting factor, each weighted by 1/var(|r|^2)), with the rest
segment's gyro noise, or the default, as a prior worth a few fixes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from visvec.chi2 import ppf as chi2_ppf
from visvec.fuse import kernels
from visvec.fuse.gate import BURST_P, nis_limit
from visvec.fuse.inputs import Fix
from visvec.rotations import expmap, logmap


@dataclass(frozen=True)
class NoiseFit:
    """Least-squares sums of the learned process noise (q_a rad^2/s, q_w 1/s): the
    normal matrix ``H`` (2, 2) and vector ``z`` (2,), with the prior ``theta0``."""

    H: np.ndarray
    z: np.ndarray
    theta0: np.ndarray
    n: int = 0

    @classmethod
    def prior(cls, theta0: np.ndarray) -> NoiseFit:
        return cls(np.zeros((2, 2)), np.zeros(2), theta0)

    def theta(self) -> np.ndarray:
        """(q_a, q_w), solved once per fit (a propagation asks for it every sample)."""
        th = self.__dict__.get("_theta")
        if th is None:
            th = self._solve()
            object.__setattr__(self, "_theta", th)
        return th

    def _solve(self) -> np.ndarray:
        # the prior: each parameter as known as from NOISE_PRIOR_FIXES fixes
        # (var(|r|^2) = 2 E(|r|^2)^2 each); it is not forgotten, so that a parameter
        # the motion does not show (q_w at rest) stays at its prior
        H0 = np.diag(NOISE_PRIOR_FIXES / (2.0 * self.theta0**2))
        th = np.linalg.solve(H0 + self.H, H0 @ self.theta0 + self.z)
        # a run of lucky fixes must not make it rigid: the white noise stays above a
        # hundredth of its prior, the rate-proportional one above 0.1 % of the rate
        return np.maximum(th, [0.01 * self.theta0[0], RATE_NOISE_FLOOR**2])


class AttitudeState(NamedTuple):
    """The 3-D filter's state after a sample (immutable: the engine keeps one per
    sample; a NamedTuple, as a 1 kHz IMU makes thousands a second, each replayed)."""

    R: np.ndarray  # R_NB
    b: np.ndarray  # gyro bias, rad/s, gyro axes
    Rm: np.ndarray  # gyro axes -> body axes
    k: np.ndarray  # gyro scale factor errors (3,)
    tau: float  # gyro time offset, s (the gyro's reading at t + tau belongs to t)
    # (15, 15): dtheta (body), db, dphi (body), dk, dtau, jitter (consider), ddrift
    P: np.ndarray
    noise: NoiseFit
    # since the last fix: [seconds, integral of |w| dt (rad), trace of the attitude
    # noise added]; whether a saturated reading was integrated; whether the last fix was refused
    acc: tuple[float, float, float] = (0.0, 0.0, 0.0)
    saturated: bool = False
    disputed: bool = False
    # the fading factor on the process noise until the next fix (see _fade)
    fade: float = 1.0
    # whether the attitude rests on a fix checked against the filter's prediction: one
    # taken while the prediction was too wide to gate it (after a long saturation, a
    # restart) must first be confirmed by a later fix that passes a narrow gate
    confirmed: bool = True
    # the gyro clock's rate against the fixes' clock, less one (s/s): tau drifts by it
    drift: float = 0.0


RATE_NOISE_FLOOR = 0.001
# a prediction wider than this (1-sigma, any axis) cannot tell a good fix from a
# glitch: at the gate's 5.5 sigma it would take a fix 30 deg off
CONFIRM_SIGMA = math.radians(5.0)
# the correlation time of the clock jitter between the gyro and the fixes (see
# AttitudeModel.jitter): short against the fixes' spacing, long against the samples'
JITTER_TIME_S = 0.2
# the fading factor's memory: each fix's NIS over its expected 3 counts this much
FADE_NEW = 0.5
NOISE_FORGET = 0.93  # per fix: the noise fit remembers about the last 15 fixes
NOISE_PRIOR_FIXES = 3.0  # the prior counts as this many fixes
N_STATE = kernels.N_STATE
# the error state's parts (kernels' layout): attitude (body, rad), gyro bias (rad/s),
# misalignment (rad), scale factors, time offset (s), clock jitter (s, considered) and
# clock rate (s/s)
TH, BIAS, MIS, SCALE = (slice(i, i + 3) for i in (kernels.TH0, kernels.BIAS0, kernels.MIS0,
                                                  kernels.SCALE0))  # fmt: skip
TAU, JIT, DRIFT = kernels.TAU, kernels.JIT, kernels.DRIFT
# two free-running clocks (the gyro's, the fixes') differ in rate, quartz oscillators by
# tens of ppm: RepoIMU's gyro against its Vicon by about 100 ppm (the time offset fitted
# per 15 s in hindsight grows from 2 to 8 ms over Test06's 90 s and from 1.5 to 9 ms
# over Test10's). The rate's prior, and its slow wander:
CLOCK_DRIFT_SIGMA = 2e-4  # s/s, the prior: 200 ppm
CLOCK_DRIFT_WALK = 0.01  # the rate's random walk, in prior sigmas per sqrt(s)
MAX_CLOCK_DRIFT = 1e-3


def transition(s: AttitudeState, g: np.ndarray, gdot: np.ndarray, dt: float,
               jitter_time: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The body rate (rad/s, (3,)) over an interval of ``dt`` s and the error state's
    transition F (15, 15), from the gyro's mean reading ``g`` (rad/s) and its rate of
    change ``gdot`` (rad/s^2) with the state's calibration: w = R_m (1 + k)
    (g + tau gdot - b), and F = I + (the error equation of the module doc) dt, its
    attitude block the exact transition exp(-[w]x dt); the clock jitter decays over
    ``jitter_time`` s and the time offset drifts with the clock rate (kernels.transition,
    the one implementation the propagation runs)."""
    return kernels.transition(s.Rm, s.k, s.b, s.tau, np.asarray(g, float),
                              np.asarray(gdot, float), dt, jitter_time)  # fmt: skip


@dataclass(frozen=True)
class AttitudeModel:
    """3-D fusion (MEKF) with gyro bias, misalignment, scale factors and time offset,
    and a process noise learned from the innovations (the module doc).

    Attributes
    ----------
    gyro_noise : float
        The prior white rate noise per sample (rad/s); learned from a rest segment
        and the fixes.
    rate_noise : float
        The prior relative rate error held between fixes (q_w its square).
    sample_s : float
        The IMU's period (s): the white noise's correlation time.
    learn_noise : bool
        Learn the process noise from the innovations.
    gyro_bias_walk : float
        The bias's random walk (rad/s per sqrt(s)).
    gyro_bias0, gyro_bias_sigma : (3,) rad/s, rad/s
        The bias's prior and its 1-sigma.
    misalignment_sigma, scale_sigma, time_offset_sigma, clock_drift_sigma : float
        The priors (rad, relative, s, s/s) of the gyro's misalignment to the fixes'
        body axes, its scale factors, its time offset and that offset's drift; 0
        keeps one fixed.
    jitter_sigma, jitter_time : float
        The clock jitter between the gyro and the fixes (s; None: one sample period)
        and its correlation time (s): considered, never estimated.
    fix_sigma : float
        A fix's attitude noise (rad) where the fix has no covariance.
    """

    gyro_noise: float = math.radians(0.3)  # rad/s per sample, the prior's white noise
    rate_noise: float = 0.03  # relative rate error, held between fixes (q_w = its square)
    sample_s: float = 0.01  # the IMU's period (the white noise's correlation time)
    learn_noise: bool = True
    gyro_bias_walk: float = math.radians(0.01)  # rad/s/sqrt(s)
    gyro_bias0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias_sigma: float = math.radians(1.0)
    misalignment_sigma: float = math.radians(5.0)  # 0: not estimated
    scale_sigma: float = 0.02  # relative; 0: not estimated
    time_offset_sigma: float = 0.01  # s; 0: not estimated
    clock_drift_sigma: float = CLOCK_DRIFT_SIGMA  # s/s; 0: not estimated
    jitter_sigma: float | None = None  # s; None: one IMU sample period (sample_s)
    jitter_time: float = JITTER_TIME_S
    fix_sigma: float = math.radians(0.1)

    planar = False

    @property
    def jitter(self) -> float:
        """The 1-sigma clock jitter between the gyro's samples and the fixes (s).

        Unless the two are triggered by one clock, a sample's time on the fixes' clock
        is known to about one sample period (the reading is the mean over its period,
        and the link adds its own delay), and it wanders: RepoIMU's gyro and motion
        capture slip against each other by several milliseconds
        (benchmarks/fusion_repoimu.py). A wrong time offset d turns into an attitude
        error d (w(t) - w(t_fix)), largest where the rate changes fastest. The filter
        carries it as a Schmidt consider state (Schmidt 1966; Simon, Optimal State
        Estimation, 2006, Sec. 7.5): a first-order Gauss-Markov time error of this
        sigma and correlation time ``jitter_time``, propagated into the attitude's
        covariance like the time offset but never estimated (its gain is zero), so
        that the rows' sigma and the fixes' gate know of it while no fix is
        explained away as jitter."""
        return self.sample_s if self.jitter_sigma is None else self.jitter_sigma

    def prior_theta(self) -> np.ndarray:
        return np.array([self.gyro_noise**2 * self.sample_s, self.rate_noise**2])

    def with_rest(self, mean: np.ndarray, std: np.ndarray, n: int) -> AttitudeModel:
        """The model with a rest segment's gyro mean as the bias prior and its scatter
        as the white noise prior."""
        noise = max(float(np.sqrt(np.mean(std**2))), math.radians(0.01))
        sigma = max(noise / math.sqrt(n), math.radians(0.02))
        return replace(self, gyro_bias0=tuple(float(x) for x in mean), gyro_noise=noise,
                       gyro_bias_sigma=sigma)  # fmt: skip

    def init(self, fix: Fix) -> AttitudeState:
        P = np.zeros((N_STATE, N_STATE))
        P[TH, TH] = self._fix_cov(fix)
        P[JIT, JIT] = self.jitter**2
        P[DRIFT, DRIFT] = self.clock_drift_sigma**2
        P[BIAS, BIAS] = np.eye(3) * self.gyro_bias_sigma**2
        P[MIS, MIS] = np.eye(3) * self.misalignment_sigma**2
        P[SCALE, SCALE] = np.eye(3) * self.scale_sigma**2
        P[TAU, TAU] = self.time_offset_sigma**2
        b0 = np.array(self.gyro_bias0, float)
        noise = NoiseFit.prior(self.prior_theta())
        return AttitudeState(fix.value.copy(), b0, np.eye(3), np.zeros(3), 0.0, P, noise)

    def reinit(self, s: AttitudeState, fix: Fix) -> AttitudeState:
        """Start again from ``fix``'s attitude, keeping what was learned of the gyro."""
        P = s.P.copy()
        P[TH, :] = 0.0
        P[:, TH] = 0.0
        P[TH, TH] = self._fix_cov(fix)
        return AttitudeState(fix.value.copy(), s.b, s.Rm, s.k, s.tau, P, s.noise,
                             confirmed=False, drift=s.drift)  # fmt: skip

    def _fix_cov(self, fix: Fix) -> np.ndarray:
        if fix.cov is not None:
            return fix.cov + np.eye(3) * 1e-10
        return np.eye(3) * self.fix_sigma**2

    def propagate(self, s: AttitudeState, gyro: np.ndarray, accel, dt: float):
        """``gyro`` is a `visvec.fuse.history.History.reading`: the interval's mean rate, its
        rate of change and the extra 1-sigma per axis of a saturated (reconstructed)
        reading. The equations: kernels.propagate (transition, process_noise)."""
        qa, qw = s.noise.theta() if self.learn_noise else self.prior_theta()
        # white: qa dt; rate-proportional, held since the last fix (an error of the
        # rate's size kappa |w|, the same through the interval): its variance
        # qw (integral of |w| dt)^2 grows by qw ((A + |w| dt)^2 - A^2)
        Rn, P, A1, trq = kernels.propagate(
            s.R, s.b, s.Rm, s.k, s.tau, s.P, gyro, dt, qa, qw, s.acc[1], s.fade, self.jitter,
            self.jitter_time, (CLOCK_DRIFT_WALK * self.clock_drift_sigma) ** 2,
            self.gyro_bias_walk**2,
        )  # fmt: skip
        sat = s.saturated or bool((gyro[2] > 0).any())
        acc = (s.acc[0] + dt, A1, s.acc[2] + trq)
        return AttitudeState(Rn, s.b, s.Rm, s.k, s.tau + s.drift * dt, P, s.noise, acc, sat,
                             s.disputed, s.fade, s.confirmed, s.drift)  # fmt: skip

    def propagate_run(self, s: AttitudeState, gyros: list[np.ndarray], dts: list[float],
                      ) -> list[AttitudeState]:  # fmt: skip
        """The states after each of consecutive intervals with no fix between them:
        `propagate` on each in turn, in one compiled call (kernels.propagate_run; a
        replay runs through hundreds of stored samples after each late fix)."""
        qa, qw = s.noise.theta() if self.learn_noise else self.prior_theta()
        G = np.array(gyros, float)
        Rs, Ps, As, trqs, taus = kernels.propagate_run(
            s.R, s.b, s.Rm, s.k, s.tau, s.drift, s.P, G, np.array(dts, float), qa, qw,
            s.acc[1], s.acc[2], s.fade, self.jitter, self.jitter_time,
            (CLOCK_DRIFT_WALK * self.clock_drift_sigma) ** 2, self.gyro_bias_walk**2,
        )  # fmt: skip
        sat = (np.cumsum((G[:, 2] > 0).any(axis=1)) > 0).tolist()
        t0 = s.acc[0]
        out = []
        for i, (dt, tau, A, trq) in enumerate(zip(dts, taus.tolist(), As.tolist(),
                                                  trqs.tolist(), strict=True)):  # fmt: skip
            t0 = t0 + dt
            out.append(AttitudeState(Rs[i], s.b, s.Rm, s.k, tau, Ps[i], s.noise, (t0, A, trq),
                                     s.saturated or sat[i], s.disputed, s.fade, s.confirmed,
                                     s.drift))  # fmt: skip
        return out

    def update(self, s: AttitudeState, fix: Fix) -> tuple[AttitudeState, bool, float]:
        R = self._fix_cov(fix)
        r = logmap(s.R.T @ fix.value)
        S = s.P[TH, TH] + R
        nis = float(r @ np.linalg.solve(S, r))
        noise = self._learn(s, r, R, S)
        fade = self._fade(s.fade, nis)
        acc0 = (0.0, 0.0, 0.0)
        if nis > nis_limit():
            # refused: the filter or the fix is wrong. Widen the attitude's covariance
            # by the disagreement, so that the rows stay honest and the next fix that
            # agrees with this one is taken (no lock-out); the widening counts as noise
            # added, so that the next fix's noise sample stays unbiased.
            P = s.P.copy()
            P[TH, TH] += np.outer(r, r)
            acc = (s.acc[0], s.acc[1], s.acc[2] + float(r @ r))
            return s._replace(P=P, noise=noise, acc=acc, disputed=True, fade=fade), False, nis
        P0 = s.P
        if nis > chi2_ppf(1.0 - BURST_P, 3):
            # taken, but far off: the gyro erred in a burst the model does not hold (a
            # swing beyond its linear range, a bump), or the fix did. The excess is
            # attitude noise of this interval (isotropic, its variance what the
            # innovation's square exceeds the expected by, per axis), so that the
            # attitude takes the fix and the sensor's calibration (bias, misalignment,
            # scale, time offset) is not pulled by one disagreement it did not cause.
            q = max(0.0, (float(r @ r) - float(np.trace(S))) / 3.0)
            P0 = s.P.copy()
            P0[TH, TH] += q * np.eye(3)
            S = P0[TH, TH] + R
        burst = P0 is not s.P
        K = np.linalg.solve(S, P0[TH, :]).T
        K[JIT] = 0.0  # the jitter is considered, never estimated (Schmidt)
        if s.saturated:
            # the interval held a reconstructed (clipped) reading, whose error is the
            # reconstruction's: the fix corrects the attitude, and the gyro's
            # calibration is, for this fix, considered (Schmidt), not estimated
            K[BIAS.start :] = 0.0
        dx = K @ r
        IKH = np.eye(N_STATE)
        IKH[:, TH] -= K
        P = IKH @ P0 @ IKH.T + K @ R @ K.T
        gated = bool(np.sqrt(np.diag(s.P[TH, TH])).max() <= CONFIRM_SIGMA)
        if burst:
            # one fix cannot tell whether the gyro erred or the fix did (a motion
            # capture's glitch, a frame's wrong detection: BROAD 18 at 154.2 s, 0.57 deg
            # for a moment): the attitude moves to the fix, and its covariance holds
            # both, the mixture's spread d d^T / 4 along the move d, so that a row is
            # within 2 sigma whichever was right; unconfirmed (fix_unconfirmed) until
            # the next fix agrees, which the widened covariance lets in either way
            d = dx[TH]
            P[TH, TH] += 0.25 * np.outer(d, d)
            gated = False
        Rn = s.R @ expmap(dx[TH])
        Rm = expmap(dx[MIS]) @ s.Rm
        tau = float(np.clip(s.tau + dx[TAU], -0.1, 0.1))
        drift = float(np.clip(s.drift + dx[DRIFT], -MAX_CLOCK_DRIFT, MAX_CLOCK_DRIFT))
        return AttitudeState(Rn, s.b + dx[BIAS], Rm, s.k + dx[SCALE], tau, P, noise,
                             acc0, fade=fade, confirmed=gated, drift=drift), True, nis  # fmt: skip

    @staticmethod
    def _fade(fade: float, nis: float) -> float:
        """The fading factor on the next interval's process noise (an adaptive fading
        Kalman filter: Xia, Rao, Ying, Shen 1994, the factor from the innovations):
        the last fixes' NIS over its expected 3, remembered with weight 1 - FADE_NEW,
        at least 1 and at most the gate's. The learned noise is the motion's average;
        real gyros err in bursts (a swing beyond the scale factors' linear range, a
        bump), and after a fix that found the filter off, the next interval is trusted
        less, so that its rows' sigma covers a burst that goes on."""
        f = (1.0 - FADE_NEW) * fade + FADE_NEW * nis / 3.0
        return float(min(max(f, 1.0), nis_limit() / 3.0))

    def _learn(self, s: AttitudeState, r, R, S) -> NoiseFit:
        """The noise fit after a fix's innovation (covariance matching, module doc)."""
        nf = s.noise
        if not self.learn_noise or s.saturated or s.acc[0] <= 0.0:
            return nf
        x = 3.0 * np.array([s.acc[0], s.acc[1] ** 2])
        y = float(r @ r) - float(np.trace(R)) - float(np.trace(s.P[TH, TH])) + s.acc[2]
        # a single wild fix (a glitch) counts at most as much as a fix at the gate
        y = min(y, nis_limit() / 3.0 * float(np.trace(S)))
        # var(y) = var(|r|^2) = 2 tr(S^2) for a Gaussian r
        v = 2.0 * float(np.sum(S * S))
        H = nf.H * NOISE_FORGET + np.outer(x, x) / v
        z = nf.z * NOISE_FORGET + x * y / v
        return NoiseFit(H, z, nf.theta0, nf.n + 1)

    @staticmethod
    def values(s: AttitudeState) -> tuple[np.ndarray, np.ndarray]:
        """R_NB and the body-axis attitude covariance (3, 3)."""
        return s.R, s.P[TH, TH]
