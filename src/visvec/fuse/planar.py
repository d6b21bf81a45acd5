"""The planar filter of `visvec fuse`: inertial propagation and fix updates on the
pose (x, y, heading) of a mock-up on an air-bearing table.

Planar (LuVeX, Keldysh preprint 2011-24, Sec. 3.1.2 and 4.1): the gyro's rate and the
accelerometer's body-frame reading, less their biases, are turned into the lab frame
and integrated (the paper's integration equations; its heading phi is our -psi, so its
(a_x cos phi + a_y sin phi, a_y cos phi - a_x sin phi) is our Rz(psi) a_B). Two update
rules share this propagation:
- "paper": a fix replaces x, y and the heading at its exposure time (the paper's
  re-integration "with quite accurate initial condition"); velocity and biases are
  kept (biases from the rest calibration only);
- "kalman" (default): an extended Kalman filter on [x, y, vx, vy, psi, b_g, b_ax, b_ay,
  tau, l] (mm, mm/s, rad, rad/s, mm/s^2, s, s) that also estimates the biases, the
  fixes' time offset tau (their stated time less their true exposure: a camera's frames
  stamped when read, not when exposed) and a lateness l that lasts (below). A fix
  stated at t measures the pose at t - tau, h = [x - vx tau, y - vy tau, psi - w tau]
  (w the gyro's rate less its bias), the first-order time shift the 3-D filter also
  makes (below; the time offset as a filter
  state: Li & Mourikis, "Online temporal calibration for camera-IMU systems", IJRR
  33(7), 2014). Fixes update it with their own covariance plus their timing jitter
  (below), and fixes whose innovation is implausible (chi-square, 3 dof, p < 1e-6) are
  refused.

  The timing jitter: beyond a constant offset, each fix's time is off by a few tenths of
  a millisecond to milliseconds (a frame timed when it arrives over a network; the
  inertial clock tied to the host's through arrivals), which moves the pose it states
  by J dt, J = dh/dt = (vx, vy, w). At 100 mm/s, 0.4 ms is 0.04 mm: more than a lamp
  fix's own sigma. The fix's covariance is R + sigma_t^2 J J^T, sigma_t learned from the
  fixes' innovations by covariance matching in J's direction (Mehra 1972, as the 3-D
  filter's process noise, below): with S the innovation covariance without the jitter,
  a = S^-1 J and g = J^T a, the projection a^T r has variance g + sigma_t^2 g^2, so
  y = ((a^T r)^2 - g) / g^2 is an unbiased sample of sigma_t^2, of variance
  2 (1/g + sigma_t^2)^2; a weighted mean with a forgetting factor (PlanarJitter).

  A lateness that lasts: a camera or its network held up for a second or so delivers
  its frames some milliseconds later than the offset says, which a white jitter does
  not hold: the filter averages those fixes as independent and follows them with a
  sigma that shrinks (a live soak, 2026-11-27: frames 1-10 ms late for a second, 78
  rows beyond 5 sigma). So the fixes' timing has a third part, a lateness l, a state of
  its own: a first-order Gauss-Markov process, l' = -l / T + w (T = LATE_TIME_S; Brown
  & Hwang, Introduction to Random Signals and Applied Kalman Filtering, 4th ed., 2012,
  Ch. 2, the first-order Gauss-Markov process: over a step dt, l decays by
  phi = exp(-dt / T) and gains the variance sigma_l^2 (1 - phi^2)). A fix stated at t
  shows the pose at t - tau - l, so l's column of H is tau's; they differ in their
  dynamics (tau stays, l goes back to 0 within T). Its variance sigma_l^2 is learned
  from the same samples y as the jitter, fitted a second time with a short memory
  (JITTER_FORGET_SHORT: about the last 10 fixes): what the recent fixes show beyond
  the long-run jitter, sigma_l^2 = max(0, short - long), is a lateness that lasts
  (covariance matching over two windows). The short fit's samples are clipped as the
  long fit's (JITTER_CLIP), but about its own value: a lateness that lasts grows it up
  to ninefold a fix, where one frame late for a moment counts for little (and is
  weighed by its own timing error, below). l's variance is kept at least sigma_l^2 (a
  lateness just found is not known in value). While the recent fixes are timed as the
  long run, sigma_l is the short fit's own noise and l stays near 0; when they come
  late, sigma_l grows within a few fixes, their disagreement along J goes to l, and the
  IMU carries the pose; as l takes it, the innovations (with l in the model) shrink,
  sigma_l goes back to 0 and l decays, so that a pose that has drifted is not held off
  by l. Replayed (benchmarks/fusion_replay.py) on a soak's kept fixes, and on an older
  soak's with two such hold-ups, no row is beyond 5 sigma (77 and 109 without l); the
  cost, that the fixes count a little less along J while sigma_l is the short fit's
  noise: on those runs a position error 5-12 % larger and a sigma 18-21 % larger.

  h is bilinear in the state (v tau, b_g tau), and a first-order time shift holds only
  to some tens of ms. So: before the filter starts, the engine aligns the offset from
  the fixes' poses against the IMU's (PlanarModel.align, Fusion._align) and applies the
  fixes at their stated time less it (Fusion._shift_fixes), leaving the filter the rest
  of it; the first two fixes give the velocity before the offset is coupled to the pose
  (PlanarModel._second); and the update carries the Gaussian second-order terms of the
  products (PlanarModel.update).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from visvec.fuse.gate import nis_limit
from visvec.fuse.inputs import Fix

# the fixes' timing jitter (PlanarModel, module doc): the prior (1 ms, a frame timed when
# it arrives) counts as this many fixes; the fit remembers about the last 1/(1 - forget)
JITTER_PRIOR_S = 1e-3
JITTER_PRIOR_FIXES = 3.0
JITTER_FORGET = 0.99
# and a second fit of the same samples that remembers about the last 10 fixes: what it
# finds beyond the first is the variance of a lateness that lasts (PlanarJitter.lasting;
# the module doc)
JITTER_FORGET_SHORT = 0.9
# the planar filter's states, and the lateness state's correlation time (s): the
# hold-ups of a camera or its network seen last about a second
N_PLANAR = 10
# the state's parts: position (mm), velocity (mm/s), heading (rad), gyro bias (rad/s),
# accelerometer biases (mm/s^2, body x, y), the fixes' time offset and lateness (s)
X, Y, VX, VY, PSI, BG, BAX, BAY, TAU, LATE = range(N_PLANAR)
POS, VEL, BA = slice(X, Y + 1), slice(VX, VY + 1), slice(BAX, BAY + 1)
POSE = [X, Y, PSI]  # what a fix measures
LATE_TIME_S = 1.0
# a single fix counts at most as one whose projected innovation is this many of its
# sigmas squared (a late frame is not jitter: it must not widen every fix after it)
JITTER_CLIP = 9.0
# a fix whose innovation along J is beyond this (chi-square, 1 dof, p = 0.01) is given its
# own timing variance (PlanarModel.update)
JITTER_OWN_CHI2 = 6.635
# the time offset's alignment before the filter starts (PlanarModel.align): the offsets
# tried (s; a network camera's frames arrive up to some hundreds of ms after their
# exposure), their coarse step and the fine one about its best, the fixes it needs at
# least, the sigma it must reach, how much worse (chi-square) another local minimum
# must fit
ALIGN_TAU = (-0.05, 0.5)
ALIGN_COARSE = 0.01
ALIGN_STEP = 0.002
ALIGN_MIN_FIXES = 15
ALIGN_SIGMA = 0.005
ALIGN_UNIQUE = 25.0


@dataclass(frozen=True)
class PlanarJitter:
    """The learned 1-sigma timing jitter of the fixes (s): a weighted mean of the samples
    y = ((a^T r)^2 - g) / g^2 (module doc) with the prior ``s0``; ``h``, ``z``: the sums
    of the weights and of the weighted samples, forgotten by JITTER_FORGET per fix;
    ``hs``, ``zs``: the same forgotten by JITTER_FORGET_SHORT, whose excess over the
    jitter is the variance of a lateness that lasts."""

    s0: float = JITTER_PRIOR_S
    h: float = 0.0
    z: float = 0.0
    n: int = 0
    # the same samples with a short memory (JITTER_FORGET_SHORT), without the prior
    hs: float = 0.0
    zs: float = 0.0

    @property
    def var(self) -> float:
        if self.s0 <= 0.0:  # no jitter (fixes timed by the IMU's own clock)
            return 0.0
        h0 = JITTER_PRIOR_FIXES / (2.0 * self.s0**4)
        return max((h0 * self.s0**2 + self.z) / (h0 + self.h), 0.0)

    @property
    def lasting(self) -> float:
        """The variance of a lateness that lasts (s^2): what the recent fixes' timing
        shows beyond the long-run jitter (PlanarModel, the lateness state)."""
        if self.s0 <= 0.0 or self.hs <= 0.0:
            return 0.0
        return max(self.zs / self.hs - self.var, 0.0)

    def learn(self, r: np.ndarray, S: np.ndarray, J: np.ndarray) -> PlanarJitter:
        a = np.linalg.solve(S, J)
        g = float(J @ a)
        if g <= 0.0 or self.s0 <= 0.0:  # at rest: nothing to learn about timing
            return self
        v = self.var
        q2 = float(a @ r) ** 2
        p2 = min(q2, JITTER_CLIP * (g + v * g * g))
        y = (p2 - g) / (g * g)
        # the short fit's samples clipped alike, about its own value: a lateness that
        # lasts grows it ninefold a fix, where one late frame counts for little
        vs = max(self.zs / self.hs, v) if self.hs > 0.0 else v
        ys = (min(q2, JITTER_CLIP * (g + vs * g * g)) - g) / (g * g)
        wt = 1.0 / (2.0 * (1.0 / g + v) ** 2)
        return PlanarJitter(self.s0, self.h * JITTER_FORGET + wt,
                            self.z * JITTER_FORGET + wt * y, self.n + 1,
                            self.hs * JITTER_FORGET_SHORT + wt,
                            self.zs * JITTER_FORGET_SHORT + wt * ys)  # fmt: skip


@dataclass(frozen=True)
class PlanarState:
    x: np.ndarray  # [x, y, vx, vy, psi, b_g, b_ax, b_ay, tau, lateness]
    P: np.ndarray
    w: float = 0.0  # the last interval's rate less the bias (rad/s)
    jitter: PlanarJitter = PlanarJitter()
    # while the last fix was refused: its disagreement with the filter (3, 3) on
    # (x, y, psi), added to the rows' covariance, not to the filter's (PlanarModel.update)
    dispute: np.ndarray | None = None
    # from one fix only: the velocity is not known yet, and the fixes' time offset is
    # not yet coupled to the pose (PlanarModel.update)
    pending: bool = False
    an: tuple[float, float] = (0.0, 0.0)  # the last interval's acceleration, lab (mm/s^2)
    # the fixes' timing not yet known (s^2; PlanarModel.timing_spread_s squared): the
    # pose's rate times it widens the fixes' and the rows' covariance
    spread: float = 0.0
    # while it is: the largest turn rate (rad/s) of the last timing_spread_s, and how
    # long ago it was (a fix's heading lags by the turn over that window)
    wmax: tuple[float, float] = (0.0, 0.0)

    @property
    def disputed(self) -> bool:
        return self.dispute is not None


def _rate_bound(s: PlanarState) -> np.ndarray:
    """The squared rates (mm/s, mm/s, rad/s) the pose may have changed at over the last
    timing_spread_s, in any direction: the speed as estimated plus three of its sigmas
    plus what the measured acceleration adds over that time, on both position axes (a
    fix's timing error moves it along a velocity the filter may not know yet), and the
    largest turn rate the gyro read over that time; what a timing error of 1 s moves a
    fix by, squared, per axis (the provisional filter's while the clocks align:
    PlanarModel.timing_spread_s)."""
    sv = math.sqrt(max(s.P[VX, VX], s.P[VY, VY], 0.0))
    speed = (math.hypot(s.x[VX], s.x[VY]) + 3.0 * sv
             + math.hypot(s.an[0], s.an[1]) * math.sqrt(s.spread))  # fmt: skip
    w = max(abs(s.w), s.wmax[0])
    return np.array([speed * speed, speed * speed, w * w])


def transition(an: np.ndarray, c: float, sn: float, dt: float) -> np.ndarray:
    """The planar state's transition F (10, 10) over ``dt`` s: position from velocity
    and acceleration, velocity from acceleration, both through the heading (``an``:
    the acceleration in the lab, mm/s^2; ``c``, ``sn``: the cosine and sine of the
    interval's mid-heading) and the accelerometers' biases; the heading from the gyro's
    bias; the lateness's decay over LATE_TIME_S."""
    F = np.eye(N_PLANAR)
    F[X, VX] = F[Y, VY] = dt
    dan = np.array([-an[1], an[0]])  # d(a_N)/d(psi)
    F[POS, PSI] = 0.5 * dan * dt * dt
    F[VEL, PSI] = dan * dt
    Rz = np.array([[c, -sn], [sn, c]])
    F[POS, BA] = -0.5 * Rz * dt * dt
    F[VEL, BA] = -Rz * dt
    F[PSI, BG] = -dt
    F[LATE, LATE] = math.exp(-dt / LATE_TIME_S)
    return F


@dataclass(frozen=True)
class PlanarModel:
    """Planar fusion; noises per IMU sample (white), bias random walks per sqrt(s).

    Attributes
    ----------
    method : str
        'kalman' (the filter with biases) or 'paper' (the paper's reset at each fix).
    gyro_noise, accel_noise : float
        White noise per sample: yaw gyro (rad/s), accelerometers (mm/s^2).
    gyro_bias_walk, accel_bias_walk : float
        The biases' random walks (rad/s, mm/s^2 per sqrt(s)).
    gyro_bias0, accel_bias0 : float, (float, float)
        The biases' priors (rad/s, mm/s^2), with ``gyro_bias_sigma``,
        ``accel_bias_sigma`` their 1-sigma.
    velocity_sigma : float
        The velocity's prior 1-sigma (mm/s).
    fix_sigma : (float, float)
        A fix's position (mm) and heading (rad) noise where it has no covariance.
    time_offset_sigma, time_offset_walk, jitter_sigma : float
        The fixes' time offset prior (s), its walk (s per sqrt(s)) and the timing
        jitter (s), learned when ``learn_jitter``.
    restart_after_s : float
        Fixes refused in a row for this long (s) restart the filter.
    timing_spread_s : float
        A provisional filter's timing spread (s) while the clocks align."""

    method: str = "kalman"
    gyro_noise: float = math.radians(0.05)  # rad/s
    accel_noise: float = 2.0  # mm/s^2 (the paper's 0.002 m/s^2)
    gyro_bias_walk: float = math.radians(0.002)  # rad/s/sqrt(s)
    accel_bias_walk: float = 0.05  # mm/s^2/sqrt(s)
    gyro_bias0: float = 0.0  # rad/s, from the rest calibration
    accel_bias0: tuple[float, float] = (0.0, 0.0)  # mm/s^2
    gyro_bias_sigma: float = math.radians(0.5)
    accel_bias_sigma: float = 20.0
    velocity_sigma: float = 300.0  # mm/s, unknown at the first fix
    fix_sigma: tuple[float, float] = (1.0, math.radians(0.05))  # mm, rad, without sigmas
    # the fixes' time offset (s): its prior (a camera's latency from exposure to a read
    # is tens of ms, more on a slow computer) and its random walk per sqrt(s)
    time_offset_sigma: float = 0.05
    time_offset_walk: float = 1e-4
    # the fixes' timing jitter (s, 1-sigma): the prior of the learned one; with
    # learn_jitter False, fixed at it
    jitter_sigma: float = JITTER_PRIOR_S
    learn_jitter: bool = True
    # fixes refused in a row restart the filter only once they have been for this long
    # (Fusion.step): a stream's frames that come late for a moment (a camera or its
    # network held up: tens to hundreds of ms) are refused while the IMU carries the
    # pose, rather than taken as the truth by a restart
    restart_after_s: float = 1.0
    # the fixes' timing not known (s): the rows' covariance widened by the pose's rate
    # times it (the provisional filter while the clocks align: Fusion.provisional)
    timing_spread_s: float = 0.0

    planar = True

    def init(self, fix: Fix) -> PlanarState:
        # the time offset's prior: centred on the shift the fix is applied with (the
        # engine's linearisation point, Fusion._shift_fixes), its sigma the prior's
        x = np.array([fix.value[0], fix.value[1], 0.0, 0.0, fix.value[2], self.gyro_bias0,
                      *self.accel_bias0, fix.shift, 0.0])  # fmt: skip
        R = self._fix_cov(fix)
        P = np.diag([R[0, 0], R[1, 1], self.velocity_sigma**2, self.velocity_sigma**2,
                     R[2, 2], self.gyro_bias_sigma**2, self.accel_bias_sigma**2,
                     self.accel_bias_sigma**2, self.time_offset_sigma**2, 0.0])  # fmt: skip
        return PlanarState(x, P, jitter=PlanarJitter(self.jitter_sigma), pending=True,
                           spread=self.timing_spread_s**2)  # fmt: skip

    def align(self, ts: np.ndarray, rate: np.ndarray, accel: np.ndarray | None,
              fixes: list[Fix]) -> tuple[float, float] | None:  # fmt: skip
        """The fixes' time offset from their poses against the IMU's, before the filter
        starts: (tau, its 1-sigma) in seconds, or None while the data cannot tell it
        (the platform has not turned or pushed enough, or too few fixes).

        ``ts`` are the IMU's sample times, ``rate`` the gyro's mean rate (rad/s, z) and
        ``accel`` the accelerometers' (m/s^2, body x, y; or None) over the interval
        ending at each. A fix stated at t shows the pose at t - tau. For each tau of a
        grid:
        - heading: from fix k to fix k+1 the heading turns by Psi(t_k+1 - tau) -
          Psi(t_k - tau) - b (t_k+1 - t_k), Psi the gyro's integral and b its bias,
          fitted (generalised least squares: the fixes' heading noise, each fix in two
          turns, plus the gyro's white noise over each interval; differencing takes the
          gyro's random walk apart, which would make a fit of the headings themselves
          too sure);
        - position: the accelerometers, turned to the lab by that heading (its start
          from the fixes), integrated twice, P(t); the fixes' positions less P at
          t_k - tau, second-differenced (which takes out the start position and
          velocity), against the accelerometers' biases turned and integrated alike
          (fitted), with the fixes' noise (each fix in three differences) and the
          accelerometers' white noise.
        tau is the grid's least sum of both chi-squares, refined by a parabola; its
        sigma is from the parabola's curvature, scaled by the fit's reduced
        chi-square when that is above 1 (a timing jitter, not in the covariance). This
        is the alignment of two sensors by correlation (Mair et al., "Spatio-temporal
        initialization for IMU to camera registration", IEEE ROBIO 2011): exact for any
        offset, where the filter's first-order time shift (update) holds to some tens
        of ms. It is refused unless the minimum is sharp (sigma under ALIGN_SIGMA) and
        unique (no other local minimum within ALIGN_UNIQUE of it in chi-square).

        Only what the offset changes tells it: a constant turn rate or acceleration
        shifted in time looks like a gyro or accelerometer bias. On 2 s windows along
        the lamps path (lap 66 s, 30 Hz lamp fixes) the accepted alignments were off
        by 12 ms rms, at most 54 ms, and by 2.6 of their sigma rms: the sigma is too
        small, and the filter's prior on the offset is at least ALIGN_PRIOR_MIN
        (replay.py), from which it learns the rest."""
        if len(ts) < 3:
            return None
        dt = np.diff(ts)
        period = float(np.median(dt))
        psi = np.concatenate([[0.0], np.cumsum(rate[1:] * dt)])
        t = np.array([f.time_s + f.shift for f in fixes])
        ok = (t - ALIGN_TAU[1] >= ts[0]) & (t - ALIGN_TAU[0] <= ts[-1])
        if ok.sum() < ALIGN_MIN_FIXES:
            return None
        fx = [f for f, k in zip(fixes, ok, strict=True) if k]
        t = t[ok]
        val = np.array([f.value for f in fx])
        var = np.array([np.diag(f.cov) if f.cov is not None else
                        [self.fix_sigma[0] ** 2] * 2 + [self.fix_sigma[1] ** 2]
                        for f in fx])  # fmt: skip
        # heading: the turns between consecutive fixes, whitened
        dz = (np.diff(val[:, 2]) + math.pi) % (2 * math.pi) - math.pi
        dtk = np.diff(t)
        n = len(dz)
        v2 = var[:, 2]
        C = np.diag(v2[1:] + v2[:-1] + self.gyro_noise**2 * period * dtk)
        C[np.arange(n - 1), np.arange(1, n)] = C[np.arange(1, n), np.arange(n - 1)] = -v2[1:-1]
        Wh = np.linalg.inv(np.linalg.cholesky(C))  # whitening: W C W^T = I
        g = Wh @ dtk
        gg = float(g @ g)
        # position: second differences (rows of D2 take out a + b t), whitened per axis
        D2 = np.zeros((n - 1, n + 1))
        for k in range(n - 1):
            h0, h1 = dtk[k], dtk[k + 1]
            D2[k, k : k + 3] = [1.0 / h0, -(1.0 / h0 + 1.0 / h1), 1.0 / h1]
        use_pos = accel is not None and n >= 3
        if use_pos:
            acc = np.asarray(accel, float) * 1000.0  # mm/s^2
            q = (self.accel_noise**2 * period * (2.0 / 3.0)
                 * (0.5 * (dtk[1:] + dtk[:-1])) ** 3 * np.sum(D2 * D2, axis=1) / 6.0)  # fmt: skip
            Wp = [np.linalg.inv(np.linalg.cholesky(D2 @ np.diag(var[:, ax]) @ D2.T + np.diag(q)))
                  for ax in (0, 1)]  # fmt: skip

        def chi2(grid: np.ndarray) -> np.ndarray:
            te = t[None, :] - grid[:, None]  # (grid, fixes): the fixes' true times
            turn = np.diff(np.interp(te, ts, psi), axis=1)
            y = (dz[None, :] - turn) @ Wh.T  # whitened; y = -b dt
            k = (y @ g) / gg
            res = y - k[:, None] * g[None, :]
            out = np.sum(res * res, axis=1)
            if use_pos:
                out = out + self._align_position(ts, psi, acc, -k, te, val, D2, Wp)
            return out

        # coarse over the whole range, then fine about its best
        coarse = np.arange(ALIGN_TAU[0], ALIGN_TAU[1] + 1e-9, ALIGN_COARSE)
        ssc = chi2(coarse)
        ic = int(np.argmin(ssc))
        if ic == 0 or ic == len(coarse) - 1:
            return None
        grid = np.arange(coarse[ic - 1], coarse[ic + 1] + 1e-9, ALIGN_STEP)
        ss = chi2(grid)
        i = int(np.argmin(ss))
        if i == 0 or i == len(grid) - 1:
            return None
        a, b, c = ss[i - 1], ss[i], ss[i + 1]
        curv = (a - 2.0 * b + c) / ALIGN_STEP**2  # d2 SS / d tau2
        if curv <= 0.0:
            return None
        tau = grid[i] + 0.5 * ALIGN_STEP * (a - c) / (a - 2.0 * b + c)
        dof = (n - 2) + (2 * (n - 1) - 2 if use_pos else 0)
        chi2_red = max(1.0, b / max(dof, 1))
        sigma = math.sqrt(2.0 / curv * chi2_red)
        # another local minimum that fits nearly as well: ambiguous
        far = np.abs(coarse - tau) > max(5.0 * sigma, 2 * ALIGN_COARSE)
        mins = (ssc[1:-1] <= ssc[:-2]) & (ssc[1:-1] <= ssc[2:]) & far[1:-1]
        if np.any(ssc[1:-1][mins] < b + ALIGN_UNIQUE * chi2_red) or sigma > ALIGN_SIGMA:
            return None
        return float(tau), sigma

    @staticmethod
    def _align_position(ts, psi, acc, bias, te, val, D2, Wp) -> np.ndarray:
        """The position part of align's chi-square at each tau of the grid (its
        docstring): ``bias`` (grid,) the gyro's bias fitted at each, ``te`` (grid,
        fixes) the fixes' true times."""
        # the heading at the samples: the gyro's, its bias off, started from the fixes'
        # (linear interpolation at the fixes' true times, as index and weight)
        j = np.clip(np.searchsorted(ts, te) - 1, 0, len(ts) - 2)  # (grid, fixes)
        w = (te - ts[j]) / (ts[j + 1] - ts[j])
        rows = np.arange(len(te))[:, None]
        phi = psi[None, :] - bias[:, None] * (ts - ts[0])[None, :]  # (grid, samples)
        at_fix = phi[rows, j] * (1.0 - w) + phi[rows, j + 1] * w
        psi0 = np.angle(np.mean(np.exp(1j * (val[None, :, 2] - at_fix)), axis=1))
        ang = phi + psi0[:, None]
        c, s = np.cos(ang), np.sin(ang)
        # a reading is the mean over the interval ending at its sample: integrated twice,
        # the acceleration and the two unit biases (body x, y) turned to the lab
        dt = np.diff(ts, prepend=ts[0])[None, :, None]
        cols = np.stack([c * acc[:, 0] - s * acc[:, 1], s * acc[:, 0] + c * acc[:, 1],
                         c, s, -s, c], axis=2)  # fmt: skip
        vel = np.cumsum(cols * dt, axis=1)
        pos = np.cumsum((vel - 0.5 * cols * dt) * dt, axis=1)  # (grid, samples, 6)
        at = pos[rows, j] * (1.0 - w[..., None]) + pos[rows, j + 1] * w[..., None]
        # z - P = p0 + v0 t - B b_a: second differences, whitened, b_a fitted
        d = np.einsum("kn,gnc->gkc", D2, at)  # (grid, n - 1, 6)
        dz = D2 @ val[:, :2]  # (n - 1, 2)
        y = np.concatenate([(dz[None, :, 0] - d[:, :, 0]) @ Wp[0].T,
                            (dz[None, :, 1] - d[:, :, 1]) @ Wp[1].T], axis=1)  # fmt: skip
        A = np.concatenate([np.einsum("kn,gnc->gkc", Wp[0], d[:, :, [2, 4]]),
                            np.einsum("kn,gnc->gkc", Wp[1], d[:, :, [3, 5]])], axis=1)  # fmt: skip
        AtA = np.einsum("gkc,gkd->gcd", A, A)
        Aty = np.einsum("gkc,gk->gc", A, y)
        coef = np.linalg.solve(AtA, Aty[..., None])[..., 0]
        r = y - np.einsum("gkc,gc->gk", A, coef)
        return np.sum(r * r, axis=1)

    @staticmethod
    def time_offset(s: PlanarState) -> tuple[float, float]:
        """The fixes' time offset and its 1-sigma (s)."""
        return float(s.x[TAU]), math.sqrt(max(float(s.P[TAU, TAU]), 0.0))

    def _fix_cov(self, fix: Fix) -> np.ndarray:
        if fix.cov is not None:
            return fix.cov + np.diag([1e-4, 1e-4, 1e-10])
        s_mm, s_rad = self.fix_sigma
        return np.diag([s_mm**2, s_mm**2, s_rad**2])

    def propagate(self, s: PlanarState, gyro: np.ndarray, accel: np.ndarray, dt: float):
        """The state ``dt`` s later: the heading turned by the gyro's mean rate less its
        bias, the body acceleration less its biases turned to the lab at the interval's
        mid-heading and integrated (LuVeX's integration equations), the lateness
        decayed (first-order Gauss-Markov over LATE_TIME_S)."""
        x = s.x
        w = gyro[0][2] - x[BG]  # the interval's mean rate (History.reading)
        psi_mid = x[PSI] + 0.5 * w * dt
        c, sn = math.cos(psi_mid), math.sin(psi_mid)
        ab = accel * 1000.0 - x[BA]  # mm/s^2, body
        an = np.array([c * ab[0] - sn * ab[1], sn * ab[0] + c * ab[1]])
        xn = x.copy()
        xn[POS] = x[POS] + x[VEL] * dt + 0.5 * an * dt * dt
        xn[VEL] = x[VEL] + an * dt
        xn[PSI] = x[PSI] + w * dt
        phi = math.exp(-dt / LATE_TIME_S)  # the lateness: first-order Gauss-Markov
        xn[LATE] = phi * x[LATE]
        F = transition(an, c, sn, dt)
        lasting = s.jitter.lasting
        Q = self.process_noise(dt, lasting)
        P = F @ s.P @ F.T + Q
        P[LATE, LATE] = max(P[LATE, LATE], lasting)  # a lateness just found is not known in value
        wmax = s.wmax
        if s.spread:
            peak, age = s.wmax
            wmax = (abs(w), 0.0) if abs(w) >= peak or age + dt > math.sqrt(s.spread) else \
                (peak, age + dt)  # fmt: skip
        return PlanarState(xn, P, w, s.jitter, s.dispute, s.pending,
                           (float(an[0]), float(an[1])), s.spread, wmax)  # fmt: skip

    def process_noise(self, dt: float, lasting: float) -> np.ndarray:
        """The process noise Q (10, 10) over an interval of ``dt`` s: the accelerometers'
        white noise integrated into velocity and position, the gyro's into the heading,
        the biases' and the time offset's random walks, and the lateness's Gauss-Markov
        increment (``lasting``: its variance, s^2)."""
        qa = (self.accel_noise * dt) ** 2
        Q = np.zeros((N_PLANAR, N_PLANAR))
        Q[X, X] = Q[Y, Y] = qa * dt * dt / 4.0
        Q[VX, VX] = Q[VY, VY] = qa
        Q[X, VX] = Q[VX, X] = Q[Y, VY] = Q[VY, Y] = qa * dt / 2.0
        Q[PSI, PSI] = (self.gyro_noise * dt) ** 2
        Q[BG, BG] = self.gyro_bias_walk**2 * dt
        Q[BAX, BAX] = Q[BAY, BAY] = self.accel_bias_walk**2 * dt
        Q[TAU, TAU] = self.time_offset_walk**2 * dt
        phi = math.exp(-dt / LATE_TIME_S)
        Q[LATE, LATE] = lasting * (1.0 - phi * phi)
        return Q

    def update(self, s: PlanarState, fix: Fix) -> tuple[PlanarState, bool, float]:
        """The state after a fix, whether the fix was accepted, and its normalised
        innovation squared (NIS; chi-square with 3 dof when the filter is consistent)."""
        R0 = self._fix_cov(fix)
        if s.spread:
            R0 = R0 + np.diag(s.spread * _rate_bound(s))
        x0 = s.x
        # the pose's rate: a timing error dt moves the fix by J dt
        J = np.array([x0[VX], x0[VY], s.w])
        if s.pending:
            return self._second(s, fix, R0), True, math.nan
        idx = POSE
        if self.method == "paper":
            x = s.x.copy()
            x[idx] = fix.value
            P = s.P.copy()
            P[idx, :] = 0.0
            P[:, idx] = 0.0
            P[np.ix_(idx, idx)] = R0
            return PlanarState(x, P, jitter=s.jitter, spread=s.spread, wmax=s.wmax), True, math.nan
        h, H = self._measure(x0, s.w, s.an, fix.shift)
        # the second-order terms of h's products (v tau, b_g tau): a Gaussian
        # second-order filter (Gelb, Applied Optimal Estimation, 1974, Sec. 6.1; for
        # h_i = c_i x_a x_tau: E h_i gains c_i P_a,tau and the innovation's covariance
        # c_i c_j (P_a,a' P_tau,tau + P_a,tau P_tau,a')). While the offset is known to tens
        # of ms and the bias to tenths of a degree per second, they are what the first
        # order leaves out: 0.5 deg/s by 50 ms is 0.025 deg, eight heading fix sigmas
        a = [VX, VY, BG]
        c = np.array([-1.0, -1.0, 1.0])
        Pa = s.P[a, TAU] + s.P[a, LATE]
        Poo = s.P[TAU, TAU] + 2.0 * s.P[TAU, LATE] + s.P[LATE, LATE]
        h = h + c * Pa
        R_nj = R0 + np.outer(c, c) * (s.P[np.ix_(a, a)] * Poo + np.outer(Pa, Pa))
        r = self._wrap(fix.value - h)
        PHt = s.P @ H.T
        S_nj = H @ PHt + R_nj  # without the timing jitter
        S = S_nj + np.outer(J, J) * s.jitter.var
        # this fix's own timing error: where its innovation along J is beyond what the
        # jitter explains (p = JITTER_OWN_P, one degree of freedom), its timing variance
        # is what makes it as expected (the one-fix covariance match of PlanarJitter):
        # a frame that came late for a moment counts for what it is worth along J
        # instead of being refused (or, taken with the jitter's sigma, pulling the pose
        # by many of its sigmas); a disagreement across J is gated as before
        u = np.linalg.solve(S, J)
        g = float(J @ u)
        p2 = float(u @ r) ** 2
        if g > 0.0 and p2 > g * JITTER_OWN_CHI2:
            S = S + np.outer(J, J) * (p2 - g) / (g * g)
        nis = float(r @ np.linalg.solve(S, r))
        if nis > nis_limit():
            # refused: the filter or the fix is wrong. The rows' covariance is widened by
            # the disagreement, so that they stay honest whichever it was; the filter's
            # own is not, so that the next fix is gated as narrowly: a fix that merely
            # agrees with this one must not be taken as the truth with its own small
            # sigma. A fix that agrees with the filter ends the dispute; fixes refused
            # for restart_after_s restart the filter on the latest (Fusion.step).
            return replace(s, dispute=np.outer(r, r)), False, nis
        R = S - H @ PHt
        K = np.linalg.solve(S, PHt.T).T
        if s.spread:
            # fixes whose timing is not known yet: they correct the pose and velocity,
            # the biases are considered (a lag taken for a bias would stay after it)
            K[BG:] = 0.0
        x = s.x + K @ r
        # the offset within what a camera can be late by (the alignment's range): beyond
        # it the filter has gone wrong, and the engine's shift follows the offset
        x[TAU] = min(max(x[TAU], ALIGN_TAU[0]), ALIGN_TAU[1])
        IKH = np.eye(N_PLANAR) - K @ H
        P = IKH @ s.P @ IKH.T + K @ R @ K.T  # Joseph form
        jitter = s.jitter
        if self.learn_jitter:
            jitter = jitter.learn(r, S_nj, J)
        return PlanarState(x, P, s.w, jitter, spread=s.spread, wmax=s.wmax), True, nis

    def _second(self, s: PlanarState, fix: Fix, R0: np.ndarray) -> PlanarState:
        """The second fix after a start: with the first, it gives the velocity, and only
        then can the fixes' time offset be coupled to the pose.

        The fix measures the pose tau before its stated time, h = pose - J tau with
        J = (v, w), bilinear in the velocity and the offset. Linearised at the start,
        where the velocity is unknown (0 +- velocity_sigma), the update would take the
        first fixes' pose as the pose at their stated time with their own small sigma:
        the heading, off by w tau, would pin the offset near its prior mean at the next
        fix (at 0.2 rad/s a heading fix's 0.003 deg is 0.3 ms), and the offset would
        then creep to its value over minutes with every row beyond its sigma (the
        planar live soak, 2026-11-27). So the first two fixes are taken as if the
        offset were zero (its column and gain left out: the state is then the pose at
        tau before the stated time, the velocity their IMU-corrected difference), and
        then the offset is added as what it is, an unknown independent of them: the
        pose at the stated time is that pose plus J tau (J from the new velocity, the
        gyro's rate and the IMU's acceleration), so the mean moves by J tau^ and the
        covariance gains J P_tt J^T with the cross terms J P_tt. From there the
        ordinary update is linearised at a known velocity."""
        H = np.zeros((3, N_PLANAR))  # the pose itself: the offset left out
        H[0, X] = H[1, Y] = H[2, PSI] = 1.0
        r = self._wrap(fix.value - s.x[POSE])
        PHt = s.P @ H.T
        J = np.array([s.x[VX], s.x[VY], s.w])
        R = R0 + np.outer(J, J) * s.jitter.var
        for _ in range(2):
            # twice: the fixes' timing jitter moves them along the velocity, which only
            # this update tells (the first pass's velocity makes the second's J)
            K = np.linalg.solve(H @ PHt + R, PHt.T).T
            K[BG if s.spread else TAU :] = 0.0
            x = s.x + K @ r
            J = np.array([x[VX], x[VY], s.w])
            R = R0 + np.outer(J, J) * s.jitter.var
        IKH = np.eye(N_PLANAR) - K @ H
        P = IKH @ s.P @ IKH.T + K @ R @ K.T
        # the offset, coupled: the pose, velocity and heading at the stated time
        G = np.zeros(N_PLANAR)
        G[[X, Y, VX, VY, PSI]] = [x[VX], x[VY], s.an[0], s.an[1], s.w]
        G[TAU] = 0.0
        ptt = P[TAU, TAU]
        x[X : PSI + 1] += G[X : PSI + 1] * (x[TAU] - fix.shift)
        cross = P[:, TAU].copy()
        P = P + np.outer(G, G) * ptt + np.outer(G, cross) + np.outer(cross, G)
        return PlanarState(x, P, s.w, s.jitter, None, False, s.an, s.spread, s.wmax)

    def reinit(self, s: PlanarState, fix: Fix) -> PlanarState:
        """Start again from ``fix``'s pose (the velocity unknown again), keeping what was
        learned of the IMU (its biases) and of the fixes' jitter; the time offset goes
        back to its prior (a filter that refused fixes in a row may have had it
        wrong), centred on the shift the fix is applied with."""
        n = self.init(fix)
        keep = [BG, BAX, BAY]
        P = n.P.copy()
        P[np.ix_(keep, keep)] = s.P[np.ix_(keep, keep)]
        x = n.x.copy()
        x[keep] = s.x[keep]
        return PlanarState(x, P, s.w, s.jitter, pending=True, spread=s.spread, wmax=s.wmax)

    @staticmethod
    def _measure(
        x: np.ndarray, w: float, an: tuple[float, float], shift: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pose a fix measures from state ``x`` (at the fix's true exposure, tau
        before its stated time) and its derivatives by the state; ``w`` is the rate
        less the bias (w = gyro - b_g: d(-w tau)/d(b_g) = tau)."""
        # what is left of the offset (the fix was applied shifted), and the lateness
        tau = x[TAU] + x[LATE] - shift
        # to second order in tau for the position (0.5 a tau^2 is 0.03 mm at 40 ms and
        # 35 mm/s^2, two lamp fix sigmas); the acceleration as the IMU measured it
        ax, ay = an
        h = np.array([x[X] - x[VX] * tau + 0.5 * ax * tau * tau,
                      x[Y] - x[VY] * tau + 0.5 * ay * tau * tau,
                      x[PSI] - w * tau])  # fmt: skip
        H = np.zeros((3, N_PLANAR))
        H[0, X] = H[1, Y] = H[2, PSI] = 1.0
        H[0, VX] = H[1, VY] = -tau
        H[2, BG] = tau
        H[:, TAU] = H[:, LATE] = [-x[VX] + ax * tau, -x[VY] + ay * tau, -w]
        return h, H

    @staticmethod
    def _wrap(r: np.ndarray) -> np.ndarray:
        r = r.copy()
        r[2] = (r[2] + math.pi) % (2 * math.pi) - math.pi
        return r

    @staticmethod
    def values(s: PlanarState) -> tuple[np.ndarray, np.ndarray]:
        """(x_mm, y_mm, heading rad) and their 1-sigma."""
        v = s.x[POSE].copy()
        v[2] = (v[2] + math.pi) % (2 * math.pi) - math.pi
        var = np.diag(s.P)[POSE]
        if s.dispute is not None:
            var = var + np.diag(s.dispute)
        if s.pending:
            # from one fix: it is the pose tau before its stated time, and the velocity
            # is not known (PlanarModel._second)
            ptt = s.P[TAU, TAU] + 2.0 * s.P[TAU, LATE] + s.P[LATE, LATE]
            var = var + ptt * np.array([s.x[VX] ** 2 + s.P[VX, VX], s.x[VY] ** 2 + s.P[VY, VY],
                                        s.w**2])  # fmt: skip
        if s.spread:
            # fixes whose time offset is not known yet (Fusion, while the clocks align):
            # the pose moves by its rate times an offset anywhere in the range
            var = var + s.spread * _rate_bound(s)
        return v, np.sqrt(np.clip(var, 0.0, None))
