"""Can a calibration learn a camera's tone curve from the triangle's own edges?

The pixel fit models a blurred step in linear light (visvec.detect.photometric); through
a tone curve the step's profile is bent. If the frames told the curves apart, `calibrate
zero-tilt` could choose one: fit each frame's pixels with the levels read through each
candidate curve (linear, sRGB, gammas 1.8, 2.2, 2.6), turn the residuals back into the
camera's grey levels (divided by the curve's slope at each pixel's level) and keep the
curve that leaves the least. Frames through visvec.sim.webcam's chain with its sRGB
curve and without it (every other step kept), cold frames at random attitudes (seed 63,
used by no test); the residual RMS (camera grey levels) per candidate. A curve the data
can tell apart is one whose RMS stands clearly below the others' for the chain that
applies it, and not for the other chain.

    python benchmarks/triangle_tone_learning.py [--frames 30]
"""

from __future__ import annotations

import argparse

import numpy as np

from visvec._kernels import pixel_fit as KP
from visvec.bench.triangle import random_cases, render_cases, with_refine
from visvec.detect import photometric as P
from visvec.detect import triangle as tri
from visvec.pipeline import TrianglePipeline
from visvec.rig import load_rig
from visvec.sim.scene import Scene
from visvec.sim.webcam import WebcamChain
from visvec.tone import tone_lut

from _common import CONFIGS, run_record, save_json

CANDIDATES = ("linear", "srgb", 1.8, 2.2, 2.6)
GN_STEPS = 6  # to convergence on every candidate


def fits_of(rig, images) -> list[tuple]:
    """The pixel fit's arguments on each frame, as the detector calls it."""
    calls = []
    real = tri.refine

    def record(*a, **k):
        calls.append(a[:5])
        return real(*a, **k)

    tri.refine = record
    try:
        pipe = TrianglePipeline(rig)
        for img in images:
            pipe.detector.reset()
            pipe.detector.detect(img)
    finally:
        tri.refine = real
    return calls


def residual_rms(calls) -> dict[str, float]:
    """Per candidate curve: the pixel fit's residual RMS over every frame's pixels, in
    the camera's grey levels."""
    sums = dict.fromkeys(map(str, CANDIDATES), 0.0)
    count = 0
    for image, normals, offsets, width, cam in calls:
        n, V, c, w, bands = P._lines_and_bands(image, normals, offsets, width, cam)
        if bands is None:
            continue
        x, y, _, counts = bands
        level = y.astype(np.int64)
        centroid = V.mean(axis=0)
        scale = max(float(np.abs(V - centroid).max()), 1.0)  # as refine takes it
        for curve in CANDIDATES:
            lut = tone_lut(curve)
            lin = y.astype(float) if lut is None else lut[level].astype(float)
            fit = KP._pixel_gn(x, lin, counts, n, c, w, centroid, scale, GN_STEPS, P._PHI,
                              P.PHI_RANGE, 1.0 / P.PHI_STEP)  # fmt: skip
            slope = np.ones(256) if lut is None else np.gradient(lut.astype(float))
            r = fit.r / np.maximum(slope[level], 1e-3)
            sums[str(curve)] += float(r @ r)
        count += len(y)
    return {k: round(float(np.sqrt(v / count)), 3) for k, v in sums.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    results = run_record()
    for cfg in ("triangle.toml", "triangle-320.toml"):
        rig = with_refine(load_rig(CONFIGS / cfg), "pixels")
        for chain, srgb in (("sRGB", True), ("no tone curve", False)):
            cases = random_cases(args.frames, Scene(webcam=WebcamChain(srgb=srgb)), seed=63)
            calls = fits_of(rig, render_cases(rig, cases))
            rms = residual_rms(calls)
            results[f"{cfg} / {chain}"] = {"fits": len(calls), "residual_rms": rms}
            print(cfg, chain, len(calls), rms, flush=True)
    print(save_json("triangle_tone_learning", results))


if __name__ == "__main__":
    main()
