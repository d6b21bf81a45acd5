"""The triangle sensor on a rolling-shutter webcam while the platform turns.

Most webcams read their rows one after another: with a readout of 25 ms over the frame,
the bottom row is exposed 25 ms after the top one, and a platform turning in yaw shears
the triangle between its vertices. Frames are rendered with the renderer's rolling
shutter (`sim/render.py`: bands of 4 rows, each at the attitude of its exposure time)
at yaw rates of 0-20 deg/s and scored against the attitude of the centre row's
exposure. First cold frames at random attitudes (as in the accuracy benchmark), which
the sensor cannot correct (no rate yet), with the rig's `[camera] readout_ms` unset and
set (then their sigma covers `[platform] max_rate_dps`, here 20 deg/s); then tracked
recordings turning at a constant rate (60 frames at 30 fps, every frame scored),
with `readout_ms` unset (uncorrected: no readout estimated from the frames; estimated:
the sensor as shipped, which takes out the frames' own readout estimate once it is
5 sigma from zero) and set (corrected: edge points taken back to the centre row's
exposure with the rate of the last two frames; the second frame detected again with
the rate from its own first pass; the first frame widened), and
the same with the camera mounted 250 mm off the rotation axis (turning also moves it:
its translation during the readout shears the image too), and 240-frame recordings
(8 s) at 10 and 20 deg/s, long enough for the readout estimated from the frames to be
told apart from a static model error.

    python benchmarks/triangle_rolling_shutter.py [--frames 80] [--readout-ms 25]
"""

from __future__ import annotations

import argparse
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from visvec.bench.triangle import Case, evaluate, random_cases
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from _common import CONFIGS, run_record, save_json, summarise

RATES_DPS = (0.0, 2.0, 5.0, 10.0, 20.0)
OFF_AXIS_MM = (250.0, 0.0, 150.0)
OFF_AXIS_RATES_DPS = (0.0, 10.0, 20.0)
# longer recordings (8 s), where the readout estimated from the frames has a turn wide
# enough to be told apart from a static model error
LONG_FRAMES = 240
LONG_RATES_DPS = (10.0, 20.0)


def _render(args) -> np.ndarray:
    """A frame of the platform turning about the lab's n3 at ``omega_n`` (rad/s): its
    body rate is R_nb^T omega_n."""
    rig, case, readout_s, omega_n = args
    R = euler_to_matrix(*case.euler)
    return render_frame(rig, R, case.scene, case.seed, readout_s, R.T @ omega_n)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--readout-ms", type=float, default=25.0)
    args = ap.parse_args()
    readout = args.readout_ms / 1000.0
    results = {
        **run_record(),
        "readout_ms": args.readout_ms,
    }
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        cases = random_cases(args.frames, Scene(), seed=41)
        res = {}
        # the rig as the user would set it up for this camera: readout_ms, and the
        # platform's fastest turn (the benchmark's) as max_rate_dps
        rolling = replace(rig, readout_ms=args.readout_ms, max_rate_dps=max(RATES_DPS))
        # the camera mounted 250 mm off the rotation axis: turning also moves it
        off_axis = replace(rig, mount=replace(rig.mount, position_mm=np.array(OFF_AXIS_MM)))
        for rate in RATES_DPS:
            omega = np.radians([0.0, 0.0, rate])  # a yaw turn about n3
            with ProcessPoolExecutor(os.cpu_count() or 1) as ex:
                images = list(ex.map(_render, [(rig, c, readout, omega) for c in cases]))
            for label, r in (("", rig), ("readout_set_", rolling)):
                out = evaluate(r, images, cases, "full")
                s = summarise(out)
                if out.n_ok:
                    e = np.array(out.err_deg)
                    s["mean_abs_err_deg"] = np.round(np.abs(e).mean(axis=0), 5).tolist()
                    s["median_sigma_deg"] = np.round(np.median(out.sigma_deg, axis=0), 5).tolist()
                res[f"{label}yaw_rate_{rate}"] = s
                print(cfg, label, rate, s)
        runs = [
            (rate, where, r0, 60)
            for rate in RATES_DPS
            for where, r0 in (("", rig), ("off_axis_", off_axis))
            if not where or rate in OFF_AXIS_RATES_DPS
        ]
        runs += [(rate, "long_", rig, LONG_FRAMES) for rate in LONG_RATES_DPS]
        for rate, where, r0, n in runs:
            omega = np.radians([0.0, 0.0, rate])
            seed = 5100 if where == "long_" else 4100
            cases = [
                Case(
                    np.array([0.3 + omega[2] * k / 30.0, np.radians(2.0), np.radians(-1.0)]),
                    Scene(),
                    seed + k,
                )
                for k in range(n)
            ]
            with ProcessPoolExecutor(os.cpu_count() or 1) as ex:
                images = list(ex.map(_render, [(r0, c, readout, omega) for c in cases]))
            rolled = replace(r0, readout_ms=args.readout_ms, max_rate_dps=max(RATES_DPS))
            for label, r, shear in (
                ("uncorrected", r0, False),
                ("estimated", r0, True),
                ("corrected", rolled, True),
            ):
                out = evaluate(r, images, cases, "full", track=True, shear=shear)
                s = summarise(out)
                estimated = [
                    i for i, w in enumerate(out.warnings) if "rolling_shutter_estimated" in w
                ]
                if label == "estimated":
                    s["first_estimated_frame"] = estimated[0] if estimated else None
                res[f"tracked_{where}{label}_yaw_rate_{rate}"] = s
                print(cfg, "tracked", where, label, rate, s)
        results[cfg] = res
    print(save_json("triangle_rolling_shutter", results))


if __name__ == "__main__":
    main()
