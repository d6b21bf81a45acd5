"""Accuracy of the triangle sensor on clean simulated webcam frames (issue: triangle).

Paper-like scene: target 2 m above the camera, noise sigma 2 grey levels, contrast 28,
yaw anywhere, tilts within +-5 deg, board edges and ceiling in view, a lighting gradient.
Compares "full" (edge-line vertices), "full" with cornerSubPix vertices, and "paper".

    python benchmarks/triangle_accuracy.py [--frames 300]
"""

from __future__ import annotations

import argparse
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from visvec.bench.triangle import evaluate, machine, random_cases, render_cases, with_refine
from visvec.rig import load_rig
from visvec.sim.scene import Scene

from _common import CONFIGS, OUT, command, save_json


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    results = {"command": command(), "machine": machine(), "date": time.strftime("%Y-%m-%d")}
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for row, (name, cfg) in enumerate(
        (("320x240", "triangle-320.toml"), ("640x480", "triangle.toml"))
    ):
        rig = load_rig(CONFIGS / cfg)
        cases = random_cases(args.frames, Scene(), seed=11 + row)
        t0 = time.time()
        images = render_cases(rig, cases)
        res = {"render_s": round(time.time() - t0, 1)}
        for label, r, method in (
            ("full", rig, "full"),
            ("full_cornersubpix", with_refine(rig, "corners"), "full"),
            ("paper", rig, "paper"),
        ):
            out = evaluate(r, images, cases, method)
            res[label] = out.summary()
            print(name, label, res[label])
            if label in ("full", "paper"):
                e = np.array(out.err_deg)
                for k, ax in enumerate(axes[row]):
                    ax.hist(e[:, k], bins=40, alpha=0.6, label=label)
        for k, ax in enumerate(axes[row]):
            ax.set_title(f"{name}: {('yaw', 'pitch', 'roll')[k]} error (deg)")
            ax.legend()
        results[name] = res
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / "triangle_accuracy.png", dpi=90)
    print(save_json("triangle_accuracy", results))


if __name__ == "__main__":
    main()
