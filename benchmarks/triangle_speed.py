"""Speed of detect + estimate at 640x480 on one core, against PNG decoding of the same
frames, measured in the same run.

A 30 fps recording: 300 frames (10 s) of a smooth motion turning at about 10 deg/s in
yaw with tilts wobbling within +-4 deg.
"tracking" processes them in order (each frame starts from the last one's vertices);
"cold" forgets the previous frame every time (lost-in-space on every frame).
"aruco": the fiducial-tag baseline (benchmarks/_fiducial.py: an ArUco tag in the
triangle's place, cv2.aruco + solvePnP IPPE_SQUARE) on every 5th attitude of the same
recording, timed in the same repeats; its accuracy beside it. Each frame is taken by
every method in turn (tracking and cold, in alternating order, the decode, the tag on
its frames), so that a machine whose speed drifts during the run slows them alike.

    python benchmarks/triangle_speed.py
    python benchmarks/triangle_speed.py --size 1920x1080   # an HD webcam, same field
    python benchmarks/triangle_speed.py --refine pixels    # with the pixel fit
    python benchmarks/triangle_speed.py --pair   # lines and pixel fit in turn: their ratio
    python benchmarks/triangle_speed.py --motion random  # every track lost: a new attitude
    VISVEC_PURE=1 python benchmarks/triangle_speed.py     # without the compiled kernels

``--size WxH`` puts the rig's lens on a sensor of that size with the same horizontal
field of view (fx scaled with the width, the principal point centred); ``--rig`` times
another rig file (a lab's own camera). ``--profile`` also says where each frame's
milliseconds go (the detector's and estimator's steps, timed by wrapping them: a few
microseconds more per frame than the plain run).
"""

from __future__ import annotations

import argparse  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import _onecore  # noqa: F401, I001 - one thread each for BLAS and OpenMP, before numpy
import cv2  # noqa: E402
import numpy as np  # noqa: E402

from visvec._kernels import jit  # noqa: E402
from visvec.bench.triangle import Case, render_cases, with_refine  # noqa: E402
from visvec.data import Frame  # noqa: E402
from visvec.pipeline import TrianglePipeline  # noqa: E402
from visvec.rig import load_rig  # noqa: E402
from visvec.sim.scene import Scene  # noqa: E402

