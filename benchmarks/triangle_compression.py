"""The triangle sensor on compressed recordings: frames that went through a video codec.

Labs often record the webcam as video and run `visvec batch` on it later. Codecs add
block-shaped, spatially correlated errors that the edge covariance (calibrated on
sensor noise) does not model. One 300-frame tracked recording per resolution (a smooth
sweep at 30 fps, the clean scene) is scored losslessly (PNG), as Motion-JPEG at JPEG
quality 95 and 75 (each frame encoded alone, as MJPG does), and through OpenCV's mp4v
(MPEG-4 part 2) writer at its default quality: accuracy, ok fraction, and whether the
sigma still covers the errors.

    python benchmarks/triangle_compression.py [--frames 300]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from visvec.bench.triangle import Case, evaluate, machine, render_cases
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.simulate import random_attitudes

from _common import CONFIGS, command, save_json, summarise


def jpeg(images: list[np.ndarray], quality: int) -> list[np.ndarray]:
    out = []
    for im in images:
        ok, buf = cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, quality])
        out.append(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
    return out


def mp4v(images: list[np.ndarray]) -> list[np.ndarray]:
    h, w = images[0].shape
    with tempfile.TemporaryDirectory() as d:
        path = str(Path(d) / "rec.mp4")
        writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (w, h))
        for im in images:
            writer.write(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))
        writer.release()
        cap = cv2.VideoCapture(path)
        out = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        cap.release()
    if len(out) != len(images):
        raise RuntimeError(f"mp4v round trip gave {len(out)} of {len(images)} frames")
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    results = {"command": command(), "machine": machine(), "date": time.strftime("%Y-%m-%d")}
    for cfg in ("triangle-320.toml", "triangle.toml"):
        rig = load_rig(CONFIGS / cfg)
        eul = random_attitudes(args.frames, 5.0, np.random.default_rng(31), "sweep")
        cases = [Case(e, Scene(), 3100 + k) for k, e in enumerate(eul)]
        frames = render_cases(rig, cases)
        res = {}
        for name, images in (
            ("png", frames),
            ("mjpeg_q95", jpeg(frames, 95)),
            ("mjpeg_q75", jpeg(frames, 75)),
            ("mp4v", mp4v(frames)),
        ):
            s = summarise(evaluate(rig, images, cases, "full", track=True))
            res[name] = s
            print(cfg, name, s)
        results[cfg] = res
    print(save_json("triangle_compression", results))


if __name__ == "__main__":
    main()
