"""The triangle through a webcam's image chain (visvec.sim.webcam: Bayer mosaic, sensor
noise, vignetting, a breathing gain, chromatic aberration, hot pixels, sRGB, Motion-JPEG
at 85), beside the plain render: the edge lines (default) and the pixel fit (refine =
"pixels"), cold frames at random attitudes (yaw uniform, tilts within 5 deg), scored on
their accuracy and whether their sigma covers the errors (share beyond 3 sigma: a
Gaussian's 0.27 % per axis; none beyond 5), uncalibrated and after `calibrate zero-tilt`
on 12 level frames through the same chain; through the webcam also with the rig
declaring the camera's tone curve (``[camera] tone_curve = "srgb"``: the fits read
linear light, visvec.tone). Seeds of its own (61, 62), used by no test.

    python benchmarks/triangle_webcam.py [--frames 60]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from visvec.bench.triangle import (
    evaluate,
    level_calibration,
    random_cases,
    render_cases,
    with_refine,
)
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.webcam import WebcamChain

from _common import CONFIGS, run_record, save_json, summarise

CHAINS = {
    "plain render": Scene(),
    "through a webcam": Scene(webcam=WebcamChain()),
    "through a webcam, no tone curve": Scene(webcam=WebcamChain(srgb=False)),
}
# the rig's tone_curve per chain: through the webcam as the rig files leave it (linear)
# and as a lab that declares its webcam's sRGB curve
TONES = {"through a webcam": ("linear", "srgb")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    results = run_record()
    for cfg in ("triangle.toml", "triangle-320.toml"):
        res = {}
        for (name, scene), tone in (
            (item, t) for item in CHAINS.items() for t in TONES.get(item[0], ("linear",))
        ):
            rig = replace(load_rig(CONFIGS / cfg), tone_curve=tone)
            if tone != "linear":
                name = f"{name}, tone_curve = {tone}"
            cases = random_cases(args.frames, scene, seed=61)
            imgs = render_cases(rig, cases)
            cal, n_found = level_calibration(rig, rig, 12, scene, seed=620)
            for refine in ("lines", "pixels"):
                est = with_refine(rig, refine)
                row = {
                    "uncalibrated": summarise(evaluate(est, imgs, cases, "full")),
                    "after calibrate zero-tilt": summarise(
                        evaluate(with_refine(cal.apply(rig), refine), imgs, cases, "full")
                    ),
                    "calibration_height_offset_mm": round(cal.height_offset_mm, 3),
                    "calibration_frames": n_found,
                }
                res[f"{name} / {refine}"] = row
                for k, v in row.items():
                    print(cfg, name, refine, k, v, flush=True)
        results[cfg] = res
    print(save_json("triangle_webcam", results))


if __name__ == "__main__":
    main()
