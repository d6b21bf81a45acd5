"""Batch self-calibration of a marker rig from frames at unknown attitudes (STASIS
Sec. 2.5, Eqs. 18-24).

Unknowns: the intrinsics (fx, fy, cx, cy, k1, k2, k3; p1, p2 kept as the rig says, as
in the paper's radial-only model), the camera's position t_N (the centre of rotation
seen from the camera), the first pattern's position in B (the paper's body offset), each
further pattern's pose in B, and every frame's attitude. The first pattern's rotation
and the camera's rotation R_NC fix the orientation gauges of B and N.

Beyond the paper: when the rig gives a marker placement error sigma_m
(``[target] placement_sigma_mm``), every marker's own offset from its file position is
an unknown too, with a Gaussian prior N(0, sigma_m^2) per axis entered as pseudo-
residuals (sigma_px / sigma_m) * offset (maximum a posteriori). A placement error is the
same in every frame, so the paper's model, which has no place for it, pushes it into the
intrinsics and the camera distance and reports a covariance that is far too small;
with the offsets estimated, the covariance is the posterior one, which for a Gaussian
prior matches the spread of the estimates over layouts drawn from it. The prior also
fixes the gauges the offsets open (a common shift, turn or scaling of the layout).

The problem is solved by Gauss-Newton (Eq. 20) with Levenberg-Marquardt damping. The
Jacobian is sparse (each frame's residuals depend on the shared parameters and on its
own attitude only, the paper's Appendix B structure): it is taken by central
differences with one residual evaluation pair per shared parameter and one pair per
attitude axis for all frames at once, a few dozen evaluations however many frames.
The covariance is sigma^2 (J^T J)^-1 with sigma^2 from the final residual
(Eqs. 22-24).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from visvec.camera import CameraModel
from visvec.errors import InputFileError
from visvec.rig import Mount, Pattern, Rig

if TYPE_CHECKING:  # (scipy.sparse is imported where it is used: not at every start)
    from scipy.sparse import csr_matrix


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """(K, 3) rotation vectors -> (K, 3, 3) matrices (Rodrigues, vectorised)."""
    t = np.linalg.norm(w, axis=1)
    small = t < 1e-12
    ts = np.where(small, 1.0, t)
    a = np.where(small, 1.0, np.sin(ts) / ts)
    b = np.where(small, 0.5, (1 - np.cos(ts)) / ts**2)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * K @ K


@dataclass(frozen=True)
class Observations:
    """Identified marker centroids of many frames: frame index (L,), marker id (L,),
    pixel position (L, 2), and the initial attitude of each frame (F, 3, 3)."""

    frame: np.ndarray
    marker: np.ndarray
    uv: np.ndarray
    R0: np.ndarray


@dataclass(frozen=True)
class SystemCalibration:
    """Result: the calibrated rig, parameter values and 1-sigma, residual statistics."""

    rig: Rig
    names: list[str]
    values: np.ndarray
    sigmas: np.ndarray
    residual_std_px: float
    mean_abs_px: float
    rms_px: float
    iterations: int
    converged: bool
    message: str
    attitudes: np.ndarray  # (F, 3, 3)
    attitude_sigma_deg: np.ndarray  # (F, 3) about body axes
    marker_offsets_mm: np.ndarray  # (M, 3) in B from the file positions; zeros if not estimated
    marker_offset_sigma_mm: np.ndarray  # (M, 3); zeros if not estimated
    prior_sigma_px: float  # centroid noise that weighed the offsets' prior
    # (3,) 1-sigma of the error every attitude shares (B's orientation as calibrated, about
    # b1, b2, b3): a constant bias of the attitudes, not in the rows' sigma columns
    b_orientation_sigma_arcsec: np.ndarray

    def report(self) -> list[str]:
        """Lines like the paper's Table 2."""
        out = [
            f"residual std {self.residual_std_px:.4f} px, mean absolute error "
            f"{self.mean_abs_px:.4f} px, rms {self.rms_px:.4f} px, "
            f"{self.iterations} iterations"
        ]
        b1, b2, b3 = self.b_orientation_sigma_arcsec
        out.append(
            f"  B's orientation, shared by every attitude (a constant bias, not in the "
            f"rows' sigma): 1-sigma {b1:.1f}, {b2:.1f}, {b3:.1f} arcsec about b1, b2, b3"
        )
        for n, v, s in zip(self.names, self.values, self.sigmas, strict=True):
            out.append(f"  {n:<28} {v:>14.6f} +- {s:.6f}")
        if np.any(self.marker_offset_sigma_mm > 0):
            off = self.marker_offsets_mm
            out.append(
                f"  marker offsets from the rig file (mm, in B): rms "
                f"{np.sqrt(np.mean(off**2)):.4f}, largest {np.abs(off).max():.4f} "
                f"(prior weighed with {self.prior_sigma_px:.4f} px of centroid noise)"
            )
            for i, (d, s) in enumerate(zip(off, self.marker_offset_sigma_mm, strict=True)):
                xyz = "  ".join(f"{a:+.4f} +- {b:.4f}" for a, b in zip(d, s, strict=True))
                out.append(f"    marker {i:<3} {xyz}")
        return out


