"""Network cameras: an MJPEG stream served by the test (127.0.0.1, frames of the sample
recording) that stalls, drops its connection or never answers; the rows across a
reconnect are neither shifted nor duplicated, a stall is noticed within 2 s."""

from __future__ import annotations

import csv
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import pytest

from conftest import ROOT, wait_until

RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = sorted((ROOT / "data" / "sample_frames").glob("*.png"))
FPS = 30.0


class Mjpeg:
    """An MJPEG server on 127.0.0.1 in a daemon thread. The first connection sends
    ``first`` frames, then ``then``: "stall" (keeps the connection, sends nothing more),
    "drop" (closes it); later connections stream until the test ends."""

    def __init__(self, first: int, then: str):
        self.jpegs = [cv2.imencode(".jpg", cv2.imread(str(p)))[1].tobytes() for p in SAMPLES]
        self.first, self.then = first, then
        self.connections = 0
        self.done = threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802
                outer.connections += 1
                nth = outer.connections
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=f")
                self.end_headers()
                i = 0
                try:
                    while not outer.done.is_set():
                        if nth == 1 and i >= outer.first:
                            if outer.then == "drop":
                                return
                            outer.done.wait(30.0)  # a stall: the connection stays open
                            return
                        b = outer.jpegs[i % len(outer.jpegs)]
                        head = (
                            f"--f\r\nContent-Type: image/jpeg\r\nContent-Length: {len(b)}\r\n\r\n"
                        )
                        self.wfile.write(head.encode() + b + b"\r\n")
                        i += 1
                        time.sleep(1.0 / FPS)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.done.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def track(url: str, out: Path, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera", url,
         "--out", str(out), *args],
        capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


def rows_of(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.parametrize("then", ["stall", "drop"])
def test_stream_that_stalls_or_drops_is_reopened_without_shifting_rows(tmp_path, then):
    srv = Mjpeg(first=20, then=then)
    try:
        out = tmp_path / "rows.csv"
        r = track(srv.url, out, "--max-frames", "45", "--retry-s", "5")
    finally:
        srv.close()
    assert r.returncode == 0, r.stderr
    rows = rows_of(out)
    # every frame one row, in order, each once; the frames after the reconnect go on
    # from the last index
    assert [int(x["frame"]) for x in rows] == list(range(45))
    assert all(x["status"] == "ok" for x in rows)
    t = [float(x["time_s"]) for x in rows]
    gaps = [b - a for a, b in zip(t, t[1:], strict=False)]
    assert min(gaps) > 0.0  # never a duplicate or a step back
    k = max(range(len(gaps)), key=gaps.__getitem__)
    assert k == 19  # the outage sits between frames 19 and 20, not elsewhere
    assert srv.connections >= 2 and "opening it again" in r.stderr
    if then == "stall":
        # noticed within 2 s (plus the reconnect), not after FFmpeg's 30 s
        assert 1.0 < gaps[k] < 2.6, gaps[k]
    # a live source's rows carry the absolute time: the computer's clock at the first
    # frame plus time_s, across the reconnect too
    unix = [float(x["time_unix"]) for x in rows]
    offsets = [u - tt for u, tt in zip(unix, t, strict=True)]
    assert max(offsets) - min(offsets) < 1e-5
    assert abs(unix[-1] - time.time()) < 30.0


def test_stream_that_never_answers_is_given_up_after_retry_s(tmp_path):
    mute = socket.socket()
    mute.bind(("127.0.0.1", 0))
    mute.listen(8)  # connections are accepted by the kernel; nothing ever answers
    url = f"http://127.0.0.1:{mute.getsockname()[1]}/stream.mjpg"
    try:
        t0 = time.monotonic()
        r = track(url, tmp_path / "rows.csv", "--retry-s", "1.5")
        took = time.monotonic() - t0
    finally:
        mute.close()
    assert r.returncode == 3, r.stderr
    assert "did not answer within 1.5 s" in r.stderr
    assert "--retry-s sets how long" in r.stderr  # the command line's advice, not the library's
    assert took < 1.5 + 3.0  # the retry time and the interpreter's start, not 30 s


def test_stream_that_stalls_for_good_ends_with_exit_3_and_its_rows_written(tmp_path):
    srv = Mjpeg(first=15, then="stall")
    try:
        # every later connection is refused: the server stops listening after the first
        out = tmp_path / "rows.csv"
        proc = subprocess.Popen(
            [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera", srv.url,
             "--out", str(out), "--retry-s", "1"],
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        wait_until(lambda: srv.connections >= 1, "track connecting", timeout=20)
        srv.httpd.shutdown()
        srv.httpd.server_close()
        err = proc.communicate(timeout=30)[1]
    finally:
        srv.done.set()
    assert proc.returncode == 3, err
    assert "stream stopped delivering frames (retried for 1 s" in err
    rows = rows_of(out)
    assert [int(x["frame"]) for x in rows] == list(range(15))


def test_an_mjpeg_streams_frames_keep_the_pixel_fit():
    """An MJPEG stream's frames do not name a codec that predicts frames from earlier
    ones (FFmpeg's "mjpeg" has no four-letter tag): a pixel-fit rig keeps its pixel fit."""
    from visvec.data import inter_frame
    from visvec.sources.open import open_source

    srv = Mjpeg(first=10**6, then="drop")
    try:
        frames = list(open_source(srv.url, fps=FPS, retry_s=5.0, max_frames=3))
    finally:
        srv.close()
    assert len(frames) == 3 and all(f.image is not None for f in frames)
    assert not any(inter_frame(f.codec) for f in frames), [f.codec for f in frames]
