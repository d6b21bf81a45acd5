"""Angular rate of the camera from matched star directions of two frames.

Two estimators of omega (rad/s, camera frame C, the camera's rate relative to the stars):

``poisson`` (Fasano et al., Sensors 2013, Sec. 2.2, Eqs. (3)-(4)): stars are fixed in
inertial space, so in the camera frame du/dt = -omega x u = [u]x omega. Each star gives
three (dependent) linear equations; all are stacked and solved by least squares through
a QR decomposition; residuals flag outliers. We evaluate [u]x at the mid-point
(u1 + u2) / 2 of the two directions, which makes the finite difference exact to second
order (u2 - u1 = 2 tan(theta/2) k x (u1 + u2) / 2 for a rotation theta about k), where
the paper's first-frame u leaves a first-order error.

``crassidis`` (after Crassidis, "Angular velocity determination directly from star
tracker measurements", J. Guidance, Control, and Dynamics 25(6), 2002): the rotation
between the matched direction sets of the two frames, found in closed form as the
optimal rotation of Wahba's problem (SVD, Markley 1988), gives omega = -log(R) / dt
with the QUEST measurement-model covariance (Shuster & Oh 1981) of the rotation. It is
exact for any rotation per frame, so it is the better choice when a frame turns the
camera by more than a few degrees (low frame rates, fast tumbles); below that both give
the same answer (measured in benchmarks/RESULTS.md).

Both reject outliers iteratively: a star whose residual exceeds 4 robust sigmas (and
three times the centroid noise), or 2 px in any case, is dropped and the fit repeated;
unless at least half the stars (and 5) agree, there is no rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visvec.rotations import expmap, logmap

OUTLIER_SIGMAS = 4.0
MIN_STARS = 5
MIN_INLIER_FRACTION = 0.5
MAX_RESIDUAL_PX = 2.0


@dataclass(frozen=True)
class RateSolution:
    """omega (3,) rad/s in C; cov (3, 3) rad^2/s^2; rms_px: RMS residual of the inliers
    in pixels; inliers: (N,) bool; ok: enough consistent stars; reason when not ok."""

    omega: np.ndarray
    cov: np.ndarray
    rms_px: float
    inliers: np.ndarray
    ok: bool
    reason: str = ""

    @property
    def n_points(self) -> int:
        return int(self.inliers.sum())


def unit_vectors(xy_n: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors of normalised image coordinates (N, 2)."""
    v = np.column_stack([xy_n, np.ones(len(xy_n))])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def skew_stack(u: np.ndarray) -> np.ndarray:
    """(3N, 3) stacked cross-product matrices [u_i]x."""
    n = len(u)
    A = np.zeros((n, 3, 3))
    A[:, 0, 1], A[:, 0, 2] = -u[:, 2], u[:, 1]
    A[:, 1, 0], A[:, 1, 2] = u[:, 2], -u[:, 0]
    A[:, 2, 0], A[:, 2, 1] = -u[:, 1], u[:, 0]
    return A.reshape(3 * n, 3)


def _poisson_fit(u1: np.ndarray, u2: np.ndarray, dt: float, w: np.ndarray):
    """omega and (A^T W A)^-1 of the Poisson least squares, star i weighted by w_i."""
    um = 0.5 * (u1 + u2)
    sw = np.repeat(np.sqrt(w), 3)[:, None]
    A = skew_stack(um) * sw
    b = ((u2 - u1) / dt).ravel() * sw[:, 0]
    Q, R = np.linalg.qr(A)  # Fasano et al.: least squares by QR
    omega = np.linalg.solve(R, Q.T @ b)
    Rinv = np.linalg.inv(R)
    return omega, Rinv @ Rinv.T


def _wahba_fit(u1: np.ndarray, u2: np.ndarray, dt: float, w: np.ndarray):
    """omega and (sum w_i (I - u_i u_i^T))^-1 (the inverse QUEST information matrix),
    from the rotation R with u2 = R u1 that best fits the pairs weighted by w_i."""
    B = (u2 * w[:, None]).T @ u1
    U, _, Vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    R = U @ np.diag([1.0, 1.0, d]) @ Vt
    # u_C(t + dt) = exp(-[omega]x dt) u_C(t), so R = exp(-[omega]x dt)
    omega = -logmap(R) / dt
    um = 0.5 * (u1 + u2)
    um /= np.linalg.norm(um, axis=1, keepdims=True)
    F = w.sum() * np.eye(3) - (um * w[:, None]).T @ um
    return omega, np.linalg.inv(F)