class _Model:
    """Parameter vector x = [shared (n_global) | marker offsets (n_off) | attitudes (3F)];
    residuals = [pixel errors u, v of every observation (2L) | offset prior (n_off)]."""

    def __init__(self, rig: Rig, obs: Observations, sigma_px: float, sigma_m: float):
        self.rig = rig
        self.obs = obs
        self.pats = rig.target.patterns
        self.pat_of = np.concatenate(
            [np.full(len(p.points_mm), j) for j, p in enumerate(self.pats)]
        )
        self.local = np.vstack([p.points_mm for p in self.pats])
        self.F = len(obs.R0)
        self.L = len(obs.frame)
        self.n_off = 3 * len(self.local) if sigma_m > 0 else 0
        self.sigma_m = sigma_m
        self.set_sigma_px(sigma_px)
        cam = rig.camera
        self.p12 = cam.dist[2:4]
        names = [
            "fx",
            "fy",
            "cx",
            "cy",
            "k1",
            "k2",
            "k3",
            "t_N x mm",
            "t_N y mm",
            "t_N z mm",
            "pattern0 x mm",
            "pattern0 y mm",
            "pattern0 z mm",
        ]
        # STASIS Sec. 3.3: when the patterns are coplanar, a further pattern only turns
        # about b3 and moves in the plane (3 unknowns instead of 6); a single LED has no
        # orientation at all
        z = [p.position_mm[2] for p in self.pats]
        flat = all(
            np.allclose(p.rotation[2], [0, 0, 1]) and np.allclose(p.points_mm[:, 2], 0)
            for p in self.pats
        )
        self.coplanar = flat and np.ptp(z) < 1e-6
        self.free: list[tuple[str, ...]] = []
        for j, p in enumerate(self.pats[1:], start=1):
            rots = () if len(p.points_mm) == 1 else ("z",) if self.coplanar else ("x", "y", "z")
            moves = ("x", "y") if self.coplanar else ("x", "y", "z")
            self.free.append(tuple(f"rot{a}" for a in rots) + moves)
            names += [
                f"pattern{j} {n} deg" if n.startswith("rot") else f"pattern{j} {n} mm"
                for n in self.free[-1]
            ]
        self.names = names
        self.n_global = len(names)
        self.att0 = self.n_global + self.n_off  # first attitude parameter
        # offsets join the fit below this pixel rms: five times what the placement
        # errors and the centroid noise together leave (see _levenberg_marquardt)
        depth = float(np.linalg.norm(rig.t_n))  # camera to centre of rotation
        self.release_rms_px = 5.0 * float(np.hypot(sigma_px, sigma_m * cam.fx / depth))

    def set_sigma_px(self, sigma_px: float) -> None:
        """The centroid noise that weighs the offset prior (w = sigma_px / sigma_m)."""
        self.sigma_px = sigma_px
        self.w_prior = sigma_px / self.sigma_m if self.n_off else 0.0

    def rms_px(self, r: np.ndarray) -> float:
        """RMS of the pixel residuals (the prior's rows left out)."""
        pix = r[: 2 * self.L]
        return float(np.sqrt(pix @ pix / len(pix)))

    def x0(self) -> np.ndarray:
        cam, rig = self.rig.camera, self.rig
        g = [
            cam.fx,
            cam.fy,
            cam.cx,
            cam.cy,
            cam.dist[0],
            cam.dist[1],
            cam.dist[4],
            *rig.t_n,
            *self.pats[0].position_mm,
        ]
        for p, free in zip(self.pats[1:], self.free, strict=True):
            g += [0.0 if n.startswith("rot") else p.position_mm["xyz".index(n)] for n in free]
        return np.concatenate([np.array(g, float), np.zeros(self.n_off + 3 * self.F)])

    def unpack(self, x: np.ndarray):
        fx, fy, cx, cy, k1, k2, k3 = x[:7]
        t_n = x[7:10]
        pos = [x[10:13]]
        rot = [self.pats[0].rotation]
        k = 13
        for p, free in zip(self.pats[1:], self.free, strict=True):
            w = np.zeros(3)
            t = p.position_mm.copy()
            for n in free:
                if n.startswith("rot"):
                    w["xyz".index(n[3])] = np.radians(x[k])
                else:
                    t["xyz".index(n)] = x[k]
                k += 1
            if self.coplanar:
                t[2] = pos[0][2]  # the boards share the first one's plane
            rot.append(_rotvec_to_matrix(w[None])[0] @ p.rotation)
            pos.append(t)
        att = self.obs.R0 @ _rotvec_to_matrix(x[self.att0 :].reshape(-1, 3))
        return (fx, fy, cx, cy, k1, k2, k3), t_n, pos, rot, att

    def offsets(self, x: np.ndarray) -> np.ndarray:
        """(M, 3) every marker's offset from its file position, in B (mm)."""
        if not self.n_off:
            return np.zeros_like(self.local)
        return x[self.n_global : self.att0].reshape(-1, 3)

    def points_b(self, pos, rot, offsets) -> np.ndarray:
        return (
            np.vstack(
                [self.local[self.pat_of == j] @ rot[j].T + pos[j] for j in range(len(self.pats))]
            )
            + offsets
        )

    def residuals(self, x: np.ndarray) -> np.ndarray:
        (fx, fy, cx, cy, k1, k2, k3), t_n, pos, rot, att = self.unpack(x)
        M = self.points_b(pos, rot, self.offsets(x))[self.obs.marker]
        Rk = att[self.obs.frame]
        p_n = np.einsum("lij,lj->li", Rk, M)
        p_c = (p_n - t_n) @ self.rig.R_nc
        xn = p_c[:, 0] / p_c[:, 2]
        yn = p_c[:, 1] / p_c[:, 2]
        r2 = xn * xn + yn * yn
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        p1, p2 = self.p12
        xd = xn * rad + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * rad + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        u = fx * xd + cx
        v = fy * yd + cy
        pix = np.column_stack([u - self.obs.uv[:, 0], v - self.obs.uv[:, 1]]).ravel()
        if not self.n_off:
            return pix
        return np.concatenate([pix, self.w_prior * x[self.n_global : self.att0]])


