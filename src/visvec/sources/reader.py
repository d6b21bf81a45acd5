"""A live source (camera or network stream) read in a thread of its own: each frame is
stamped when it arrives, not when the pipeline gets round to it, and the pipeline
always takes the newest frame (as a camera's one-frame driver buffer gives it).

Why: where the source's frames carry no usable capture time (an MJPEG stream: FFmpeg's
demuxer numbers its frames at 25 fps whatever the camera's rate), a frame's time is the
moment it was read. Read in the pipeline's thread, a frame that waited in the socket
while the last one was processed (a slow frame, a starved CPU) was stamped late by as
long as it waited, 300 ms after a 300 ms stall, and the fusion took it for a fix of that
later moment.

What cannot be mended by reading sooner is said: a frame read sooner after the one
before than QUEUED_SHARE of the stream's frame period had waited in a queue (the reader
itself was held up), so its read time is later than its exposure by an unknown amount;
so was the frame before it, read when the hold-up ended. Both get their ``late`` event
set (the one before possibly after it was handed out: the pipeline looks at it when its
row is made, the fusion again when the fix is sent)."""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

# a frame read within this share of the stream's frame period after the one before had
# waited in a queue: frames come at the period, one waiting for the reader comes at
# once (in the time it takes to decode, a few ms)
QUEUED_SHARE = 0.5
# the stream's frame period: the mean interval over this many frames (a burst of queued
# frames among them lowers it, so the share above still tells them); until that many
# have come, every frame is taken as queued (an opened stream hands out the frames it
# buffered while it was probed)
PERIOD_FRAMES = 8
# a reader that has handed out nothing new for this long is asked again (s): its
# capture's own read gives up sooner (a stream's STREAM_STALL_S, a camera's select)
TAKE_TIMEOUT_S = 12.0


@dataclass
class Arrival:
    """One read of the capture: ``t`` the time.monotonic() it returned, ``ms`` the
    capture's CAP_PROP_POS_MSEC then, ``n`` the frames this capture gave before it."""

    ok: bool
    image: np.ndarray | None
    t: float
    ms: float = 0.0
    n: int = 0
    late: threading.Event = field(default_factory=threading.Event)


class LiveReader:
    """Reads ``cap`` (opened) in a daemon thread, from the first :meth:`take` until the
    capture fails or :meth:`release`; :meth:`take` hands out the newest frame read
    (frames read and not taken are counted in ``dropped``). Once the thread runs, the
    capture is used by it alone, and it releases it; ``get`` answers from what was read
    before the thread started, and the POS_MSEC of the frame taken last. The frames
    pass through a queue.SimpleQueue (None when the capture has ended), drained to the
    newest at each take."""

    def __init__(self, cap: cv2.VideoCapture, name: str = "visvec-reader"):
        self._cap = cap
        self._props: dict[int, float] = {}
        self._q: queue.SimpleQueue[Arrival | None] = queue.SimpleQueue()  # None: ended
        self._last: Arrival | None = None  # the last one taken (POS_MSEC)
        self._ended = False
        self._stop = threading.Event()
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    # what the source asks of a cv2.VideoCapture
    def isOpened(self) -> bool:  # noqa: N802 - cv2's name
        return True

    def get(self, prop: int) -> float:
        if self._thread.ident is None and not self._ended:
            return self._cap.get(prop)  # not started: the capture is still ours
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self._last.ms if self._last is not None else 0.0
        return float(self._props.get(prop, 0.0) or 0.0)

    def read(self) -> tuple[bool, np.ndarray | None]:
        a = self.take()
        return a.ok, a.image

    def release(self) -> None:
        """Stops the thread and waits for it (its read returns within a frame, or
        fails within the capture's timeout): a thread left inside OpenCV's read when
        the interpreter exits aborts the process. Never started: the capture released
        here."""
        self._stop.set()
        if self._thread.ident is None:
            self._ended = True
            self._cap.release()
        elif self._thread is not threading.current_thread():
            self._thread.join(TAKE_TIMEOUT_S)

    def take(self, timeout_s: float = TAKE_TIMEOUT_S) -> Arrival:
        """The newest frame read since the last taken, waited for; a failed Arrival
        when the capture failed (its frames all taken) or nothing came within
        ``timeout_s``."""
        if self._thread.ident is None and not self._ended:
            self._props = {
                p: self._cap.get(p)
                for p in (cv2.CAP_PROP_FPS, cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_COUNT)
            }
            self._thread.start()
        a = None
        if not self._ended:
            try:
                a = self._q.get(timeout=timeout_s)
                while a is not None:  # the newest of those waiting
                    b = self._q.get_nowait()
                    if b is None:
                        self._ended = True
                        break
                    a = b
                    self.dropped += 1
            except queue.Empty:
                pass
            if a is None and not self._ended:
                self._ended = not self._thread.is_alive()
        if a is None:
            return Arrival(False, None, time.monotonic())
        self._last = a
        return a

    def _run(self) -> None:
        arrivals: deque[float] = deque(maxlen=PERIOD_FRAMES + 1)
        prev: Arrival | None = None
        n = 0
        try:
            while not self._stop.is_set():
                ok, img = self._cap.read()
                if not ok:
                    return  # (the frames read and not yet taken are still handed out)
                t = time.monotonic()
                a = Arrival(True, img, t, self._cap.get(cv2.CAP_PROP_POS_MSEC), n)
                if len(arrivals) < arrivals.maxlen:
                    a.late.set()  # the period is not known yet
                else:
                    period = (arrivals[-1] - arrivals[0]) / (len(arrivals) - 1)
                    if t - arrivals[-1] < QUEUED_SHARE * period:
                        a.late.set()
                        if prev is not None:
                            prev.late.set()  # read when the hold-up ended
                arrivals.append(t)
                n += 1
                self._q.put(a)
                prev = a
        finally:
            self._q.put(None)
            self._cap.release()
