"""A camera pipeline as a live source of fixes (`visvec track --imu`).

The camera's frames are processed in their own thread, exactly as `track` processes
them; each row goes to the camera's own output (if any) and each ok row to the fusion
as a fix. A fix's exposure is put on the host's clock (the moment the first frame was
delivered plus the frame's time from the first) and taken onto the IMU's clock by the
fusion loop (`live.run_live`), which learns the IMU clock's offset from its samples'
arrivals. The fusion thread never waits for the camera: frames that take long only
make their fixes later, and late fixes are replayed where they belong.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator

from visvec.data import Frame
from visvec.fuse.live import Event


def paced(frames: Iterable[Frame]) -> Iterator[Frame]:
    """Frames delivered at their own pace (``time_s`` from the first), as a camera
    would deliver a recording: for replaying a recording live."""
    t0 = first = None
    for f in frames:
        if t0 is None:
            t0, first = time.monotonic(), f.time_s
        wait = t0 + (f.time_s - first) - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        yield f


class CameraFixes:
    """Reads ``frames`` through ``pipe`` in a thread; rows to ``sink`` (or nowhere),
    ok rows as "fix" events with ``_host_exposure`` (time.monotonic() seconds); then
    ``watcher`` (the live view) sees the frame."""

    name = "fix"

    def __init__(
        self, frames: Iterable[Frame], pipe, events, sink=None, source="camera", watcher=None
    ):
        self.frames = frames
        self.watcher = watcher  # sees each frame, its row and the pipeline after the row
        self.pipe = pipe
        self.events = events
        self.sink = sink
        self.source = source
        self.stop = threading.Event()
        self.n_frames = 0
        self.n_ok = 0
        self.error: BaseException | None = None

    def check(self) -> None:
        pass

    def run(self) -> None:
        t0 = first = None
        try:
            for frame in self.frames:
                if self.stop.is_set():
                    break
                if t0 is None:
                    t0, first = time.monotonic(), frame.time_s
                    self.events.put(
                        Event(
                            "note",
                            "fix",
                            t0,
                            text=(f"{self.source}: first frame (host monotonic clock {t0:.6f} s)"),
                        )
                    )
                row = self.pipe.process(frame)
                self.n_frames += 1
                if self.sink is not None:
                    self.sink.write(row.as_dict())
                if row.ok and not frame.late:
                    # (late asked again: its reader may have learnt it since the row)
                    self.n_ok += 1
                    # the row itself (its covariance whole), and its exposure on the host
                    d = {"_row": row, "_host_exposure": t0 + (frame.time_s - first)}
                    self.events.put(Event("fix", "fix", time.monotonic(), d))
                if self.watcher is not None:
                    self.watcher.see(frame, row, self.pipe)
        except Exception as exc:  # reported by the fusion loop; the IMU rows go on
            self.error = exc
            self.events.put(Event("note", "fix", time.monotonic(),
                                  text=f"camera stopped: {exc}"))  # fmt: skip
        self.events.put(Event("end", "fix", time.monotonic()))

    def start(self) -> threading.Thread:
        th = threading.Thread(target=self.run, name="visvec-camera", daemon=True)
        th.start()
        return th
