"""Zero-tilt calibration: a rig whose target hangs 15 mm off the axis and whose camera is
mounted 0.7 deg askew; tilt errors before and after `calibrate zero-tilt`.

    python benchmarks/triangle_zero_tilt.py [--frames 200] [--level 12]
"""

from __future__ import annotations

import argparse

import numpy as np

from visvec.bench.triangle import (
    evaluate,
    level_calibration,
    random_cases,
    render_cases,
)
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.simulate import true_rig

from _common import CONFIGS, run_record, save_json

ASKEW = 0.7 / np.sqrt(2.0)  # 0.7 deg in all, about an axis between b1 and b2


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--level", type=int, default=12)
    args = ap.parse_args()
    results = {
        **run_record(),
        "truth": {"target_offset_mm": [15.0, 0.0], "camera_askew_deg": [ASKEW, ASKEW]},
    }
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        world = true_rig(rig, (15.0, 0.0), (ASKEW, ASKEW))
        cal, n_found = level_calibration(rig, world, args.level)
        cal_rig = cal.apply(rig)
        cases = random_cases(args.frames, Scene(), seed=31)
        imgs = render_cases(world, cases)
        res = {
            "calibration": {
                "target_offset_mm": cal.target_offset_mm.round(3).tolist(),
                "sigma_target_offset_mm": cal.sigma_target_offset_mm.round(3).tolist(),
                "camera_tilt_deg": cal.camera_tilt_deg.round(4).tolist(),
                "sigma_camera_tilt_deg": cal.sigma_camera_tilt_deg.round(4).tolist(),
                "height_offset_mm": round(cal.height_offset_mm, 3),
                "sigma_height_offset_mm": round(cal.sigma_height_offset_mm, 3),
                "rms_px": round(cal.rms_px, 4),
                "frames": n_found,
                "left_out": int(cal.outliers.sum()),
                "sigma_ratio": round(cal.sigma_ratio, 3),
                "sigma_ratio_95": cal.sigma_ratio_95.round(3).tolist(),
                "sigma_scale": round(cal.sigma_scale, 3),
            }
        }
        for label, r in (("uncalibrated", rig), ("calibrated", cal_rig)):
            for method in ("full", "paper"):
                res[f"{label}/{method}"] = evaluate(r, imgs, cases, method).summary()
                print(cfg, label, method, res[f"{label}/{method}"])
        results[cfg] = res
    print(save_json("triangle_zero_tilt", results))


if __name__ == "__main__":
    main()
