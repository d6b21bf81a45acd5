"""A lab that is not quite what its rig file says: the ceiling measured wrong, the
triangle printed at 99.5 %, a webcam's tone curve. Each frame's fit with the target's
height held as the rig gives it (`[target] height_sigma_mm = 0`, the model before the
eleventh session) and estimated under its prior (the default, 20 mm); then after
`calibrate zero-tilt` on 12 level frames of the same lab.

    python benchmarks/triangle_lab_errors.py [--frames 100]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from visvec.bench.triangle import evaluate, level_calibration, random_cases, render_cases
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.simulate import true_rig

from _common import CONFIGS, run_record, save_json, summarise


def labs(rig):
    """(name, true lab, scene) of each case."""
    printed = rig.target.vertices_mm.copy()
    printed[:, :2] *= 0.995
    small = replace(rig, target=replace(rig.target, vertices_mm=printed))
    return [
        ("as the rig says", rig, Scene()),
        ("ceiling 5 mm higher", true_rig(rig, height_offset_mm=5.0), Scene()),
        ("ceiling 20 mm higher", true_rig(rig, height_offset_mm=20.0), Scene()),
        ("ceiling 25 mm lower", true_rig(rig, height_offset_mm=-25.0), Scene()),
        ("triangle printed at 99.5 %", small, Scene()),
        ("tone curve, gamma 2.2", rig, Scene(tone_gamma=2.2)),
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100)
    args = ap.parse_args()
    results = run_record()
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        fixed = replace(rig, target=replace(rig.target, height_sigma_mm=0.0))
        res = {}
        for name, world, scene in labs(rig):
            cases = random_cases(args.frames, scene, seed=41)
            imgs = render_cases(world, cases)
            cal, n_found = level_calibration(rig, world, 12, scene)
            calibrated = cal.apply(rig)
            row = {
                "height fixed": summarise(evaluate(fixed, imgs, cases, "full")),
                "height estimated": summarise(evaluate(rig, imgs, cases, "full")),
                "after calibrate zero-tilt": summarise(evaluate(calibrated, imgs, cases, "full")),
                "calibration": {
                    "frames": n_found,
                    "height_offset_mm": round(cal.height_offset_mm, 3),
                    "sigma_height_offset_mm": round(cal.sigma_height_offset_mm, 3),
                    "target_offset_mm": cal.target_offset_mm.round(3).tolist(),
                    "camera_tilt_deg": cal.camera_tilt_deg.round(4).tolist(),
                    "sigma_ratio": round(cal.sigma_ratio, 3),
                    "sigma_scale": round(cal.sigma_scale, 3),
                },
            }
            res[name] = row
            for k, v in row.items():
                print(cfg, name, k, v, flush=True)
        results[cfg] = res
    print(save_json("triangle_lab_errors", results))


if __name__ == "__main__":
    main()
