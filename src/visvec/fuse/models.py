"""Filters for `visvec fuse`: inertial propagation and fix updates, planar and 3-D.

Planar (LuVeX, Keldysh preprint 2011-24, Sec. 3.1.2 and 4.1): the gyro's rate and the
accelerometer's body-frame reading, less their biases, are turned into the lab frame
and integrated (the paper's integration equations; its heading phi is our -psi, so its
(a_x cos phi + a_y sin phi, a_y cos phi - a_x sin phi) is our Rz(psi) a_B). Two update
rules share this propagation:
- "paper": a fix replaces x, y and the heading at its exposure time (the paper's
  re-integration "with quite accurate initial condition"); velocity and biases are
  kept (biases from the rest calibration only);
- "kalman" (default): an extended Kalman filter on [x, y, vx, vy, psi, b_g, b_ax, b_ay]
  (mm, mm/s, rad, rad/s, mm/s^2) that also estimates the biases; fixes update it with
  their own covariance and fixes whose innovation is implausible (chi-square, 3 dof,
  p < 1e-6) are refused.

3-D: a multiplicative extended Kalman filter (Markley & Crassidis, Fundamentals of
Spacecraft Attitude Determination and Control, 2014, Sec. 6.2) on the attitude error,
the gyro bias and, beyond the usual filter, the gyro's misalignment to the fixes' body
frame and its scale factors: omega_B = R_m (1 + k) (omega_g - b), k diagonal. With
R_true = R exp([dth]x), b = b^ + db, R_m = exp([dphi]x) R_m^ and k = k^ + dk, the
error obeys (to first order)
    dth' = -[w]x dth - R_m^ (1 + k^) db - [w]x dphi - R_m^ diag(omega_g - b^) dk,
    w = R_m^ (1 + k^) (omega_g - b^),
so misalignment and scale show whenever the body turns; they are estimated from the
data. A zero prior sigma keeps a parameter fixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from visvec.fuse.inputs import Fix
from visvec.rotations import expmap, logmap, skew

NIS_LIMIT = float(chi2.ppf(1.0 - 1e-6, 3))


@dataclass(frozen=True)
class PlanarState:
    x: np.ndarray  # [x, y, vx, vy, psi, b_g, b_ax, b_ay]
    P: np.ndarray


@dataclass(frozen=True)
class PlanarModel:
    """Planar fusion; noises per IMU sample (white), bias random walks per sqrt(s)."""

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

    planar = True

    def init(self, fix: Fix) -> PlanarState:
        x = np.array([fix.value[0], fix.value[1], 0.0, 0.0, fix.value[2], self.gyro_bias0,
                      *self.accel_bias0])  # fmt: skip
        R = self._fix_cov(fix)
        P = np.diag([R[0, 0], R[1, 1], self.velocity_sigma**2, self.velocity_sigma**2,
                     R[2, 2], self.gyro_bias_sigma**2, self.accel_bias_sigma**2,
                     self.accel_bias_sigma**2])  # fmt: skip
        return PlanarState(x, P)

    def _fix_cov(self, fix: Fix) -> np.ndarray:
        if fix.cov is not None:
            return fix.cov + np.diag([1e-4, 1e-4, 1e-10])
        s_mm, s_rad = self.fix_sigma
        return np.diag([s_mm**2, s_mm**2, s_rad**2])

    def propagate(self, s: PlanarState, gyro: np.ndarray, accel: np.ndarray, dt: float):
        x = s.x
        w = gyro[2] - x[5]
        psi_mid = x[4] + 0.5 * w * dt
        c, sn = math.cos(psi_mid), math.sin(psi_mid)
        ab = accel * 1000.0 - x[6:8]  # mm/s^2, body
        an = np.array([c * ab[0] - sn * ab[1], sn * ab[0] + c * ab[1]])
        xn = x.copy()
        xn[0:2] = x[0:2] + x[2:4] * dt + 0.5 * an * dt * dt
        xn[2:4] = x[2:4] + an * dt
        xn[4] = x[4] + w * dt
        F = np.eye(8)
        F[0, 2] = F[1, 3] = dt
        dan = np.array([-an[1], an[0]])  # d(a_N)/d(psi)
        F[0:2, 4] = 0.5 * dan * dt * dt
        F[2:4, 4] = dan * dt
        Rz = np.array([[c, -sn], [sn, c]])
        F[0:2, 6:8] = -0.5 * Rz * dt * dt
        F[2:4, 6:8] = -Rz * dt
        F[4, 5] = -dt
        qa = (self.accel_noise * dt) ** 2
        Q = np.zeros((8, 8))
        Q[0, 0] = Q[1, 1] = qa * dt * dt / 4.0
        Q[2, 2] = Q[3, 3] = qa
        Q[0, 2] = Q[2, 0] = Q[1, 3] = Q[3, 1] = qa * dt / 2.0
        Q[4, 4] = (self.gyro_noise * dt) ** 2
        Q[5, 5] = self.gyro_bias_walk**2 * dt
        Q[6, 6] = Q[7, 7] = self.accel_bias_walk**2 * dt
        return PlanarState(xn, F @ s.P @ F.T + Q)

    def update(self, s: PlanarState, fix: Fix) -> tuple[PlanarState, bool, float]:
        """The state after a fix, whether the fix was accepted, and its normalised
        innovation squared (NIS; chi-square with 3 dof when the filter is consistent)."""
        R = self._fix_cov(fix)
        r = fix.value - s.x[[0, 1, 4]]
        r[2] = (r[2] + math.pi) % (2 * math.pi) - math.pi
        idx = [0, 1, 4]
        if self.method == "paper":
            x = s.x.copy()
            x[idx] = fix.value
            P = s.P.copy()
            P[idx, :] = 0.0
            P[:, idx] = 0.0
            P[np.ix_(idx, idx)] = R
            return PlanarState(x, P), True, math.nan
        S = s.P[np.ix_(idx, idx)] + R
        nis = float(r @ np.linalg.solve(S, r))
        if nis > NIS_LIMIT:
            return s, False, nis
        K = np.linalg.solve(S, s.P[idx, :]).T
        x = s.x + K @ r
        IKH = np.eye(8)
        IKH[:, idx] -= K
        P = IKH @ s.P @ IKH.T + K @ R @ K.T  # Joseph form
        return PlanarState(x, P), True, nis

    @staticmethod
    def values(s: PlanarState) -> tuple[np.ndarray, np.ndarray]:
        """(x_mm, y_mm, heading rad) and their 1-sigma."""
        v = s.x[[0, 1, 4]].copy()
        v[2] = (v[2] + math.pi) % (2 * math.pi) - math.pi
        return v, np.sqrt(np.clip(np.diag(s.P)[[0, 1, 4]], 0.0, None))


@dataclass(frozen=True)
class AttitudeState:
    R: np.ndarray  # R_NB
    b: np.ndarray  # gyro bias, rad/s, gyro axes
    Rm: np.ndarray  # gyro axes -> body axes
    k: np.ndarray  # gyro scale factor errors (3,)
    P: np.ndarray  # (12, 12): dtheta (body), db, dphi (body), dk


@dataclass(frozen=True)
class AttitudeModel:
    """3-D fusion (MEKF) with gyro bias, misalignment and scale factors."""

    gyro_noise: float = math.radians(0.3)  # rad/s per sample
    gyro_bias_walk: float = math.radians(0.01)  # rad/s/sqrt(s)
    gyro_bias0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_bias_sigma: float = math.radians(1.0)
    misalignment_sigma: float = math.radians(5.0)  # 0: not estimated
    scale_sigma: float = 0.0  # relative; 0: not estimated (the default)
    fix_sigma: float = math.radians(0.1)

    planar = False

    def init(self, fix: Fix) -> AttitudeState:
        P = np.zeros((12, 12))
        P[0:3, 0:3] = self._fix_cov(fix)
        P[3:6, 3:6] = np.eye(3) * self.gyro_bias_sigma**2
        P[6:9, 6:9] = np.eye(3) * self.misalignment_sigma**2
        P[9:12, 9:12] = np.eye(3) * self.scale_sigma**2
        b0 = np.array(self.gyro_bias0, float)
        return AttitudeState(fix.value.copy(), b0, np.eye(3), np.zeros(3), P)

    def _fix_cov(self, fix: Fix) -> np.ndarray:
        if fix.cov is not None:
            return fix.cov + np.eye(3) * 1e-10
        return np.eye(3) * self.fix_sigma**2

    def propagate(self, s: AttitudeState, gyro: np.ndarray, accel, dt: float):
        wg = (1.0 + s.k) * (gyro - s.b)  # scaled, in gyro axes
        w = s.Rm @ wg
        Rn = s.R @ expmap(w * dt)
        F = np.eye(12)
        F[0:3, 0:3] = expmap(-w * dt)  # exact transition of -[w]x
        F[0:3, 3:6] = -(s.Rm * (1.0 + s.k)) * dt
        F[0:3, 6:9] = -skew(w) * dt
        F[0:3, 9:12] = -(s.Rm * (gyro - s.b)) * dt
        Q = np.zeros((12, 12))
        Q[0:3, 0:3] = np.eye(3) * (self.gyro_noise * dt) ** 2
        Q[3:6, 3:6] = np.eye(3) * self.gyro_bias_walk**2 * dt
        return AttitudeState(Rn, s.b, s.Rm, s.k, F @ s.P @ F.T + Q)

    def update(self, s: AttitudeState, fix: Fix) -> tuple[AttitudeState, bool, float]:
        R = self._fix_cov(fix)
        r = logmap(s.R.T @ fix.value)
        S = s.P[0:3, 0:3] + R
        nis = float(r @ np.linalg.solve(S, r))
        if nis > NIS_LIMIT:
            return s, False, nis
        K = np.linalg.solve(S, s.P[0:3, :]).T
        dx = K @ r
        IKH = np.eye(12)
        IKH[:, 0:3] -= K
        P = IKH @ s.P @ IKH.T + K @ R @ K.T
        Rn = s.R @ expmap(dx[0:3])
        Rm = expmap(dx[6:9]) @ s.Rm
        return AttitudeState(Rn, s.b + dx[3:6], Rm, s.k + dx[9:12], P), True, nis

    @staticmethod
    def values(s: AttitudeState) -> tuple[np.ndarray, np.ndarray]:
        """R_NB and the body-axis attitude covariance (3, 3)."""
        return s.R, s.P[0:3, 0:3]