def initial_attitudes(
    rig: Rig, frame: np.ndarray, marker: np.ndarray, uv: np.ndarray
) -> np.ndarray:
    """(F, 3, 3) starting attitudes: a 6-DoF PnP (SQPnP) per frame with the rig's
    nominal camera, as the paper starts from P3P; it needs no centre of rotation, so it
    is not thrown off by an error in the camera's distance or the body offset."""
    import cv2

    F = int(frame.max()) + 1
    out = np.repeat(np.eye(3)[None], F, axis=0)
    X = rig.target.points_b
    for f in range(F):
        sel = frame == f
        if sel.sum() < 4:
            continue
        ok, rvec, _ = cv2.solvePnP(
            X[marker[sel]],
            uv[sel].astype(np.float64),
            rig.camera.K,
            rig.camera.dist,
            flags=cv2.SOLVEPNP_SQPNP,
        )
        if ok:
            out[f] = rig.R_nc @ cv2.Rodrigues(rvec)[0]
    return out


# finite-difference steps: px for intrinsics, 1e-4 for distortion, mm, degrees, rad
_STEPS = {"intr": 1e-3, "dist": 1e-6, "mm": 1e-4, "deg": 1e-5, "att": 1e-7}


def _steps(model: _Model) -> np.ndarray:
    h = [_STEPS["intr"]] * 4 + [_STEPS["dist"]] * 3 + [_STEPS["mm"]] * 6
    for free in model.free:
        h += [_STEPS["deg"] if n.startswith("rot") else _STEPS["mm"] for n in free]
    return np.array(h + [_STEPS["mm"]] * model.n_off + [_STEPS["att"]] * (3 * model.F))


