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
(8 s) at 10 and 20 deg/s: turning one way (where a shear cannot be told apart from a
principal point a few px off), and swinging out and back once (peak rates 10 and
20 deg/s), where it can. Last, a global-shutter camera whose principal point is 2 or
4 px from the rig file's, after `calibrate zero-tilt`, on the one-way 8 s turn at
20 deg/s: the readout the frames suggest must not be taken out.

    python benchmarks/triangle_rolling_shutter.py [--frames 80] [--readout-ms 25]
    python benchmarks/triangle_rolling_shutter.py --refine pixels   # the pixel fit
"""

from __future__ import annotations

import argparse
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from visvec.bench.triangle import Case, evaluate, level_calibration, random_cases, with_refine
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from _common import CONFIGS, add_refine_option, run_record, save_json, summarise

RATES_DPS = (0.0, 2.0, 5.0, 10.0, 20.0)
OFF_AXIS_MM = (250.0, 0.0, 150.0)
OFF_AXIS_RATES_DPS = (0.0, 10.0, 20.0)
# longer recordings (8 s), where the readout estimated from the frames has a turn wide
# enough to be told apart from a static model error
LONG_FRAMES = 240
LONG_RATES_DPS = (10.0, 20.0)
# the swing's period (s): out and back once over the 240 frames
SWING_PERIOD_S = 8.0
# a global-shutter camera's principal point this far (px, x) from the rig file's
PRINCIPAL_POINT_ERRORS_PX = (2.0, 4.0)


def _render(args) -> np.ndarray:
    """A frame of the platform turning about the lab's n3 at ``omega_n`` (rad/s): its
    body rate is R_nb^T omega_n."""
    rig, case, readout_ms, omega_n = args
    R = euler_to_matrix(*case.euler)
    return render_frame(rig, R, case.scene, case.seed, readout_ms, R.T @ omega_n)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--readout-ms", type=float, default=25.0)
    add_refine_option(ap)
    args = ap.parse_args()
    readout = args.readout_ms
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
                out = evaluate(with_refine(r, args.refine), images, cases, "full")
                s = summarise(out)
                if out.n_ok:
                    e = np.array(out.err_deg)
                    s["mean_abs_err_deg"] = np.round(np.abs(e).mean(axis=0), 5).tolist()
                    s["median_sigma_deg"] = np.round(np.median(out.sigma_deg, axis=0), 5).tolist()
                res[f"{label}yaw_rate_{rate}"] = s
                print(cfg, label, rate, s)
        # (label, peak yaw rate, the lab, the rig the sensor is given, frames, motion,
        # readout rendered)
        runs = [
            (where, rate, r0, r0, 60, "oneway", readout)
            for rate in RATES_DPS
            for where, r0 in (("", rig), ("off_axis_", off_axis))
            if not where or rate in OFF_AXIS_RATES_DPS
        ]
        runs += [("long_", r, rig, rig, LONG_FRAMES, "oneway", readout) for r in LONG_RATES_DPS]
        runs += [("swing_", r, rig, rig, LONG_FRAMES, "swing", readout) for r in LONG_RATES_DPS]
        for dcx in PRINCIPAL_POINT_ERRORS_PX:
            lab = replace(rig, camera=replace(rig.camera, cx=rig.camera.cx + dcx))
            calibrated = level_calibration(rig, lab)[0].apply(rig)
            where = f"principal_point_{dcx:g}px_global_"
            runs.append((where, 20.0, lab, calibrated, LONG_FRAMES, "oneway", 0.0))
        for where, rate, lab, r0, n, motion, readout_ms in runs:
            w, t = np.radians(rate), np.arange(n) / 30.0
            if motion == "swing":
                amp = w * SWING_PERIOD_S / (2.0 * np.pi)
                yaw = 0.3 + amp * np.sin(2.0 * np.pi * t / SWING_PERIOD_S)
                yaw_rate = w * np.cos(2.0 * np.pi * t / SWING_PERIOD_S)
            else:
                yaw, yaw_rate = 0.3 + w * t, np.full(n, w)
            seed = 5100 if n == LONG_FRAMES else 4100
            cases = [
                Case(np.array([yaw[k], np.radians(2.0), np.radians(-1.0)]), Scene(), seed + k)
                for k in range(n)
            ]
            jobs = [
                (lab, c, readout_ms, np.array([0.0, 0.0, yaw_rate[k]])) for k, c in enumerate(cases)
            ]
            with ProcessPoolExecutor(os.cpu_count() or 1) as ex:
                images = list(ex.map(_render, jobs))
            rolled = replace(r0, readout_ms=args.readout_ms, max_rate_dps=max(RATES_DPS))
            labels = [("uncorrected", r0, False), ("estimated", r0, True)]
            if readout_ms:
                labels.append(("corrected", rolled, True))
            for label, r, shear in labels:
                out = evaluate(with_refine(r, args.refine), images, cases, "full", track=True,
                               shear=shear)  # fmt: skip
                s = summarise(out)
                estimated = [
                    i for i, w in enumerate(out.warnings) if "rolling_shutter_estimated" in w
                ]
                if label == "estimated":
                    s["first_estimated_frame"] = estimated[0] if estimated else None
                res[f"tracked_{where}{label}_yaw_rate_{rate}"] = s
                print(cfg, "tracked", where, label, rate, s)
        results[cfg] = res
    name = "triangle_rolling_shutter"
    print(save_json(name if args.refine == "lines" else f"{name}_{args.refine}", results))


if __name__ == "__main__":
    main()
