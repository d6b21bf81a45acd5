"""What the live view knows: the newest frame, the rows of the last minute, the run's
figures, kept by the sensor's loop in O(1) per frame and read by the page's thread."""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque

import cv2
import numpy as np

from visvec.view.aids import Aids, aids
from visvec.view.words import in_words

# the page's plots span this much of the rows' time (s)
WINDOW_S = 60.0
# the rows of the last WINDOW_S are kept, at most this many (a 1 kHz IMU for a minute)
MAX_HISTORY = 60_000
# a frame is drawn and encoded for the page at most this often (s), and less often when
# drawing takes more than RENDER_SHARE of the time (a slow computer): frames are dropped
# for the page, never for the rows
FRAME_EVERY_S = 0.1
RENDER_SHARE = 0.02
# the set-up aids (histogram, sharpness, margin) are computed at most this often (s)
AIDS_EVERY_S = 0.5
# the picture sent is at most this wide (px)
MAX_WIDTH_PX = 960
JPEG_QUALITY = 80
# the frame rate and latency shown are over this many of the newest rows
RECENT = 100


class ViewState:
    """The sensor's side (:meth:`see`, :meth:`fused`, :meth:`end`) only stores
    references and numbers; the page's side (:meth:`snapshot`, :meth:`frame_jpeg`) does
    the drawing, the encoding and the aids, in the server's threads.

    Parameters
    ----------
    rig : Rig
        For the overlay and the kind of values.
    value_columns, sigma_columns : names of the rows' values and their 1-sigma columns
    info : lines the page shows about the run (the source, the rig, what `visvec check`
        says, the camera's settings)
    """

    def __init__(self, rig, value_columns, sigma_columns, info: list[str] | None = None):
        self.rig = rig
        self.value_columns = list(value_columns)
        self.sigma_columns = list(sigma_columns)
        self.info = list(info or ())
        self._lock = threading.Lock()
        self._render = threading.Lock()
        self.seq = 0
        self.n = self.n_ok = 0
        self._latest = None  # (seq, frame index, image, detection, row)
        self._last = None  # the newest row as a dict
        self._hist: deque = deque(maxlen=MAX_HISTORY)
        self._fused: deque = deque(maxlen=MAX_HISTORY)
        self._arrivals: deque = deque(maxlen=RECENT)
        self._latency: deque = deque(maxlen=RECENT)
        self.ended = False
        self._jpeg: tuple[int, bytes, int] | None = None
        self._jpeg_t = 0.0
        self._every = FRAME_EVERY_S
        self._aids: Aids | None = None
        self._aids_t = -1e9
        self.t0 = time.monotonic()

    # ---- the sensor's side: O(1), no drawing, no encoding

    def see(self, frame, row, pipe) -> None:
        """A frame, its row and the pipeline's detection (a watcher of the frame loop)."""
        d = row.as_dict()
        now = time.monotonic()
        d["_host_s"] = round(now - self.t0, 4)
        with self._lock:
            self.seq += 1
            self.n += 1
            self.n_ok += int(row.ok)
            self._last = d
            _keep_window(self._hist, self.seq, d)
            self._arrivals.append(now)
            self._latency.append(row.latency_ms)
            if frame.image is not None:
                self._latest = (self.seq, frame.index, frame.image, pipe.last_detection, row)

    def fused(self, d: dict) -> None:
        """A fused row (a dict of its columns), for a run with an IMU. The page then
        plots the camera's rows and the fused ones on this computer's clock (the two
        come on their own clocks)."""
        d = dict(d, _host_s=round(time.monotonic() - self.t0, 4))
        with self._lock:
            self.seq += 1
            _keep_window(self._fused, self.seq, d)

    def close(self) -> None:
        with self._lock:
            self.ended = True

    # ---- the page's side

    def snapshot(self, since: int = 0) -> dict:
        """The page's data: the run's figures, the newest row, the rows after ``since``
        within the last WINDOW_S, the newest frame's aids."""
        with self._lock:
            # copies only of the rows the page has not had (at most seq - since of
            # each), the filtering done outside the sensor's lock
            hist_all = _newest(self._hist, self.seq - since)
            fused_all = _newest(self._fused, self.seq - since)
            last = self._last
            arrivals = list(self._arrivals)
            latency = list(self._latency)
            n, n_ok, seq, ended = self.n, self.n_ok, self.seq, self.ended
            frame_no = self._latest[1] if self._latest else None
        hist = [d for s, d in hist_all if s > since]
        fused = [d for s, d in fused_all if s > since]
        fps = None
        if len(arrivals) > 2 and arrivals[-1] > arrivals[0]:
            fps = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
        out = {
            "seq": seq,
            "values": self.value_columns,
            "sigmas": self.sigma_columns,
            "run": {
                "rows": n,
                "ok": n_ok,
                "ok_share": n_ok / n if n else None,
                "rows_per_s": round(fps, 2) if fps else None,
                "latency_ms": round(statistics.median(latency), 3) if latency else None,
                "elapsed_s": round(time.monotonic() - self.t0, 1),
                "ended": ended,
            },
            "last": dict(last, words=in_words(last["status"], last["warnings"])) if last else None,
            "frame": frame_no,
            "history": hist,
            "fused": fused,
            "aids": self._aids.as_dict() if self._aids is not None else None,
            "info": self.info,
        }
        return out

    def frame_jpeg(self) -> tuple[int, bytes] | None:
        """(frame index, JPEG) of the newest frame with its detection drawn; drawn
        again at most every FRAME_EVERY_S, however many pages ask."""
        with self._render:
            now = time.monotonic()
            with self._lock:
                latest = self._latest
            if latest is None:
                return None
            seq, index, image, det, row = latest
            cached = self._jpeg
            if cached is not None and (cached[0] == seq or now - self._jpeg_t < self._every):
                return cached[2], cached[1]
            from visvec.overlay import draw_overlay

            t0 = time.perf_counter()
            img = draw_overlay(image, det, row, self.rig)
            if img.shape[1] > MAX_WIDTH_PX:
                f = MAX_WIDTH_PX / img.shape[1]
                img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                return None
            if now - self._aids_t >= AIDS_EVERY_S:
                gray = image if image.dtype == np.uint8 else np.clip(image, 0, 255).astype(np.uint8)
                self._aids = aids(gray, det)
                self._aids_t = now
            self._jpeg = (seq, buf.tobytes(), index)
            self._jpeg_t = now
            # the next frame no sooner than keeps the drawing within RENDER_SHARE
            self._every = max(FRAME_EVERY_S, (time.perf_counter() - t0) / RENDER_SHARE)
            return index, self._jpeg[1]


def _keep_window(rows: deque, seq: int, d: dict) -> None:
    """Append the row ``d`` (number ``seq``) to ``rows`` and drop those more than
    WINDOW_S older than it (by their time_s): O(1) a row over a run, so that the page's
    first request (since 0), or one after a reload, costs a minute's rows whenever it
    comes, not the run's so far (which, copied and trimmed in the server's thread, took
    the sensor's core for seconds after ten minutes of a 100 Hz IMU)."""
    rows.append((seq, d))
    t_end = d["time_s"]
    while rows and rows[0][1]["time_s"] < t_end - WINDOW_S:
        rows.popleft()


def _newest(rows: deque, n: int) -> list:
    """The newest ``n`` of ``rows`` (all when n >= len), oldest first: a deque is
    indexed in O(1) near its ends, so a page's poll copies only what is new."""
    if n <= 0:
        return []
    if n >= len(rows):
        return list(rows)
    return [rows[i] for i in range(len(rows) - n, len(rows))]
