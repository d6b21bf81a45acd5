"""The triangle sensor on defocused frames: a soft or mis-focused webcam lens.

The clean-scene benchmark uses the default blur (sigma 0.6 px). Here the same scene is
rendered with Gaussian defocus blur sigma 0.6 to 3 px, 100 cold frames per level and
resolution, and "full" is scored on its accuracy, its ok fraction and whether its sigma
still covers the errors (error/sigma RMS, rows beyond 3 and 5 sigma). Then a tracked
recording (a smooth sweep at 30 fps) whose lens refocuses every 100 frames
(REFOCUS_PX), scored per stretch of constant focus.

    python benchmarks/triangle_defocus.py [--frames 100]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from visvec.bench.triangle import Case, evaluate, random_cases, render_cases
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.simulate import random_attitudes

from _common import CONFIGS, run_record, save_json, summarise

BLURS_PX = (0.6, 1.0, 1.5, 2.0, 3.0)
# blur sigma (px) of each 100-frame stretch of the tracked recording
REFOCUS_PX = (0.6, 1.5, 3.0, 0.8)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100)
    args = ap.parse_args()
    results = run_record()
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        res = {}
        for blur in BLURS_PX:
            cases = random_cases(args.frames, replace(Scene(), blur_sigma_px=blur), seed=21)
            s = summarise(evaluate(rig, render_cases(rig, cases), cases, "full"))
            res[f"blur_{blur}"] = s
            print(cfg, blur, s)
        # tracked: one pipeline through the whole recording, focus changing under it
        eul = random_attitudes(100 * len(REFOCUS_PX), 5.0, np.random.default_rng(22), "sweep")
        cases = [
            Case(e, replace(Scene(), blur_sigma_px=REFOCUS_PX[k // 100]), 2200 + k)
            for k, e in enumerate(eul)
        ]
        out = evaluate(rig, render_cases(rig, cases), cases, "full", track=True)
        for j, blur in enumerate(REFOCUS_PX):
            s = summarise(out.part(100 * j, 100 * (j + 1)))
            res[f"tracked_stretch_{j}_blur_{blur}"] = s
            print(cfg, "tracked", j, blur, s)
        results[cfg] = res
    print(save_json("triangle_defocus", results))


if __name__ == "__main__":
    main()
