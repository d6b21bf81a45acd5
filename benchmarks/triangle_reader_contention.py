"""What work beside a frame costs it: a tracked 640x480 frame on the default rig, timed
while nothing else runs, and while the next PNG file is read and decoded beside it: by a
thread as the folder's reader does (visvec.imageio.read_image_why), by a thread in one
OpenCV call (cv2.imread, which holds the GIL only at its ends), and by another process
(no GIL shared at all). Blocks of 20 frames, the four settings in turn, 12 rounds; the
median frame time in each, and its ratio to the frame alone.

If the process slows the frame as much as the threads do, the cost is the machine's
(two CPUs that share caches, memory or a core), not the GIL's: no reader design on it
makes the frame beside it free.

    python benchmarks/triangle_reader_contention.py
"""

from __future__ import annotations

import multiprocessing as mp
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from visvec.bench.triangle import Case, render_cases
from visvec.data import Frame
from visvec.imageio import read_image_why
from visvec.pipeline import TrianglePipeline
from visvec.rig import load_rig
from visvec.sim.scene import Scene

from _common import CONFIGS, run_record, save_json

SETTINGS = ("alone", "thread, as the folder reader", "thread, cv2.imread", "process")
ROUNDS, BLOCK = 12, 20


def _decode(how: str, path: str) -> None:
    if how == "thread, cv2.imread":
        cv2.imread(path, cv2.IMREAD_UNCHANGED)
    else:
        read_image_why(path)


def _process_reader(conn, files: list[str]) -> None:
    """Another process: decode the next file each time it is asked."""
    k = 0
    while conn.recv() is not None:
        read_image_why(files[k % len(files)])
        k += 1
        conn.send(True)


def main() -> None:
    results = run_record()
    rig = load_rig(CONFIGS / "triangle.toml")
    # a slow swing (tracked frames), written as PNG files to read beside the frames
    yaws = np.radians(np.linspace(0.0, 40.0, 120))
    cases = [Case(np.array([y, 0.01, -0.01]), Scene(), 900 + k) for k, y in enumerate(yaws)]
    images = render_cases(rig, cases)
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for k, img in enumerate(images):
            files.append(str(Path(tmp) / f"frame_{k:05d}.png"))
            cv2.imwrite(files[-1], img)
        pipe = TrianglePipeline(rig)
        for k, img in enumerate(images[:5]):
            pipe.estimate(Frame(k, k / 30, img))
        how = {"now": "alone"}
        go, done = threading.Event(), threading.Event()

        def thread_reader() -> None:
            k = 0
            while True:
                go.wait()
                go.clear()
                if how["now"] is None:
                    return
                _decode(how["now"], files[k % len(files)])
                k += 1
                done.set()

        reader = threading.Thread(target=thread_reader, daemon=True)
        reader.start()
        ctx = mp.get_context("spawn")
        mine, theirs = ctx.Pipe()
        proc = ctx.Process(target=_process_reader, args=(theirs, files), daemon=True)
        proc.start()
        times: dict[str, list[float]] = {s: [] for s in SETTINGS}
        try:
            for rnd in range(ROUNDS):
                for setting in SETTINGS:
                    how["now"] = setting
                    for i in range(BLOCK):
                        k = (rnd * BLOCK + i) % len(images)
                        if setting.startswith("thread"):
                            done.clear()
                            go.set()
                        elif setting == "process":
                            mine.send(True)
                        t = time.perf_counter()
                        pipe.estimate(Frame(k, k / 30, images[k]))
                        times[setting].append(time.perf_counter() - t)
                        if setting.startswith("thread"):
                            done.wait()
                        elif setting == "process":
                            mine.recv()
        finally:
            how["now"] = None
            go.set()
            mine.send(None)
            proc.join(10)
    alone = float(np.median(times["alone"]))
    for setting in SETTINGS:
        med = float(np.median(times[setting]))
        results[setting] = {"median_ms": round(med * 1e3, 3), "to_alone": round(med / alone, 3)}
        print(f"{setting:30s} {med * 1e3:.3f} ms  {med / alone:.3f}x", flush=True)
    print(save_json("triangle_reader_contention", results))


if __name__ == "__main__":
    main()
