"""Perturbed labs for marker Monte Carlo studies (STASIS Sec. 3.5, Table 3)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from visvec.calib.system import Observations, calibrate_system, initial_attitudes
from visvec.estimate.markers import solve_markers
from visvec.estimate.pnp import PNP_FLAGS, solve_pnp
from visvec.estimate.rotation import residuals_and_jacobian
from visvec.geometry import lab_camera_offset_c, markers_to_camera
from visvec.rig import Pattern, Rig
from visvec.rotations import euler_rates_from_body, euler_to_matrix, matrix_to_euler
from visvec.sim.simulate import random_attitudes


def perturbed_lab(rig: Rig, rng: np.random.Generator) -> Rig:
    """A lab that differs from the rig file within ranges like STASIS Table 3."""
    cam = rig.camera
    cam2 = replace(
        cam,
        fx=cam.fx + rng.uniform(-50, 50),
        fy=cam.fy + rng.uniform(-50, 50),
        cx=cam.cx + rng.uniform(-50, 50),
        cy=cam.cy + rng.uniform(-50, 50),
        dist=np.array([rng.uniform(-0.15, 0.15), 0.0, 0.0, 0.0, 0.0]),
    )
    # the boards stay coplanar (they are): each moves +-10 mm in the plane and turns
    # +-1 deg about b3 (not the first: it defines B); the plane moves +-10 mm up or down
    dz = rng.uniform(-10, 10)
    pats = tuple(
        Pattern(
            p.position_mm + [*rng.uniform(-10, 10, 2), dz],
            euler_to_matrix(np.radians(rng.uniform(-1, 1)) * (j > 0), 0, 0) @ p.rotation,
            p.points_mm,
        )
        for j, p in enumerate(rig.target.patterns)
    )
    t = rig.t_n + np.array([*rng.uniform(-10, 10, 2), rng.uniform(-50, 50)])
    return replace(
        rig,
        camera=cam2,
        mount=replace(rig.mount, position_mm=t),
        target=replace(rig.target, patterns=pats),
    )


# --------------------------------------------------------------------------- Monte Carlo


ARCSEC_PER_DEG = 3600.0
METHODS = ("full", *PNP_FLAGS)


@dataclass(frozen=True)
class RunSpec:
    """One Monte Carlo run: the rig, the noise levels and the sizes (STASIS Sec. 3.5)."""

    rig: Rig
    sigma_c_px: float
    sigma_m_mm: float
    seed: int
    frames: int = 350
    poses: int = 500
    calibrate: bool = True
    max_tilt_deg: float = 22.0


def crb_arcsec(rig: Rig, R_nb: np.ndarray, sigma_px: float) -> np.ndarray:
    """(3,) 1-sigma Cramer-Rao bound of yaw, pitch, roll (arcsec) from the Fisher
    information of every marker's pixel coordinates with Gaussian noise sigma_px."""
    X = rig.target.points_b
    R_cb = rig.R_nc.T @ R_nb
    _, J = residuals_and_jacobian(R_cb, lab_camera_offset_c(rig), X, np.zeros((len(X), 2)))
    Jp = J * rig.camera.fx
    cov_b = R_cb.T @ np.linalg.inv(Jp.T @ Jp / sigma_px**2) @ R_cb
    Je = euler_rates_from_body(*matrix_to_euler(R_nb))
    return np.degrees(np.sqrt(np.diag(Je @ cov_b @ Je.T))) * ARCSEC_PER_DEG


def run_one(spec: RunSpec) -> dict:
    """Perturb the lab, place the LEDs with error, calibrate virtually (or not), then
    estimate fresh poses with every method. Returns per-method error spreads (arcsec),
    the bound, and the calibration's outcome."""
    rng = np.random.default_rng(spec.seed)
    rig = spec.rig
    true = perturbed_lab(rig, rng)
    n = len(true.target.points_b)
    X_true = true.target.points_b + rng.standard_normal((n, 3)) * spec.sigma_m_mm
    s_c = max(spec.sigma_c_px, 1e-4)

    def observe(R):
        u = true.camera.project(markers_to_camera(true, R, X_true))
        return u + rng.standard_normal(u.shape) * spec.sigma_c_px

    out: dict = {"sigma_c_px": spec.sigma_c_px, "sigma_m_mm": spec.sigma_m_mm, "seed": spec.seed}
    est = true
    if spec.calibrate:
        fr, mk, uv = [], [], []
        for k, e in enumerate(random_attitudes(spec.frames, spec.max_tilt_deg, rng)):
            uv.append(observe(euler_to_matrix(*e)))
            fr += [k] * n
            mk += list(range(n))
        fr, mk, uv = np.array(fr), np.array(mk), np.vstack(uv)
        # the virtual calibration knows the centroid noise and the LEDs' tolerance (it
        # estimates each LED's offset with that prior; the paper's model when it is 0)
        obs = Observations(fr, mk, uv, initial_attitudes(rig, fr, mk, uv))
        cal = calibrate_system(rig, obs, sigma_px=s_c, placement_sigma_mm=spec.sigma_m_mm)
        out.update(
            converged=bool(cal.converged),
            iterations=int(cal.iterations),
            residual_std_px=float(cal.residual_std_px),
        )
        est = cal.rig
    errs = {m: [] for m in METHODS}
    crb = []
    ids = np.arange(n)
    for e in random_attitudes(spec.poses, spec.max_tilt_deg, rng):
        R = euler_to_matrix(*e)
        uv = observe(R)
        crb.append(crb_arcsec(true, R, s_c))
        for m in METHODS:
            if m == "full":
                sol = solve_markers(est.camera.undistort(uv), ids, est, s_c)
            else:
                sol = solve_pnp(uv, ids, est, m, s_c)
            if sol.R_nb is not None and np.all(np.isfinite(sol.R_nb)):
                d = np.degrees(np.array(matrix_to_euler(sol.R_nb)) - e)
                d[0] = (d[0] + 180.0) % 360.0 - 180.0
                errs[m].append(d * ARCSEC_PER_DEG)
    out["std_arcsec"] = {m: np.std(v, axis=0).tolist() for m, v in errs.items() if v}
    out["crb_arcsec"] = np.sqrt(np.mean(np.square(crb), axis=0)).tolist()
    return out


def summarise(runs: list[dict]) -> list[dict]:
    """Per (sigma_c, sigma_m) point: mean 1-sigma per method and axis, the bound, our
    efficiency (ours over the bound) and each baseline's ratio to ours."""
    groups: dict[tuple[float, float], list[dict]] = {}
    for r in runs:
        groups.setdefault((r["sigma_c_px"], r["sigma_m_mm"]), []).append(r)
    out = []
    for (sc, sm), rs in sorted(groups.items()):
        std = {
            m: np.mean([r["std_arcsec"][m] for r in rs if m in r["std_arcsec"]], axis=0)
            for m in METHODS
        }
        crb = np.mean([r["crb_arcsec"] for r in rs], axis=0)
        conv = [r.get("converged", True) for r in rs]
        out.append(
            {
                "sigma_c_px": sc,
                "sigma_m_mm": sm,
                "runs": len(rs),
                "calibration_converged": float(np.mean(conv)),
                "std_arcsec": {m: np.round(v, 2).tolist() for m, v in std.items()},
                "crb_arcsec": np.round(crb, 2).tolist(),
                "efficiency": np.round(std["full"] / crb, 3).tolist(),
                "ratio_to_full": {
                    m: np.round(std[m] / std["full"], 2).tolist() for m in METHODS if m != "full"
                },
            }
        )
    return out