from _common import CONFIGS, add_refine_option, run_record, save_json  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rig", default=str(CONFIGS / "triangle.toml"))
    ap.add_argument("--size", help="WxH: the same lens on a sensor of this size")
    ap.add_argument("--profile", action="store_true", help="the time of each step")
    ap.add_argument(
        "--tag-every",
        type=int,
        default=5,
        help="the tag baseline on every n-th attitude (its frames render slowly)",
    )
    ap.add_argument(
        "--motion",
        choices=["sweep", "random"],
        default="sweep",
        help="random: every frame at a new random attitude (yaw anywhere, tilts within 5 "
        "deg), so that every frame in sequence is a lost track and a search ('lost')",
    )
    add_refine_option(ap)
    ap.add_argument(
        "--pair",
        action="store_true",
        help="the edge lines and the pixel fit frame by frame in turn: their ratio, "
        "which the machine's speed (and its drift during the run) leaves alone",
    )
    args = ap.parse_args()
    _onecore.one_core()
    import _fiducial  # after _onecore: it imports numpy

    rig = with_refine(load_rig(args.rig), args.refine)
    name = "triangle_speed" if args.refine == "lines" else f"triangle_speed_{args.refine}"
    if not jit.ON:
        name += "_pure"
    if args.size:
        w, h = (int(v) for v in args.size.lower().split("x"))
        k = w / rig.camera.width
        cam = replace(
            rig.camera,
            width=w,
            height=h,
            fx=rig.camera.fx * k,
            fy=rig.camera.fy * k,
            cx=(w - 1) / 2.0,
            cy=(h - 1) / 2.0,
        )
        rig = replace(rig, camera=cam)
        name += f"_{w}x{h}"
    if args.motion == "random":
        from visvec.sim.simulate import random_attitudes

        eul = random_attitudes(args.frames, 5.0, np.random.default_rng(3), "random")
        name += "_random"
    else:
        eul = _fiducial.speed_sweep(args.frames)
    cases = [Case(e, Scene(), k) for k, e in enumerate(eul)]
    images = render_cases(rig, cases)
    pngs = [cv2.imencode(".png", im)[1] for im in images]
    if args.pair:
        res = {**run_record(), "image": f"{rig.camera.width}x{rig.camera.height}",
               "frames": args.frames, "repeats": args.repeats, "compiled_kernels": jit.ON,
               **pair(rig, images, pngs, args.repeats)}  # fmt: skip
        print(res)
        print(save_json(name.replace("triangle_speed", "triangle_speed_pair"), res))
        return
    tag_eul = eul[:: args.tag_every]
    tags = _fiducial.render_tags(rig, tag_eul, Scene())
    bases = {"aruco": _fiducial.ArucoBaseline(rig, Scene()),
             "aruco_subpix": _fiducial.ArucoBaseline(rig, Scene(), subpixel=True)}  # fmt: skip
    res = {
        **run_record(),
        "image": f"{rig.camera.width}x{rig.camera.height}, fx {rig.camera.fx:g} px",
        "frames": args.frames,
        "repeats": args.repeats,
        # the edge fit's compiled kernels (the fast extra; VISVEC_PURE=1 turns them off)
        "compiled_kernels": jit.ON,
    }
    # in sequence: tracking on the sweep; on random attitudes every frame's track is lost
    seq = "lost" if args.motion == "random" else "tracking"
    times = {seq: [], "cold": [], "png_decode": [], "aruco": [], "aruco_subpix": []}
    n_ok = {seq: 0, "cold": 0}
    for _ in range(args.repeats):
        pipes = {mode: TrianglePipeline(rig) for mode in n_ok}
        # frame by frame, each method in turn: a machine whose speed drifts during the
        # run (a shared host) slows them alike
        for i, im in enumerate(images):
            # which goes first alternates: the first to touch a frame finds it out of
            # the processor's cache
            order = list(pipes.items()) if i % 2 == 0 else list(pipes.items())[::-1]
            for mode, pipe in order:
                if mode == "cold":
                    pipe.detector.reset()
                t = time.perf_counter()
                # the recording's times: the rate between frames (and with it the
                # evidence of an undeclared rolling shutter) is part of each frame's work
                row = pipe.process(Frame(i, i / rig.fps, im))
                times[mode].append(time.perf_counter() - t)
                n_ok[mode] += row.ok
            t = time.perf_counter()
            cv2.imdecode(pngs[i], cv2.IMREAD_GRAYSCALE)
            times["png_decode"].append(time.perf_counter() - t)
            if i % args.tag_every == 0:
                for k, base in bases.items():
                    t = time.perf_counter()
                    base.attitude(tags[i // args.tag_every])
                    times[k].append(time.perf_counter() - t)
    for k, v in times.items():
        v = np.array(v) * 1000
        res[k] = {
            "median_ms": round(float(np.median(v)), 3),
            "p90_ms": round(float(np.percentile(v, 90)), 3),
            # each repeat's own median: how much the machine drifted during the run
            "repeat_medians_ms": np.round(
                np.median(v.reshape(args.repeats, -1), axis=1), 3
            ).tolist(),  # fmt: skip
        }
    for k, v in n_ok.items():
        res[k]["ok_fraction"] = round(v / (args.frames * args.repeats), 4)
    for k, base in bases.items():
        res[k].update(_fiducial.accuracy(base, tags, tag_eul), frames=len(tags))
    # each repeat's cold median over its tag median (the two taken frame by frame in the
    # same stretch of the run), and their median: the machine's drift left out
    per_repeat = np.array(res["cold"]["repeat_medians_ms"]) / res["aruco"]["repeat_medians_ms"]
    res["cold_to_aruco"] = round(float(np.median(per_repeat)), 2)
    res["cold_to_aruco_per_repeat"] = np.round(per_repeat, 2).tolist()
    per_repeat = np.array(res[seq]["repeat_medians_ms"]) / res["aruco"]["repeat_medians_ms"]
    res[f"{seq}_to_aruco"] = round(float(np.median(per_repeat)), 2)
    res[f"{seq}_to_aruco_per_repeat"] = np.round(per_repeat, 2).tolist()
    if seq == "lost":
        # a lost track's frame against a cold one, each repeat's medians
        per_repeat = np.array(res["lost"]["repeat_medians_ms"]) / res["cold"]["repeat_medians_ms"]
        res["lost_to_cold_per_repeat"] = np.round(per_repeat, 2).tolist()
    # the same on the machine the targets were set on (its tag: _fiducial.REFERENCE_TAG_MS)
    for k in ("cold", seq):
        res[f"{k}_reference_ms"] = round(res[f"{k}_to_aruco"] * _fiducial.REFERENCE_TAG_MS, 2)
    if args.profile:
        res["profile_ms_per_frame"] = {m: profile(rig, images, m == "cold") for m in n_ok}
    if not args.size:
        res["batch"] = batch_end_to_end(args.rig, pngs, args.repeats, args.refine)
    dec = res["png_decode"]["median_ms"]
    for k in (seq, "cold"):
        res[k]["ratio_to_png_decode"] = round(res[k]["median_ms"] / dec, 2)
    print(res)
    print(save_json(name, res))


def batch_end_to_end(rig_path: str, pngs, repeats: int, refine: str = "lines") -> dict:
    """`visvec batch FOLDER --rig RIG --out CSV` in this process (the interpreter's and
    the imports' start left out) on the recording written as PNG files, against reading
    and decoding the same files (cv2.imread, grey), each timed over the whole folder
    (the best of ``repeats`` runs): with the machine's cores (the folder is read by a
    thread beside the processing) and pinned to one CPU. ``refine``: the rig's [detect]
    refine (a copy of the rig file with it set)."""
    import csv
    import os
    import tempfile
    from pathlib import Path

    from click.testing import CliRunner

    from visvec.cli.main import cli

    cpus = os.sched_getaffinity(0)
    out = {"frames": len(pngs)}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "frames"
        folder.mkdir()
        for i, p in enumerate(pngs):
            (folder / f"frame_{i:05d}.png").write_bytes(p.tobytes())
        files = sorted(folder.glob("*.png"))
        if refine != "lines":
            text = Path(rig_path).read_text()
            if re.search(r'^refine = "\w+"', text, re.M) is None:
                raise SystemExit(f"{rig_path}: no [detect] refine key to set to {refine}")
            rig_path = str(Path(tmp) / "rig.toml")
            Path(rig_path).write_text(re.sub(r'^refine = "\w+"', f'refine = "{refine}"', text,
                                             flags=re.M))  # fmt: skip
        runner = CliRunner()
        settings = (("all_cpus", cpus), ("one_cpu", {min(cpus)}))
        best = {label: [float("inf"), float("inf")] for label, _ in settings}  # batch, decode
        frame_ms: dict[str, list[float]] = {label: [] for label, _ in settings}
        try:
            # the settings in turn within each repeat: the host's drift slows them alike
            for _ in range(repeats):
                for label, use in settings:
                    os.sched_setaffinity(0, use)
                    t = time.perf_counter()
                    for f in files:
                        cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                    best[label][1] = min(best[label][1], time.perf_counter() - t)
                    t = time.perf_counter()
                    r = runner.invoke(cli, ["batch", str(folder), "--rig", rig_path, "--out",
                                            str(Path(tmp) / "rows.csv")])  # fmt: skip
                    best[label][0] = min(best[label][0], time.perf_counter() - t)
                    if r.exit_code != 0:
                        raise RuntimeError(r.output)
                    with open(Path(tmp) / "rows.csv") as fh:
                        lat = [float(row["latency_ms"]) for row in csv.DictReader(fh)]
                    frame_ms[label].append(float(np.median(lat)))
        finally:
            os.sched_setaffinity(0, cpus)
        n = len(pngs)
        for label, use in settings:
            b, d = best[label]
            out[label] = {"cpus": len(use), "batch_ms_per_frame": round(b / n * 1000, 3),
                          "read_decode_ms_per_frame": round(d / n * 1000, 3),
                          "ratio": round(b / d, 2),
                          # a frame's own time (its processing, beside the folder's
                          # reading thread where there are two CPUs): each run's median
                          "frame_ms_medians": np.round(frame_ms[label], 3).tolist()}  # fmt: skip
        # the reading thread's cost to the frame beside it: each repeat's two CPUs over
        # one CPU
        out["frame_beside_reader_ratio"] = np.round(
            np.array(frame_ms["all_cpus"]) / frame_ms["one_cpu"], 2
        ).tolist()  # fmt: skip
    return out


# the steps timed by --profile: (module, class or None, function, label)
STEPS = (
    ("visvec.detect.triangle", None, "iter_candidates", "candidate regions (contours)"),
    ("visvec.detect.triangle", None, "fit_edges", "edge fit (all passes)"),
    ("visvec.detect.edges", None, "_profiles", "  profiles: sampling and step fits"),
    ("visvec.detect.edges", None, "_lines", "  lines: robust line fits"),
    ("visvec.detect.edges", None, "_widths", "  blur widths"),
    ("visvec.detect.triangle", None, "refine", "pixel fit (refine = pixels), all of it"),
    ("visvec.detect.photometric", None, "_band", "  the bands' pixels"),
    ("visvec._kernels.pixel_fit", None, "pixel_solve", "  the solve"),
    ("visvec.detect.triangle", "TriangleDetector", "_usability_reason", "checks of the image"),
    ("visvec.detect.triangle", "TriangleDetector", "detect", "detection (total)"),
    ("visvec.pipeline.triangle", "TrianglePipeline", "_solve", "attitude solve"),
)


def pair(rig, images, pngs, repeats: int) -> dict:
    """Median ms of each frame with the edge lines and with the pixel fit, tracked and
    cold, the four pipelines taking each frame in turn (with its PNG decode), and the
    pixel fit's over the lines'."""
    rigs = {r: with_refine(rig, r) for r in ("lines", "pixels")}
    keys = [(r, m) for r in rigs for m in ("tracking", "cold")]
    times: dict = {f"{r}_{m}": [] for r, m in keys}
    times["png_decode"] = []
    for _ in range(repeats):
        pipes = {(r, m): TrianglePipeline(rigs[r]) for r, m in keys}
        for i, im in enumerate(images):
            for (r, m), pipe in pipes.items():
                if m == "cold":
                    pipe.detector.reset()
                t = time.perf_counter()
                pipe.process(Frame(i, i / rig.fps, im))
                times[f"{r}_{m}"].append(time.perf_counter() - t)
            t = time.perf_counter()
            cv2.imdecode(pngs[i], cv2.IMREAD_GRAYSCALE)
            times["png_decode"].append(time.perf_counter() - t)
    med = {k: round(float(np.median(v)) * 1000, 3) for k, v in times.items()}
    return {"median_ms": med,
            "pixels_over_lines": {m: round(med[f"pixels_{m}"] / med[f"lines_{m}"], 3)
                                  for m in ("tracking", "cold")}}  # fmt: skip


def profile(rig, images, cold: bool) -> dict:
    """Median-free mean time per frame of each step in STEPS (ms), and of the whole."""
    import importlib

    spent: dict[str, float] = {label: 0.0 for *_, label in STEPS}
    saved = []

    def timed(f, label, generator):
        def run(*a, **k):
            t = time.perf_counter()
            if not generator:
                out = f(*a, **k)
                spent[label] += time.perf_counter() - t
                return out
            it = f(*a, **k)
            spent[label] += time.perf_counter() - t
            return timed_iter(it, label)

        return run

    def timed_iter(it, label):
        while True:
            t = time.perf_counter()
            try:
                x = next(it)
            except StopIteration:
                spent[label] += time.perf_counter() - t
                return
            spent[label] += time.perf_counter() - t
            yield x

    for mod_name, cls_name, fn, label in STEPS:
        owner = importlib.import_module(mod_name)
        if cls_name:
            owner = getattr(owner, cls_name)
        f = getattr(owner, fn)
        saved.append((owner, fn, f))
        setattr(owner, fn, timed(f, label, fn == "iter_candidates"))
    try:
        pipe = TrianglePipeline(rig)
        t0 = time.perf_counter()
        for i, im in enumerate(images):
            if cold:
                pipe.detector.reset()
            pipe.process(Frame(i, i / rig.fps, im))
        total = time.perf_counter() - t0
    finally:
        for owner, fn, f in saved:
            setattr(owner, fn, f)
    n = len(images)
    # (the steps a run does not take left out: the pixel fit's on the edge lines)
    out = {label: round(v / n * 1000, 3) for label, v in spent.items() if v > 0}
    out["frame (total)"] = round(total / n * 1000, 3)
    return out


if __name__ == "__main__":
    main()
