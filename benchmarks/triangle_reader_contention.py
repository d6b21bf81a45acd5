"""What work beside a frame costs it: a tracked 640x480 frame on the default rig, timed
while nothing else runs, and while the next PNG file is read and decoded beside it: by a
thread as the folder's reader does (visvec.imageio.read_image_why), by a thread in one
OpenCV call (cv2.imread, which holds the GIL only at its ends), and by another process
(no GIL shared at all). Blocks of 20 frames, the four settings in turn, 12 rounds; the
median frame time in each, and its ratio to the frame alone.

If the process slows the frame as much as the threads do, the cost is the machine's
(two CPUs that share caches, memory or a core), not the GIL's: no reader design on it
makes the frame beside it free.

A live camera is read the other way: visvec.sources.reader.LiveReader's thread waits in
the capture's read until the camera hands over the next frame, decodes it, and the
frame is processed while the reader waits for the one after. Timed here with a camera
at 30 fps whose read waits for the frame's time and then decodes its PNG (as a Motion-
JPEG camera's frames are decoded in the read), against frames processed at the same
pace with no reader at all (a frame after an idle wait is slower than one straight
after another: the caches and the CPU's clock cooled).

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
from visvec.sources.reader import LiveReader

from _common import CONFIGS, run_record, save_json

SETTINGS = ("alone", "thread, as the folder reader", "thread, cv2.imread", "process")
LIVE = ("paced at 30 fps, alone", "paced at 30 fps, a live camera's reader")
ROUNDS, BLOCK = 12, 20
PERIOD_S = 1.0 / 30.0


class _Camera:
    """A camera at PERIOD_S for LiveReader: read() waits for its next frame's time, then
    decodes the frame's PNG file and hands it over."""

    def __init__(self, files: list[str], first: int):
        self.files, self.k = files, first
        self.next = time.monotonic()

    def isOpened(self) -> bool:  # noqa: N802 - cv2's name
        return True

    def get(self, prop: int) -> float:
        return 1.0 / PERIOD_S if prop == cv2.CAP_PROP_FPS else 0.0

    def read(self):
        self.next += PERIOD_S
        wait = self.next - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        img, _ = read_image_why(self.files[self.k % len(self.files)])
        self.k += 1
        return img is not None, img

    def release(self) -> None:
        pass


def _live_block(pipe, images, files, first: int, reader: bool) -> list[float]:
    """BLOCK frames at the camera's pace, each frame's processing time: taken from a
    LiveReader on _Camera, or (``reader`` False) with the pace kept by sleeping."""
    out = []
    cam = LiveReader(_Camera(files, first)) if reader else None
    nxt = time.monotonic()
    try:
        for i in range(BLOCK):
            k = (first + i) % len(images)
            if cam is not None:
                cam.take()
            else:
                nxt += PERIOD_S
                time.sleep(max(nxt - time.monotonic(), 0.0))
            t = time.perf_counter()
            pipe.estimate(Frame(k, k / 30, images[k]))
            out.append(time.perf_counter() - t)
    finally:
        if cam is not None:
            cam.release()
    return out


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
        times: dict[str, list[float]] = {s: [] for s in SETTINGS + LIVE}
        try:
            for rnd in range(ROUNDS):
                for setting in LIVE:
                    times[setting] += _live_block(pipe, images, files, rnd * BLOCK,
                                                  setting == LIVE[1])  # fmt: skip
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
    for group in (SETTINGS, LIVE):
        alone = float(np.median(times[group[0]]))
        for setting in group:
            med = float(np.median(times[setting]))
            results[setting] = {"median_ms": round(med * 1e3, 3),
                                "to_alone": round(med / alone, 3)}  # fmt: skip
            print(f"{setting:40s} {med * 1e3:.3f} ms  {med / alone:.3f}x", flush=True)
    print(save_json("triangle_reader_contention", results))


if __name__ == "__main__":
    main()
