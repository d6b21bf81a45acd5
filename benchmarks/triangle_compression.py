"""The triangle sensor on compressed recordings: frames that went through a video codec.

Labs often record the webcam as video and run `visvec batch` on it later, and network
cameras stream H.264. Codecs add block-shaped, spatially correlated errors that the edge
covariance (calibrated on sensor noise) does not model. Two 300-frame tracked
recordings per resolution (a smooth yaw sweep and a swing of the tilts, at 30 fps, the
clean scene) are scored losslessly (PNG), as Motion-JPEG at JPEG quality 95 and 75
(each frame encoded alone, as MJPG does), through OpenCV's mp4v (MPEG-4 part 2) writer
at its default quality, and (with PyAV, the bench extra) through H.264 as an IP camera
streams it (libx264 at its default quality, CRF 23, a key frame a second, no B-frames):
accuracy, ok fraction, and whether the sigma still covers the errors. Each frame
carries the codec OpenCV's reader names for it (Frame.codec).

Then the remedy a lab has: `calibrate zero-tilt` on level frames recorded through the
same codec (12 yaws, 10 frames each) measures how much wider the vertices scatter than
their sigma; both recordings are scored again with that ratio as `[detect] sigma_scale`.

    python benchmarks/triangle_compression.py [--frames 300] [--refine pixels]
"""

from __future__ import annotations

import argparse
import importlib.util
from dataclasses import replace

import numpy as np

from visvec.bench.codecs import h264, jpeg, mp4v
from visvec.bench.triangle import Case, evaluate, render_cases, with_refine
from visvec.calib.zero_tilt import calibrate_zero_tilt
from visvec.data import Frame, Status
from visvec.pipeline import TrianglePipeline
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.simulate import random_attitudes

from _common import CONFIGS, add_refine_option, run_record, save_json, summarise


def sigma_check(rig, images: list[np.ndarray], codec: str = "") -> dict:
    """`calibrate zero-tilt` on level frames: the sigma ratio it measures and writes."""
    pipe = TrianglePipeline(rig)
    dets = []
    for i, im in enumerate(images):
        pipe.process(Frame(i, i / 30.0, im, codec=codec))
        if pipe.last_detection is not None and pipe.last_detection.status is Status.OK:
            dets.append(pipe.last_detection)
    cal = calibrate_zero_tilt(dets, rig)
    return {
        "frames": len(dets),
        "left_out": int(cal.outliers.sum()),
        "sigma_ratio": round(cal.sigma_ratio, 3),
        "sigma_ratio_95": cal.sigma_ratio_95.round(3).tolist(),
        "sigma_scale": round(cal.sigma_scale, 3),
        # the camera check (aspect and principal point free): a codec must not read as
        # a wrong camera model (calibrate zero-tilt would then refuse)
        "camera_off": cal.camera_off,
        "aspect": round(cal.aspect, 6),
        "sigma_aspect": round(cal.sigma_aspect, 6),
        "principal_point_px": cal.principal_point_px.round(2).tolist(),
        "sigma_principal_point_px": cal.sigma_principal_point_px.round(2).tolist(),
    }


def codecs(images: list[np.ndarray]) -> dict[str, tuple[list[np.ndarray], str]]:
    """The frames through each format, and the codec a video file's reader names for
    them (Frame.codec: Motion-JPEG's MJPG codes each frame alone; mp4v's FMP4 and
    H.264's h264 predict frames from earlier ones, and the pixel fit is set aside on
    them). H.264 with PyAV (the bench extra) only."""
    out = {
        "png": (images, ""),
        "mjpeg_q95": (jpeg(images, 95), "MJPG"),
        "mjpeg_q75": (jpeg(images, 75), "MJPG"),
        "mp4v": mp4v(images, with_codec=True),
    }
    if importlib.util.find_spec("av") is not None:
        out["h264"] = h264(images)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    add_refine_option(ap)
    args = ap.parse_args()
    results = run_record()
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = with_refine(load_rig(CONFIGS / cfg), args.refine)
        # level frames, 10 at each of 12 yaws (a few seconds of video per yaw)
        yaws = np.repeat(np.linspace(-np.pi, np.pi, 12, endpoint=False) + 0.1, 10)
        level = render_cases(
            rig, [Case(np.array([y, 0.0, 0.0]), Scene(), 500 + k) for k, y in enumerate(yaws)]
        )
        level_by_codec = codecs(level)
        checks = {name: sigma_check(rig, *lv) for name, lv in level_by_codec.items()}
        # a yaw sweep, and a swing of the tilts (the image's content translating,
        # which a codec's motion prediction follows less well)
        for motion, seed in (("sweep", 31), ("swing", 7)):
            eul = random_attitudes(args.frames, 5.0, np.random.default_rng(seed), motion)
            cases = [Case(e, Scene(), 3100 + k) for k, e in enumerate(eul)]
            res = {}
            for name, (images, codec) in codecs(render_cases(rig, cases)).items():
                s = summarise(evaluate(rig, images, cases, "full", track=True, codec=codec))
                s["codec"] = codec
                check = checks[name]
                scaled = replace(rig, detect=replace(rig.detect, sigma_scale=check["sigma_scale"]))
                s["zero_tilt_sigma_check"] = check
                s["with_sigma_scale"] = summarise(
                    evaluate(scaled, images, cases, "full", track=True, codec=codec)
                )
                res[name] = s
                print(cfg, motion, name, s)
            results[cfg if motion == "sweep" else f"{cfg} {motion}"] = res
    name = "triangle_compression" + ("" if args.refine == "lines" else f"_{args.refine}")
    print(save_json(name, results))


if __name__ == "__main__":
    main()
