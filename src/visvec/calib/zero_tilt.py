"""Zero-tilt calibration of the triangle rig from frames taken with the platform level.

For the "full" estimator: the target's horizontal offset from the rotation axis
(dx, dy in N), its height's error against the rig file (dh: the triangle's image size;
a camera's tone curve and most of a print's scale show here too) and the camera's
mounting tilt (small rotations about b1 and b2), jointly with
each frame's unknown yaw, by weighted least squares on the vertex positions
(scipy.optimize.least_squares). A camera rotation about b3 cannot be told from a yaw
offset without a yaw reference: with stops at known yaws it is estimated after the fit
(:func:`yaw_reference`). A sideways camera offset cannot be told from a camera tilt (the
target is one plane), so the rig's camera position is kept.

Before the sigma check below, the frames test the rig's camera model: the fit is repeated with
the camera's aspect fy / fx and principal point free. A wrong aspect stretches the
image along its columns, which changes the triangle's shape with twice the yaw (an
offset moves it with the yaw, a camera tilt not at all, a print drawn wrong keeps its
shape in the triangle's frame); a principal point off shifts the image as a camera tilt
does, but leaves a keystone that turns with the yaw. From 24 level frames at 640x480
they come out to 0.009 % and 0.43 px. When the check is significant
(CAMERA_CHECK_QUANTILE) and the aspect is ASPECT_MIN or the principal point
PRINCIPAL_POINT_MIN of the width off, the rig's [camera] is said to be wrong, with the
values that fit, and nothing is written: the residuals such an error leaves would
otherwise read as a wider noise (a sigma_scale of 5.5 for an aspect 0.5 % off, 1.33
for a principal point 4 px off).

The same fit checks the vertices' sigma on this camera: with each frame's yaw free, the
weighted residuals' chi-square over its degrees of freedom (the a-posteriori variance
factor of a least-squares adjustment) is the square of how much wider the vertices
scatter than their covariance says. Recordings through a lossy codec scatter wider than
the edge-noise model (block errors correlated along an edge); when the excess is
significant the ratio is written as ``[detect] sigma_scale``, which scales every later
row's sigma.

For the "paper" estimator: the zero-tilt centroid, the centre of the circle the
triangle's centroid traces as the level platform turns (Kasa's algebraic circle fit; the
mean when the yaws do not spread).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from visvec.chi2 import ppf as chi2_ppf
from visvec.data import Detection, Status
from visvec.errors import InputFileError, SourceError
from visvec.estimate.shear import ASPECT_MIN, PRINCIPAL_POINT_MIN
from visvec.rig import Rig
from visvec.rotations import rot_x, rot_y, rot_z

MIN_FRAMES = 3
MIN_YAW_SPREAD_DEG = 60.0
# the vertices' scatter counts as wider than their sigma when chi-square exceeds this
# quantile of its distribution under the covariance (a 1 % false alarm rate)
SIGMA_CHECK_QUANTILE = 0.99
# the camera check: significant when the chi-square falls by more than this quantile of
# a chi-square of 3 degrees of freedom (aspect, principal point x and y) once they are
# free; the rig's [camera] is then said to be wrong if the aspect is ASPECT_MIN off or
# the principal point PRINCIPAL_POINT_MIN of the image width (2 px at 640: a principal
# point 2 px off leaves the sigma check at 1.09, 4 px at 1.33)
CAMERA_CHECK_QUANTILE = 0.999
# a frame whose own weighted residual (chi-square, 5 degrees of freedom: 6 vertex
# coordinates less its yaw) exceeds this quantile is named as an outlier
OUTLIER_QUANTILE = 0.999


@dataclass(frozen=True)
class ZeroTiltResult:
    """Estimated offsets with 1-sigma uncertainties.

    target_offset_mm : (2,) and sigma_target_offset_mm : (2,)
    height_offset_mm, sigma_height_offset_mm : the target's height less the rig's
    camera_tilt_deg : (2,) rotation of the camera about b1 then b2, and its sigma
    centroid_px : (2,) zero-tilt centroid for the paper estimator, and its sigma
    yaw_deg : (K,) each frame's yaw
    residual_px : (K,) RMS vertex residual per frame
    rms_px : float, overall
    sigma_ratio : float, the vertices' scatter over their sigma without any sigma_scale
        (sqrt of chi-square per degree of freedom), and sigma_ratio_95 : (2,) its 95 %
        interval; dof : int, the degrees of freedom
    sigma_scale : float, sigma_ratio if significantly above 1, else 1
    camera check, the offsets fitted with the rig's camera model free besides:
    aspect, sigma_aspect : its aspect error e (the true fy is about (1 + e) times the
        rig's, for its fx), and its 1-sigma
    principal_point_px, sigma_principal_point_px : (2,) the true principal point less
        the rig's (cx, cy), and their 1-sigma
    camera_off : the check significant and the error large enough to matter (see
        calibrate_zero_tilt)
    outliers : (K,) bool, frames left out of the fit (see calibrate_zero_tilt); their
        yaw_deg and residual_px are against the offsets of the others
    """

    target_offset_mm: np.ndarray
    sigma_target_offset_mm: np.ndarray
    camera_tilt_deg: np.ndarray
    sigma_camera_tilt_deg: np.ndarray
    height_offset_mm: float
    sigma_height_offset_mm: float
    centroid_px: np.ndarray
    sigma_centroid_px: np.ndarray
    yaw_deg: np.ndarray
    residual_px: np.ndarray
    rms_px: float
    converged: bool
    sigma_ratio: float = 1.0
    sigma_ratio_95: np.ndarray = field(default_factory=lambda: np.ones(2))
    dof: int = 0
    sigma_scale: float = 1.0
    outliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    aspect: float = 0.0
    sigma_aspect: float = float("inf")
    principal_point_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    sigma_principal_point_px: np.ndarray = field(default_factory=lambda: np.full(2, np.inf))
    camera_off: bool = False
    # (K,) each frame's yaw sigma from the fit (deg; nan for a frame left out)
    sigma_yaw_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # the camera's turn about b3 on its mount (deg), from stops at known yaws (see
    # yaw_reference); nan: not calibrated
    camera_turn_deg: float = float("nan")
    sigma_camera_turn_deg: float = float("nan")
    yaw_stops: int = 0
    # the stops' scatter about the turn over their sigma (chi-square per degree of
    # freedom, nan with one stop): above about 3, a yaw given wrong or a stop that moved
    yaw_stop_chi2_dof: float = float("nan")
    # (4, 4) the covariance of (dx, dy: mm; camera tilt about b1, b2: deg), the errors
    # every row made with this calibration shares (Rig.zero_tilt.cov_body)
    offsets_cov: np.ndarray | None = None

    def apply(self, rig: Rig) -> Rig:
        """The rig with the calibration applied."""
        v = rig.target.vertices_mm.copy()
        v[:, :2] += self.target_offset_mm
        v[:, 2] += self.height_offset_mm
        a = np.radians(self.camera_tilt_deg)
        R_bc = rot_x(a[0]) @ rot_y(a[1]) @ rig.R_bc
        if np.isfinite(self.camera_turn_deg):
            # the camera turned about b3 (the body's own axis, applied last)
            R_bc = rot_z(np.radians(self.camera_turn_deg)) @ R_bc
        return replace(
            rig,
            target=replace(rig.target, vertices_mm=v),
            mount=replace(rig.mount, rotation=R_bc),
            zero_tilt=replace(
                rig.zero_tilt,
                centroid_px=self.centroid_px,
                offsets_cov=self.offsets_cov,
                turn_sigma_deg=self.sigma_camera_turn_deg,
            ),
            detect=replace(rig.detect, sigma_scale=self.sigma_scale),
        )


# the offsets fitted besides each frame's yaw: dx, dy, a, b, dh
N_COMMON = 5


# the camera check's parameters, after the offsets: aspect e, principal point (px) x, y
N_CAMERA = 3


def _model(params: np.ndarray, rig: Rig, n: int, camera: bool = False) -> np.ndarray:
    """(n, 3, 2) normalised projections for params = [dx, dy, a, b, dh, yaw_1..yaw_n]
    (``camera``: [dx, dy, a, b, dh, e, px, py, yaw_1..]: seen through the rig's camera
    model, y is (1 + e) times the true one, and x, y are shifted by px / fx, py / fy for
    a true principal point (px, py) from the rig's)."""
    dx, dy, a, b, dh = params[:N_COMMON]
    e, px, py = params[N_COMMON : N_COMMON + N_CAMERA] if camera else (0.0, 0.0, 0.0)
    v = rig.target.vertices_mm + np.array([dx, dy, dh])
    R_bc = rot_x(a) @ rot_y(b) @ rig.R_bc
    t_c = -R_bc.T @ rig.t_b
    out = np.empty((n, 3, 2))
    for k, yaw in enumerate(params[N_COMMON + N_CAMERA * camera :]):
        p = v @ (R_bc.T @ rot_z(yaw).T).T + t_c
        out[k] = p[:, :2] / p[:, 2:3]
    if camera:
        out[:, :, 1] *= 1.0 + e
        out[:, :, 0] += px / rig.camera.fx
        out[:, :, 1] += py / rig.camera.fy
    return out


def _initial_yaw(det: Detection, rig: Rig) -> float:
    d = det.points_px[0] - det.points_px.mean(axis=0)
    cam = rig.camera
    v_b = rig.R_bc @ np.array([d[0] / cam.fx, d[1] / cam.fy, 0.0])
    return float(np.arctan2(-v_b[1], v_b[0]))


def circle_centre(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (2,) of the circle through (K, 2) points and its standard error (2,).

    Kasa's fit: x^2 + y^2 = 2 a x + 2 b y + c, linear least squares.
    """
    A = np.column_stack([2 * pts, np.ones(len(pts))])
    rhs = (pts**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    res = rhs - A @ sol
    dof = max(len(pts) - 3, 1)
    r = np.sqrt(max(sol[2] + sol[0] ** 2 + sol[1] ** 2, 0.0))
    s2 = (res @ res) / dof / max(4 * r * r, 1e-9)
    cov = s2 * np.linalg.inv(A.T @ A) * 4 * max(r * r, 1e-9)
    return sol[:2], np.sqrt(np.diag(cov)[:2])


def _whitened(dets: list[Detection]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Measured vertices (K, 3, 2) and, per frame, the Cholesky factor of the inverse
    covariance that whitens its residuals."""
    meas = np.stack([d.points_n for d in dets])
    return meas, [np.linalg.cholesky(np.linalg.inv(d.cov_n)).T for d in dets]


def _fit(
    dets: list[Detection],
    rig: Rig,
    yaw0: np.ndarray,
    x0: np.ndarray | None = None,
    camera: bool = False,
):
    """Weighted least squares of [dx, dy, a, b, dh, yaw_1..yaw_K] over the frames'
    vertices (x0: the N_COMMON offsets to start from; ``camera``: the camera check's
    parameters fitted too, after them, from 0)."""
    from scipy.optimize import least_squares  # (0.3 s to import: not at every start)

    n = len(dets)
    meas, Ls = _whitened(dets)

    def fun(p: np.ndarray) -> np.ndarray:
        r = (_model(p, rig, n, camera) - meas).reshape(n, 6)
        return np.concatenate([L @ ri for L, ri in zip(Ls, r, strict=True)])

    common = np.zeros(N_COMMON) if x0 is None else x0
    cam0, cam_scale = (np.zeros(N_CAMERA), [1e-3, 1.0, 1.0]) if camera else ([], [])
    start = np.concatenate([common, cam0, yaw0])
    scale = np.concatenate([[10.0, 10.0, 0.01, 0.01, 10.0], cam_scale, np.full(n, 0.01)])
    return least_squares(
        fun, start, x_scale=scale, method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200
    )


def _yaw_alone(det: Detection, rig: Rig, offsets: np.ndarray, yaw0: float) -> tuple:
    """The yaw of one frame left out of the fit, with the offsets fixed, and its whitened
    residuals."""
    from scipy.optimize import least_squares

    meas, (L,) = _whitened([det])

    def fun(y: np.ndarray) -> np.ndarray:
        return L @ (_model(np.concatenate([offsets, y]), rig, 1) - meas).reshape(6)

    sol = least_squares(fun, [yaw0], x_scale=[0.01], method="trf", xtol=1e-12, ftol=1e-12)
    return float(sol.x[0]), sol.fun


def calibrate_zero_tilt(dets: list[Detection], rig: Rig) -> ZeroTiltResult:
    """Zero-tilt offsets from ok detections of frames taken with the platform level.

    Parameters
    ----------
    dets : list of Detection
        The triangle's detections of frames with the platform level (and at rest),
        at yaws spread over 60 degrees or more.
    rig : Rig
        The triangle rig they were taken with.

    Returns
    -------
    ZeroTiltResult
        The camera's tilt on its mount and the target's offset on the ceiling (deg,
        mm) with their sigmas, the height offset (mm), the vertices' noise scale
        (``sigma_scale``), the frames used and left out; its TOML is the rig's
        ``[zero_tilt]``.

    Frames far outside their sigma (a platform nudged or not at rest, a bad frame) are
    left out one at a time, worst first, while one is beyond the 99.9 % point of its
    chi-square (5 degrees of freedom) after scaling by the frames' median, so that a
    uniformly wider noise leaves every frame in; at most a fifth of the frames, and only
    while the yaws left still spread over 60 degrees. One such frame pulls the common
    offsets and with them the residuals of its neighbours in yaw, so they are judged
    again after each one is left out.

    Raises
    ------
    InputFileError
        Fewer than 3 usable frames, or yaws spread over less than 60 degrees (then the
        target offset cannot be told from the camera tilt).
    """
    n = len(dets)
    yaw0 = _initial_yaws(dets, rig)
    own = rig.detect.sigma_scale**2  # the detections' covariance over the detector's own
    sol, keep = _fit_leaving_out(dets, rig, yaw0, own)
    idx = np.flatnonzero(keep)
    m = len(idx)
    J = sol.jac
    dof = max(5 * m - N_COMMON, 1)
    chi2 = float(sol.fun @ sol.fun)
    cov = np.linalg.pinv(J.T @ J) * max(1.0, chi2 / dof)
    # the sigma check, against the detector's own covariance
    chi2_own = chi2 * own
    ratio = float(np.sqrt(chi2_own / dof))
    # 95 % interval of the ratio: chi2_own / ratio^2 ~ chi-square(dof)
    ratio_95 = ratio * np.sqrt(dof / np.array([chi2_ppf(0.975, dof), chi2_ppf(0.025, dof)]))
    wider = chi2_own > chi2_ppf(SIGMA_CHECK_QUANTILE, dof)
    sig = np.sqrt(np.diag(cov))
    deg = np.array([1.0, 1.0, np.degrees(1.0), np.degrees(1.0)])
    offsets_cov = cov[:4, :4] * np.outer(deg, deg)
    offsets_cov = 0.5 * (offsets_cov + offsets_cov.T)
    sigma_yaw = np.full(n, np.nan)
    sigma_yaw[idx] = np.degrees(sig[N_COMMON:])
    check_x, check_sig, camera_off = _camera_check([dets[i] for i in idx], rig, sol, chi2, dof)
    # every frame's yaw: the fit's, or for a frame left out its own with the offsets fixed
    yaw = np.empty(n)
    yaw[idx] = sol.x[N_COMMON:]
    for i in np.flatnonzero(~keep):
        yaw[i] = _yaw_alone(dets[i], rig, sol.x[:N_COMMON], yaw0[i])[0]
    params = np.concatenate([sol.x[:N_COMMON], yaw])
    r = (_model(params, rig, n) - np.stack([d.points_n for d in dets])) * rig.camera.fx
    per_frame = np.sqrt((r**2).reshape(n, 6).mean(axis=1))
    cents = np.stack([d.points_px.mean(axis=0) for d in dets])[keep]
    cen, cen_sig = circle_centre(cents) if m >= 3 else (cents.mean(axis=0), np.zeros(2))
    return ZeroTiltResult(
        target_offset_mm=sol.x[:2],
        sigma_target_offset_mm=sig[:2],
        camera_tilt_deg=np.degrees(sol.x[2:4]),
        sigma_camera_tilt_deg=np.degrees(sig[2:4]),
        height_offset_mm=float(sol.x[4]),
        sigma_height_offset_mm=float(sig[4]),
        centroid_px=cen,
        sigma_centroid_px=cen_sig,
        yaw_deg=np.degrees((yaw + np.pi) % (2 * np.pi) - np.pi),
        residual_px=per_frame,
        rms_px=float(np.sqrt(np.mean(r[keep] ** 2))),
        converged=bool(sol.success),
        sigma_ratio=ratio,
        sigma_ratio_95=ratio_95,
        offsets_cov=offsets_cov,
        dof=dof,
        sigma_scale=ratio if wider else 1.0,
        outliers=~keep,
        aspect=float(check_x[0]),
        sigma_aspect=float(check_sig[0]),
        principal_point_px=check_x[1:].copy(),
        sigma_principal_point_px=check_sig[1:].copy(),
        camera_off=camera_off,
        sigma_yaw_deg=sigma_yaw,
    )


def _initial_yaws(dets: list[Detection], rig: Rig) -> np.ndarray:
    """Each frame's yaw to start from (rad); refused when too few frames, or their yaws
    too close together, to tell the target offset from the camera tilt."""
    if len(dets) < MIN_FRAMES:
        raise InputFileError(
            f"zero-tilt calibration needs at least {MIN_FRAMES} frames with "
            f"the triangle found; got {len(dets)}"
        )
    yaw0 = np.array([_initial_yaw(d, rig) for d in dets])
    spread = _yaw_spread_deg(yaw0)
    if spread < MIN_YAW_SPREAD_DEG:
        raise InputFileError(
            f"zero-tilt calibration needs frames at yaws spread over at least "
            f"{MIN_YAW_SPREAD_DEG:.0f} deg (turn the level platform between frames); "
            f"these span {spread:.1f} deg"
        )
    return yaw0


def _fit_leaving_out(dets: list[Detection], rig: Rig, yaw0: np.ndarray, own: float):
    """The fit over the frames, the worst left out one at a time while it is beyond
    OUTLIER_QUANTILE of its chi-square (scaled by the frames' median), at most a fifth of
    them and while the rest still spread over MIN_YAW_SPREAD_DEG: (solution, kept)."""
    n = len(dets)
    keep = np.ones(n, dtype=bool)
    limit = chi2_ppf(OUTLIER_QUANTILE, 5)
    while True:
        idx = np.flatnonzero(keep)
        sol = _fit([dets[i] for i in idx], rig, yaw0[idx])
        frame_chi2 = (sol.fun.reshape(len(idx), 6) ** 2).sum(axis=1) * own
        s2 = max(1.0, float(np.median(frame_chi2)) / chi2_ppf(0.5, 5))
        worst = int(np.argmax(frame_chi2))
        rest = np.delete(idx, worst)
        if (
            frame_chi2[worst] / s2 <= limit
            or len(rest) < max(MIN_FRAMES, np.ceil(0.8 * n))
            or _yaw_spread_deg(yaw0[rest]) < MIN_YAW_SPREAD_DEG
        ):
            return sol, keep
        keep[idx[worst]] = False


def _camera_check(dets: list[Detection], rig: Rig, sol, chi2: float, dof: int):
    """The same frames with the camera's aspect and principal point free: their
    estimates (aspect, cx, cy), 1-sigmas, and whether they are off both significantly
    and by more than ASPECT_MIN / PRINCIPAL_POINT_MIN."""
    check = _fit(dets, rig, sol.x[N_COMMON:], sol.x[:N_COMMON], camera=True)
    check_chi2 = float(check.fun @ check.fun)
    check_s2 = max(1.0, check_chi2 / max(dof - N_CAMERA, 1))
    cam = slice(N_COMMON, N_COMMON + N_CAMERA)
    check_x = check.x[cam]
    check_sig = np.sqrt(np.diag(np.linalg.pinv(check.jac.T @ check.jac))[cam] * check_s2)
    significant = (chi2 - check_chi2) / check_s2 > chi2_ppf(CAMERA_CHECK_QUANTILE, N_CAMERA)
    large = abs(check_x[0]) >= ASPECT_MIN or np.max(np.abs(check_x[1:])) >= (
        PRINCIPAL_POINT_MIN * rig.camera.width
    )
    return check_x, check_sig, bool(significant and large)


def yaw_reference(
    res: ZeroTiltResult,
    known_yaw_deg: np.ndarray,
    stop: np.ndarray,
    reference_sigma_deg: float,
) -> ZeroTiltResult:
    """The camera's turn about b3 from frames whose platform yaw the lab knows.

    Level frames cannot tell a camera turned on its mount from where the platform's yaw
    zero is: both add to every frame's yaw (the fit's ``yaw_deg`` is the true yaw plus
    the turn, exactly, for a level platform: R_NC = Rz(yaw) Rz(turn) R_BC). A lab that
    sets the platform at known yaws (a mark on the table, an encoder, a laser on a wall;
    yaws about n3 from n1, toward the triangle's most acute vertex) gives the turn as
    the weighted mean over its stops of (fitted yaw - known yaw). Each stop's frames
    share its reference's error ``reference_sigma_deg``; a stop's variance is that plus
    its mean yaw's (the frames' fit sigma, or their scatter when wider), and the stops'
    scatter against the turn is checked (``yaw_stop_chi2_dof``).

    ``known_yaw_deg`` (K,) per frame, nan where not known; ``stop`` (K,) which stop
    (recording) each frame is of. Frames left out of the fit as outliers are not used.
    """
    use = np.isfinite(known_yaw_deg) & ~res.outliers
    if not use.any():
        return res
    d = (res.yaw_deg[use] - known_yaw_deg[use] + 180.0) % 360.0 - 180.0
    stops = stop[use]
    sy = res.sigma_yaw_deg[use] if len(res.sigma_yaw_deg) else np.zeros(len(d))
    means, var = [], []
    for s_id in np.unique(stops):
        sel = stops == s_id
        ds = d[sel]
        means.append(float(np.mean(ds)))
        # the stop's mean yaw: its frames' own sigma, or their scatter when wider
        fit = float(np.mean(np.square(sy[sel]))) / len(ds)
        scatter = float(np.var(ds, ddof=1) / len(ds)) if len(ds) > 1 else 0.0
        var.append(reference_sigma_deg**2 + max(fit, scatter))
    means_a, var_a = np.array(means), np.array(var)
    w = 1.0 / var_a
    turn = float(np.sum(w * means_a) / np.sum(w))
    sigma = float(np.sqrt(1.0 / np.sum(w)))
    chi2_dof = (
        float(np.sum(w * (means_a - turn) ** 2) / (len(means_a) - 1))
        if len(means_a) > 1
        else float("nan")
    )
    return replace(
        res,
        camera_turn_deg=turn,
        sigma_camera_turn_deg=sigma,
        yaw_stops=len(means_a),
        yaw_stop_chi2_dof=chi2_dof,
    )


def _yaw_spread_deg(yaw: np.ndarray) -> float:
    """How far the yaws spread (deg): 360 less the largest gap between neighbours."""
    a = np.sort(np.mod(yaw, 2 * np.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2 * np.pi]]))
    return float(np.degrees(2 * np.pi - gaps.max()))


def calibration_sections(res: ZeroTiltResult, rig: Rig) -> dict[str, dict[str, object]]:
    """Sections of the calibration file that overrides the rig."""
    cal = res.apply(rig)
    return {
        "mount": {"rotation": np.round(cal.R_bc, 12)},
        "target": {"vertices_mm": np.round(cal.target.vertices_mm, 4)},
        "zero_tilt": {
            "centroid_px": np.round(res.centroid_px, 4),
            "residual_px": round(res.rms_px, 5),
            # how well the offsets were found: carried into every row's sigma
            **(
                {"offsets_cov": [[float(f"{x:.6g}") for x in row] for row in res.offsets_cov]}
                if res.offsets_cov is not None
                else {}
            ),
            **(
                {"turn_sigma_deg": round(res.sigma_camera_turn_deg, 6)}
                if np.isfinite(res.camera_turn_deg)
                else {}
            ),
        },
        "detect": {"sigma_scale": round(res.sigma_scale, 4)},
        "report": {
            "frames": len(res.yaw_deg),
            "target_offset_mm": np.round(res.target_offset_mm, 4),
            "sigma_target_offset_mm": np.round(res.sigma_target_offset_mm, 4),
            "camera_tilt_deg": np.round(res.camera_tilt_deg, 5),
            "sigma_camera_tilt_deg": np.round(res.sigma_camera_tilt_deg, 5),
            "height_offset_mm": round(res.height_offset_mm, 3),
            "sigma_height_offset_mm": round(res.sigma_height_offset_mm, 3),
            "sigma_centroid_px": np.round(res.sigma_centroid_px, 4),
            "sigma_ratio": round(res.sigma_ratio, 4),
            "sigma_ratio_95": np.round(res.sigma_ratio_95, 4),
            "sigma_dof": res.dof,
            **(
                {
                    "camera_turn_deg": round(res.camera_turn_deg, 5),
                    "sigma_camera_turn_deg": round(res.sigma_camera_turn_deg, 5),
                    "yaw_stops": res.yaw_stops,
                }
                if np.isfinite(res.camera_turn_deg)
                else {"yaw_zero": "not calibrated (no stops at known yaws)"}
            ),
        },
    }


@dataclass
class LevelFrames:
    """The ok detections of the level recordings, each frame's name and recording
    (stop) index, and how many frames were skipped."""

    dets: list = field(default_factory=list)
    names: list = field(default_factory=list)
    stop: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    bad: int = 0
    unreadable: int = 0  # of the skipped, those that could not be read at all


def level_detections(frames, sources, rig: Rig, say=None, step=None) -> LevelFrames:
    """Every frame of every recording (``sources``, opened from the paths ``frames``)
    through the still-platform triangle pipeline: the detections `calibrate_zero_tilt`
    takes. Each skipped frame is named with its reason through ``say(text)``; ``step()``
    is called after each frame (a progress bar).

    Raises
    ------
    SourceError
        Not one frame could be read (the sources are unreadable, not a calibration that
        failed).
    """
    from visvec.pipeline import TrianglePipeline

    pipe = TrianglePipeline(rig, "full", still=True)
    out = LevelFrames()
    stops = []
    for k, (path, src) in enumerate(zip(frames, sources, strict=True)):
        pipe.reset()  # another recording: another yaw
        where = f"{path}: " if len(frames) > 1 else ""
        for frame in src:
            if step is not None:
                step()
            row = pipe.process(frame)
            det = pipe.last_detection
            if det is not None and det.status is Status.OK:
                out.dets.append(det)
                out.names.append(where + (frame.name or f"frame {frame.index}"))
                stops.append(k)
                continue
            out.bad += 1
            out.unreadable += row.status == "read_error"
            why = (
                frame.error or pipe.check_frame(frame) or "unreadable"
                if row.status == "read_error"
                else ";".join(row.warnings) or "no detail"
            )
            if say is not None:
                say(f"{where}frame {frame.index}: skipped ({row.status}: {why})")
    out.stop = np.array(stops, int)
    if out.bad and out.unreadable == out.bad and not out.dets:
        raise SourceError(
            f"{', '.join(map(str, frames))}: none of the {out.bad} frames could be read "
            "(the reasons above): expected images or a video of the rig's camera"
        )
    return out