def _jacobian(model: _Model, x: np.ndarray) -> csr_matrix:
    """Sparse Jacobian by central differences using its structure (Appendix B): one
    column pair per shared parameter, and one pair for the a-th parameter of every
    frame's attitude at once (frames do not share residuals); likewise one pair for the
    a-th offset of every marker at once (an observation sees one marker only). The
    offset prior's rows are the constant diagonal w_prior."""
    h = _steps(model)
    ng, L = model.n_global, model.L
    cols, data, rows = [], [], []
    for k in range(ng):
        d = np.zeros_like(x)
        d[k] = h[k]
        col = (model.residuals(x + d) - model.residuals(x - d)) / (2 * h[k])
        nz = np.nonzero(col)[0]
        rows.append(nz)
        cols.append(np.full(len(nz), k))
        data.append(col[nz])
    blocks = [(model.att0, len(x), model.obs.frame)]
    if model.n_off:
        blocks.append((ng, model.att0, model.obs.marker))
        rows.append(2 * L + np.arange(model.n_off))
        cols.append(ng + np.arange(model.n_off))
        data.append(np.full(model.n_off, model.w_prior))
    for start, stop, owner in blocks:
        owner2 = np.repeat(owner, 2)
        for a in range(3):
            d = np.zeros_like(x)
            d[start + a : stop : 3] = h[start + a]
            col = (model.residuals(x + d) - model.residuals(x - d))[: 2 * L] / (2 * h[start + a])
            rows.append(np.arange(2 * L))
            cols.append(start + 3 * owner2 + a)
            data.append(col)
    n_rows = 2 * L + model.n_off
    from scipy.sparse import csr_matrix

    return csr_matrix(
        (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, len(x))
    )


# converged when the minimum of the Gauss-Newton model is closer than this fraction of
# the parameters' own 1-sigma (in the metric of their covariance)
CONVERGED_SIGMA_FRACTION = 0.01


def _normal_equations(J: csr_matrix, r: np.ndarray, hold: slice | None):
    """A = J^T J, g = J^T r and the damping diagonal D; the parameters in ``hold`` are
    kept where they are (their rows and columns replaced by the identity's, g zero)."""
    A = (J.T @ J).toarray()
    g = J.T @ r
    if hold is not None:
        A[hold, :] = 0.0
        A[:, hold] = 0.0
        n = hold.stop - hold.start
        A[hold, hold] = np.eye(n)
        g[hold] = 0.0
    return A, g, np.diag(np.diag(A)) + 1e-12 * np.eye(len(g))