def estimate_rate(
    xy1: np.ndarray,
    xy2: np.ndarray,
    dt: float,
    f_px: float,
    sigma_px: float,
    method: str = "poisson",
    var_px: np.ndarray | None = None,
) -> RateSolution:
    """omega from matched normalised image points of two frames ``dt`` seconds apart.

    Parameters
    ----------
    xy1, xy2 : (N, 2) undistorted normalised coordinates of the same stars.
    f_px : focal length in pixels (to express residuals in pixels).
    sigma_px : a-priori 1-sigma of one centroid on one axis, every star's floor.
    method : "poisson" (the paper) or "crassidis".
    var_px : (N,) each star's displacement variance per axis (px^2) from its pixel
        noise, both centroids together, or None (then the floor alone). Stars are
        weighted by the inverse of their variance plus the floor: a faint star's
        centroid is worse than a bright one's, and the paper's unweighted least
        squares lets it count as much.
    """
    u1, u2 = unit_vectors(xy1), unit_vectors(xy2)
    n = len(u1)
    inl = np.ones(n, dtype=bool)
    fit = _poisson_fit if method == "poisson" else _wahba_fit
    nan3 = np.full(3, np.nan)
    if n < MIN_STARS:
        return RateSolution(nan3, np.full((3, 3), np.nan), np.nan, inl, False, "too_few_matches")
    sig_rad = sigma_px / f_px
    var = np.full(n, 2.0 * sigma_px**2) if var_px is None else var_px + 2.0 * sigma_px**2
    w = (f_px**2) / var  # 1 / rad^2
    cap = MAX_RESIDUAL_PX / f_px  # a star off by more never fits
    for it in range(10):
        omega, _ = fit(u1[inl], u2[inl], dt, w[inl])
        full = np.linalg.norm(u2 - _predict(u1, omega, dt), axis=1)
        s = 1.4826 * np.median(full[inl])
        lim = max(OUTLIER_SIGMAS * s, 3.0 * np.sqrt(2.0) * sig_rad)
        if it > 0:  # the first fit may be pulled by the outliers: no cap yet
            lim = min(lim, cap)
        new = full <= lim
        if np.array_equal(new, inl) or new.sum() < MIN_STARS:
            inl = new
            break
        inl = new
    if inl.sum() >= MIN_STARS:
        omega, _ = fit(u1[inl], u2[inl], dt, w[inl])
        inl &= np.linalg.norm(u2 - _predict(u1, omega, dt), axis=1) <= cap
    if inl.sum() < MIN_STARS:
        return RateSolution(
            nan3, np.full((3, 3), np.nan), np.nan, inl, False, "no_consistent_motion"
        )
    omega, H = fit(u1[inl], u2[inl], dt, w[inl])
    k = int(inl.sum())
    if k < MIN_STARS or k < MIN_INLIER_FRACTION * n:
        return RateSolution(
            nan3, np.full((3, 3), np.nan), np.nan, inl, False, "no_consistent_motion"
        )
    # H / dt^2 is the covariance if the noise model is right. Beside it, the sandwich
    # (heteroscedasticity-consistent) form H (sum w_i^2 A_i^T e_i e_i^T A_i) H with
    # A_i = [u_i]x and e_i the residual of star i measures what the residuals show,
    # whatever the model: the larger is reported. Each residual is divided by 1 - h_i,
    # its star's leverage (HC3, MacKinnon & White 1985): the fit pulls toward the stars
    # that weigh most and hides their errors, which matters with few stars.
    wi = w[inl]
    um = 0.5 * (u1[inl] + u2[inl])
    e = u2[inl] - _predict(u1[inl], omega, dt)
    A = skew_stack(um).reshape(-1, 3, 3)
    lev = wi * np.einsum("kij,jl,kil->k", A, H, A) / 2.0  # w_i trace(A_i H A_i^T) / 2 dof
    g = wi[:, None] * np.cross(um, e) / np.clip(1.0 - lev, 0.2, 1.0)[:, None]  # -w_i A_i^T e_i
    cov = H @ (g.T @ g) @ H / dt**2
    model = H / dt**2
    if np.trace(cov) < np.trace(model):
        cov = model
    res = np.linalg.norm(e, axis=1)
    rms_px = float(np.sqrt(np.mean(res**2))) * f_px
    return RateSolution(omega, cov, rms_px, inl, True)


def _predict(u1: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Directions after dt at rate omega: u(t + dt) = exp(-[omega]x dt) u(t)."""
    return u1 @ expmap(-omega * dt).T


@dataclass(frozen=True)
class RateBudget:
    """The paper's first-order error budget (deg/s): ``cross`` for omega_1 and omega_2
    (Eq. 14), ``boresight`` for omega_3 (Eq. 28), ``boresight_full`` with the
    rate-dependent term of Eq. (26) kept (equal to Eq. 28 at zero rate)."""

    cross: float
    boresight: float
    boresight_full: float


def rate_budget(
    ifov_deg: float,
    fps: float,
    n_stars: float,
    pixels_per_star: float,
    off_boresight_deg: float,
    w3_dps: float = 0.0,
) -> RateBudget:
    """Fasano et al. (Sensors 2013), Sec. 2.3.

    One star's centroid is good to IFOV / sqrt(N_starpixels) (Eq. 13), its apparent
    velocity to sqrt(2) times that over dt, and N stars average it down:
    sigma_w1 = sqrt(2) IFOV / (dt sqrt(N N_starpixels)) (Eq. 14). About the boresight a
    star at chi from the boresight sees only chi times the motion:
    sigma_w3 = sigma_w1 / chi (Eq. 28), or with the first term of Eq. (26) kept,
    sigma_w3^2 = [(w3 / chi)^2 IFOV^2 / N_px + (1 / chi)^2 2 IFOV^2 / (dt^2 N_px)] / N.
    """
    dt = 1.0 / fps
    ifov = np.radians(ifov_deg)
    chi = np.radians(off_boresight_deg)
    w1 = np.sqrt(2.0) * ifov / (dt * np.sqrt(n_stars * pixels_per_star))
    w3 = w1 / chi
    w3r = np.radians(w3_dps)
    full = np.sqrt(
        ((w3r / chi) ** 2 * ifov**2 / pixels_per_star
         + (1.0 / chi) ** 2 * 2.0 * ifov**2 / (dt**2 * pixels_per_star)) / n_stars
    )  # fmt: skip
    return RateBudget(float(np.degrees(w1)), float(np.degrees(w3)), float(np.degrees(full)))
