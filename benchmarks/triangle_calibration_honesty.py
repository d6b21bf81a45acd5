"""Is `calibrate zero-tilt`'s own sigma honest? Its error enters every row's sigma of a
calibrated rig (Rig.ZeroTilt), and every row of a run carries the same error, so a
single calibration cannot tell: here it is drawn many times, each on 12 level frames at
yaws evenly spread from a random start, with fresh noise, and its offsets (the target's
two, the camera's two tilts, the target's height) are scored against the truth (the
rig's own values: the lab is the rig) as error / sigma over the draws: an RMS near 1 and
a mean near 0 are honest. On the plain render and through visvec.sim.webcam's chain with
its sRGB curve declared, at both resolutions, with the edge lines (the default) and the
pixel fit. Seeds of its own (from 7000), used by no test.

    python benchmarks/triangle_calibration_honesty.py [--draws 40]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from visvec.bench.triangle import level_calibration, with_refine
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.webcam import WebcamChain

from _common import CONFIGS, run_record, save_json

NAMES = ("target x", "target y", "camera tilt 1", "camera tilt 2", "height")
CHAINS = {"plain render": Scene(), "through a webcam, sRGB declared": Scene(webcam=WebcamChain())}


def scores(cal) -> np.ndarray:
    """The calibration's five offsets over their sigma (the truth is zero)."""
    est = np.r_[cal.target_offset_mm, cal.camera_tilt_deg, cal.height_offset_mm]
    sig = np.r_[cal.sigma_target_offset_mm, cal.sigma_camera_tilt_deg, cal.sigma_height_offset_mm]
    return est / sig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=40)
    args = ap.parse_args()
    results = run_record()
    rng = np.random.default_rng(7000)
    for cfg in ("triangle-320.toml", "triangle.toml"):
        res = {}
        for name, scene in CHAINS.items():
            tone = "srgb" if scene.webcam is not None else "linear"
            for refine in ("lines", "pixels"):
                rig = with_refine(replace(load_rig(CONFIGS / cfg), tone_curve=tone), refine)
                z, found = [], []
                for _ in range(args.draws):
                    yaw0 = float(rng.uniform(0.0, 2.0 * np.pi / 12))
                    seed = int(rng.integers(7000, 2**31))
                    cal, n = level_calibration(rig, rig, 12, scene, seed=seed, yaw0=yaw0)
                    z.append(scores(cal))
                    found.append(n)
                z = np.array(z)
                rms = np.sqrt((z**2).mean(0))
                row = {
                    "draws": args.draws,
                    "frames_found_min": int(min(found)),
                    "z_rms": dict(zip(NAMES, rms.round(2).tolist(), strict=True)),
                    "z_mean": dict(zip(NAMES, z.mean(0).round(2).tolist(), strict=True)),
                    "beyond_3": int((np.abs(z) > 3).sum()),
                    "max_abs_z": round(float(np.abs(z).max()), 2),
                }
                res[f"{name} / {refine}"] = row
                print(cfg, name, refine, row, flush=True)
        results[cfg] = res
    print(save_json("triangle_calibration_honesty", results))


if __name__ == "__main__":
    main()
