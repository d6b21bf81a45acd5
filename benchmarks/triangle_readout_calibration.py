"""`visvec calibrate readout` on simulated recordings: is the readout found, and does its
1-sigma cover the error?

Each recording: 60 frames at 30 fps (2 s) of the platform turning in yaw at a set rate
with its tilts nutating slowly (simulate's sweep with --yaw-rate-dps, or a swing out
and back at that peak rate), rendered with a rolling shutter of a set readout
(negative: the last row first; 0: a global shutter) and, in some conditions, a camera
whose principal point is 4 px right of the rig file's, at 640x480 and 320x240, four
recordings per condition, each with its own seed. Reports each estimate, its sigma and
error/sigma, and the grid search's (the camera model taken as exact) beside it; then
the same recording calibrated as for a camera whose principal point is known to 1 px
at 640x480 (0.5 px at 320x240: `--principal-point-sigma`, as `calibrate camera`
gives it).

    python benchmarks/triangle_readout_calibration.py [--seeds 4]
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from visvec.calib.readout import calibrate_readout
from visvec.data import Frame
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene
from visvec.sim.simulate import body_rates, random_attitudes

from _common import CONFIGS, run_record, save_json

FRAMES = 60
FPS = 30.0
# the principal point's 1-sigma of a calibrated camera, px per 640 px of image width
CALIBRATED_PP_PX = 1.0
# (yaw rate deg/s, readout ms, motion, principal point error px)
CONDITIONS = (
    (5.0, 25.0, "sweep", 0.0),
    (10.0, 25.0, "sweep", 0.0),
    (20.0, 25.0, "sweep", 0.0),
    (10.0, 15.0, "sweep", 0.0),
    (10.0, -20.0, "sweep", 0.0),
    (10.0, 0.0, "sweep", 0.0),
    (10.0, 25.0, "swing", 0.0),
    (10.0, 0.0, "sweep", 4.0),
    (10.0, 0.0, "swing", 4.0),
)


def _recording(args) -> list[Frame]:
    cfg, rate, readout_ms, motion, cx_error, seed = args
    rig = load_rig(CONFIGS / cfg)
    # the camera as it is: its principal point cx_error px right of the rig file's
    rig = replace(rig, camera=replace(rig.camera, cx=rig.camera.cx + cx_error))
    span = (FRAMES - 1) / FPS
    rng = np.random.default_rng(seed)
    # a swing's turn argument is its peak rate times the span, as simulate's
    eul = random_attitudes(
        FRAMES, 4.0, rng, motion, np.radians(rate) * span, (0.13 * span, 0.09 * span)
    )
    R = np.array([euler_to_matrix(*e) for e in eul])
    w = body_rates(R, 1.0 / FPS)
    return [
        Frame(k, k / FPS, render_frame(rig, R[k], Scene(), seed * 1000 + k, readout_ms, w[k]))
        for k in range(FRAMES)
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    args = ap.parse_args()
    results = {
        **run_record(),
        "frames": FRAMES,
        "fps": FPS,
    }
    for cfg in ("triangle.toml", "triangle-320.toml"):
        rig = load_rig(CONFIGS / cfg)
        # a seed of its own for every recording (noise and motion independent)
        jobs = [
            (cfg, *cond, 50 + 10 * i + s)
            for i, cond in enumerate(CONDITIONS)
            for s in range(args.seeds)
        ]
        with ProcessPoolExecutor(os.cpu_count() or 1) as ex:
            recordings = list(ex.map(_recording, jobs))
        rows = []
        for (_, rate, readout, motion, cx_error, seed), frames in zip(
            jobs, recordings, strict=True
        ):
            t0 = time.perf_counter()
            res = calibrate_readout(frames, rig)
            row = {
                "yaw_rate_dps": rate,
                "true_readout_ms": readout,
                "motion": motion,
                "principal_point_error_px": cx_error,
                "seed": seed,
                "converged": res.converged,
                "reason": res.reason,
                "readout_ms": round(res.readout_ms, 3),
                "sigma_ms": round(res.sigma_ms, 3),
                "z": round((res.readout_ms - readout) / res.sigma_ms, 2) if res.converged else None,
                # the grid search's, the camera model taken as exact
                "grid_readout_ms": round(res.grid_ms, 3),
                "grid_sigma_ms": round(res.grid_sigma_ms, 3),
                "grid_z": round((res.grid_ms - readout) / res.grid_sigma_ms, 2)
                if res.converged
                else None,
                "rate_dps": round(res.rate_dps, 2),
                "chi2_per_dof": round(res.chi2_per_dof, 3),
                "chi2_per_dof_uncorrected": round(res.chi2_per_dof_global, 3),
                "seconds": round(time.perf_counter() - t0, 1),
            }
            cal = calibrate_readout(frames, rig, CALIBRATED_PP_PX * rig.camera.width / 640)
            row["calibrated_camera"] = {
                "converged": cal.converged,
                "readout_ms": round(cal.readout_ms, 3),
                "sigma_ms": round(cal.sigma_ms, 3),
                "z": round((cal.readout_ms - readout) / cal.sigma_ms, 2) if cal.converged else None,
            }
            rows.append(row)
            print(cfg, row)
        z = np.array([r["z"] for r in rows if r["z"] is not None])
        results[cfg] = {
            "runs": rows,
            "converged": int(sum(r["converged"] for r in rows)),
            "z_rms": round(float(np.sqrt(np.mean(z**2))), 2) if len(z) else None,
            "max_abs_z": round(float(np.abs(z).max()), 2) if len(z) else None,
        }
    print(save_json("triangle_readout_calibration", results))


if __name__ == "__main__":
    main()