def _levenberg_marquardt(model: _Model, x: np.ndarray, max_iterations: int):
    """The paper's Gauss-Newton iteration (Eq. 20) with Levenberg-Marquardt damping for
    a safe start far from the solution. Returns x, r, J, iterations (steps taken),
    converged, message.

    Convergence is judged by the Newton decrement g^T A^-1 g (A = J^T J, g = J^T r):
    the fall in the sum of squares that the undamped step would bring, which is the
    squared distance to the model's minimum in the metric of the covariance, in units
    of sigma^2 = cost / dof. Converged when it is under CONVERGED_SIGMA_FRACTION^2, that
    is when no parameter can move by more than 1 % of its 1-sigma. Unlike a test on the
    last step, damping cannot fake it, and noise in the cost near the minimum cannot
    hide it.

    The marker offsets are held at zero while the pixel residuals are far larger than
    placement errors could explain (model.release_rms_px): a few hundredths of a mm
    cannot account for a start that is pixels off, and left free they only slow the
    first steps. They join once the fit is close, or once it has converged without them."""
    r = model.residuals(x)
    cost = float(r @ r)
    dof = max(len(r) - len(x), 1)
    lam = 1e-3
    J = _jacobian(model, x)
    off = slice(model.n_global, model.att0)
    released = not model.n_off or model.rms_px(r) <= model.release_rms_px
    for it in range(max_iterations + 1):
        A, g, D = _normal_equations(J, r, None if released else off)
        try:
            decrement = float(g @ np.linalg.solve(A + 1e-12 * D, g))
        except np.linalg.LinAlgError:
            decrement = np.inf
        if decrement < CONVERGED_SIGMA_FRACTION**2 * cost / dof:
            if released:
                return x, r, J, it, True, "converged"
            released = True  # converged without the offsets: now with them
            lam = 1e-3
            A, g, D = _normal_equations(J, r, None)
        if it == max_iterations:
            break
        while True:
            try:
                step = -np.linalg.solve(A + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step
            r_new = model.residuals(x_new)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                break
            lam *= 10
            if lam > 1e12:
                return x, r, J, it, False, "no step lowers the residual"
        x, r, cost = x_new, r_new, c_new
        lam = max(lam / 10, 1e-12)
        released = released or model.rms_px(r) <= model.release_rms_px
        J = _jacobian(model, x)
    return x, r, J, max_iterations, False, f"not converged in {max_iterations} iterations"


def calibrate_system(
    rig: Rig,
    obs: Observations,
    max_iterations: int = 30,
    sigma_px: float | None = None,
    placement_sigma_mm: float | None = None,
) -> SystemCalibration:
    """Self-calibrate the rig from identified marker centroids of many frames.

    Parameters
    ----------
    rig : Rig
        A markers rig: its layout, camera and mount are the starting point.
    obs : Observations
        The identified marker centroids (px) of many frames at several attitudes.
    max_iterations : int
        Gauss-Newton iterations at most.
    sigma_px, placement_sigma_mm : float, optional
        The centroid noise (px) and the markers' placement error (mm) that weigh the
        offset prior against the pixels (default: the rig's ``[detect]
        centroid_sigma_px`` and ``[target] placement_sigma_mm``); only their ratio
        matters, the covariance is scaled by the final residual.

    Returns
    -------
    SystemCalibration
        The camera's mounting (deg), the markers' offsets (mm) with their sigmas, the
        residual (px); its TOML overrides the rig's.

    Raises
    ------
    InputFileError
        Too few frames or observations for the unknowns.
    """
    if sigma_px is None:
        sigma_px = rig.detect.centroid_sigma_px
    if placement_sigma_mm is None:
        placement_sigma_mm = rig.target.placement_sigma_mm
    model = _Model(rig, obs, sigma_px, placement_sigma_mm)
    # the offsets come with as many prior rows as unknowns: they add no degree of freedom
    n_par = model.n_global + 3 * model.F
    if model.F < 10 or 2 * model.L <= n_par:
        raise InputFileError(
            f"system calibration needs at least 10 frames and more measurements than "
            f"unknowns: {model.F} frames, {2 * model.L} coordinates, {n_par} unknowns"
        )
    x, r, J, it, converged, message = _solve(model, n_par, max_iterations)
    dof = max(2 * model.L - n_par, 1)
    s2 = float(r @ r) / dof  # Eq. (24), the prior's rows included
    JtJ = (J.T @ J).toarray()
    cov = np.linalg.pinv(JtJ) * s2  # Eqs. (22)-(23)
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    cal, att = _calibrated_rig(rig, model, x)
    res = r[: 2 * model.L].reshape(-1, 2)
    att_sig = np.degrees(sig[model.att0 :].reshape(-1, 3))
    off_sig = (
        sig[model.n_global : model.att0].reshape(-1, 3)
        if model.n_off
        else np.zeros_like(model.local)
    )
    return SystemCalibration(
        rig=cal,
        names=model.names,
        values=x[: model.n_global],
        sigmas=sig[: model.n_global],
        residual_std_px=float(np.sqrt(s2)),
        mean_abs_px=float(np.mean(np.abs(res))),
        rms_px=float(np.sqrt(np.mean(res**2))),
        iterations=it,
        converged=bool(converged),
        message=message,
        attitudes=att,
        attitude_sigma_deg=att_sig,
        marker_offsets_mm=model.offsets(x).copy(),
        marker_offset_sigma_mm=off_sig,
        prior_sigma_px=model.sigma_px,
        b_orientation_sigma_arcsec=_common_attitude_sigma_arcsec(cov, model),
    )


def _solve(model: _Model, n_par: int, max_iterations: int):
    """Levenberg-Marquardt on the model; the prior weighs offsets against pixels
    through the centroid noise: if the rig's value is off, it is taken from the
    residuals and the solve repeated (variance components; the offsets use up about one
    measurement each). (x, r, J, iterations, converged, message)."""
    x, r, J, it, converged, message = _levenberg_marquardt(model, model.x0(), max_iterations)
    for _ in range(3):
        if not (converged and model.n_off):
            break
        pix = r[: 2 * model.L]
        s_px = float(np.sqrt(pix @ pix / max(2 * model.L - n_par - model.n_off, 1)))
        if abs(s_px / model.sigma_px - 1.0) < 0.05:
            break
        model.set_sigma_px(s_px)
        x, r, J, it2, converged, message = _levenberg_marquardt(model, x, max_iterations - it)
        it += it2
    return x, r, J, it, converged, message


def _calibrated_rig(rig: Rig, model: _Model, x: np.ndarray) -> tuple[Rig, np.ndarray]:
    """The rig with the calibrated camera, mount and marker positions (each back in its
    board's frame), and the frames' attitudes."""
    (fx, fy, cx, cy, k1, k2, k3), t_n, pos, rot, att = model.unpack(x)
    dist = np.array([k1, k2, rig.camera.dist[2], rig.camera.dist[3], k3])
    cam = CameraModel(rig.camera.width, rig.camera.height, fx, fy, cx, cy, dist)
    X = model.points_b(pos, rot, model.offsets(x))
    pats = tuple(
        Pattern(pos[j], rot[j], (X[model.pat_of == j] - pos[j]) @ rot[j])
        for j in range(len(model.pats))
    )
    cal = replace(
        rig,
        camera=cam,
        mount=Mount("lab", t_n, rig.R_nc),
        target=replace(rig.target, patterns=pats),
    )
    return cal, att


def _common_attitude_sigma_arcsec(cov: np.ndarray, model: _Model) -> np.ndarray:
    """The part of the attitude errors every frame shares (arcsec, body axes): the mean
    covariance between two different frames' attitude errors. B's orientation is fixed
    only through the calibrated geometry (and, with placement errors, the offsets'
    prior), so its error is common to all attitudes, those measured later included."""
    C = cov[model.att0 :, model.att0 :].reshape(model.F, 3, model.F, 3)
    common = (C.sum(axis=(0, 2)) - np.einsum("fifj->ij", C)) / (model.F * (model.F - 1))
    return np.degrees(np.sqrt(np.clip(np.diag(common), 0.0, None))) * 3600.0


def calibration_sections(cal: SystemCalibration) -> dict[str, dict[str, object]]:
    """Sections of the calibration file (camera, mount, the centroid noise, target
    patterns, the report)."""
    rig = cal.rig
    cam = rig.camera
    return {
        "camera": {
            "fx": round(cam.fx, 6),
            "fy": round(cam.fy, 6),
            "cx": round(cam.cx, 6),
            "cy": round(cam.cy, 6),
            "dist": [round(float(v), 9) for v in cam.dist],
        },
        "mount": {"position_mm": np.round(rig.t_n, 5)},
        # the residual per image coordinate, the LEDs' centroid noise as the calibrated
        # model leaves it: the prior of the noise later runs learn (noise.LearnedNoise),
        # so that their first rows' sigma is the lab's rather than the rig file's guess
        "detect": {"centroid_sigma_px": round(min(max(cal.residual_std_px, 1e-4), 10.0), 5)},
        "target": {
            "patterns": [
                {
                    "position_mm": np.round(p.position_mm, 5),
                    "rotation": np.round(p.rotation, 9),
                    "points_mm": np.round(p.points_mm, 5),
                }
                for p in rig.target.patterns
            ]
        },
        "report": {
            "residual_std_px": round(cal.residual_std_px, 5),
            "mean_abs_px": round(cal.mean_abs_px, 5),
            "frames": len(cal.attitudes),
        },
    }
