"""The triangle sensor on defocused frames: a soft or mis-focused webcam lens.

The clean-scene benchmark uses the default blur (sigma 0.6 px). Here the same scene is
rendered with Gaussian defocus blur sigma 0.6 to 3 px, 100 cold frames per level and
resolution, and "full" is scored on its accuracy, its ok fraction and whether its sigma
still covers the errors (error/sigma RMS, rows beyond 3 and 5 sigma).

    python benchmarks/triangle_defocus.py [--frames 100]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from visvec.bench.triangle import evaluate, machine, random_cases, render_cases
from visvec.rig import load_rig
from visvec.sim.scene import Scene

from _common import CONFIGS, command, save_json

BLURS_PX = (0.6, 1.0, 1.5, 2.0, 3.0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100)
    args = ap.parse_args()
    results = {"command": command(), "machine": machine(), "date": time.strftime("%Y-%m-%d")}
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        res = {}
        for blur in BLURS_PX:
            cases = random_cases(args.frames, replace(Scene(), blur_sigma_px=blur), seed=21)
            out = evaluate(rig, render_cases(rig, cases), cases, "full")
            s = out.summary()
            if out.n_ok:
                z = np.array(out.err_deg) / np.array(out.sigma_deg)
                rms = np.sqrt(np.mean(z**2, axis=0)).round(2).tolist()
                s["z_rms"] = dict(zip(("yaw", "pitch", "roll"), rms, strict=True))
            res[f"blur_{blur}"] = s
            print(cfg, blur, s)
        results[cfg] = res
    print(save_json("triangle_defocus", results))


if __name__ == "__main__":
    main()
