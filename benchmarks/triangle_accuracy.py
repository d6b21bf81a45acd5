"""Accuracy of the triangle sensor on clean simulated webcam frames (issue: triangle).

Paper-like scene: target 2 m above the camera, noise sigma 2 grey levels, contrast 28,
yaw anywhere, tilts within +-5 deg, board edges and ceiling in view, a lighting gradient.
Compares "full" (edge-line vertices), "full" with cornerSubPix vertices, and "paper".

    python benchmarks/triangle_accuracy.py [--frames 300]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from visvec.bench.triangle import evaluate, random_cases, render_cases, with_refine
from visvec.rig import load_rig
from visvec.sim.scene import Scene

from _common import CONFIGS, OUT, pyplot, run_record, save_json


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    results = run_record()
    plt = pyplot()
    fig, axes = plt.subplots(2, 4, figsize=(16, 7))
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
            e = np.array(out.err_deg)
            if label == "full":
                z = e / np.array(out.sigma_deg)
                for k in range(3):
                    axes[row, k].hist(e[:, k], bins=40, color="C0")
                    axes[row, 3].hist(
                        z[:, k],
                        bins=np.linspace(-4, 4, 33),
                        histtype="step",
                        density=True,
                        label=("yaw", "pitch", "roll")[k],
                    )
                x = np.linspace(-4, 4, 200)
                axes[row, 3].plot(
                    x, np.exp(-x * x / 2) / np.sqrt(2 * np.pi), "k--", label="N(0, 1)"
                )
                axes[row, 3].set_title(f"{name}: full, error / sigma")
                axes[row, 3].legend(fontsize=8)
                rms_full = out.rms()
            if label == "paper":
                rms_paper = out.rms()
        for k in range(3):
            axes[row, k].set_title(
                f"{name}: {('yaw', 'pitch', 'roll')[k]} error, full (deg)\n"
                f"RMS {rms_full[k]:.4f} (paper: {rms_paper[k]:.4f})",
                fontsize=9,
            )
        results[name] = res
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / "triangle_accuracy.png", dpi=90)
    print(save_json("triangle_accuracy", results))


if __name__ == "__main__":
    main()
