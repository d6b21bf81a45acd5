"""A network camera for the tests: an MJPEG stream of the sample frames on 127.0.0.1,
served by a daemon thread, whose subclasses say what each connection gets."""

from __future__ import annotations

import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2

from conftest import ROOT

SAMPLES = sorted((ROOT / "data" / "sample_frames").glob("*.png"))


class MjpegServer:
    """Streams the sample frames at ``fps`` to every connection until the test ends
    (`close`); a subclass's `refuse(nth)` answers the nth connection 503, and its
    `ends(nth, i)` ends the nth connection before its frame ``i`` (True: close it;
    "stall": keep it open and send nothing more). `sent(nth, t)` is told each frame's
    sending time (time.monotonic())."""

    def __init__(self, fps: float = 30.0):
        self.jpegs = [cv2.imencode(".jpg", cv2.imread(str(p)))[1].tobytes() for p in SAMPLES]
        self.fps = fps
        self.connections = 0
        self.done = threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802
                outer.connections += 1
                nth = outer.connections
                if outer.refuse(nth):
                    self.send_error(503)
                    return
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=f")
                self.end_headers()
                i = 0
                try:
                    while not outer.done.is_set():
                        end = outer.ends(nth, i)
                        if end == "stall":
                            outer.done.wait(30.0)  # the connection stays open
                            return
                        if end:
                            return
                        b = outer.jpegs[i % len(outer.jpegs)]
                        head = (
                            f"--f\r\nContent-Type: image/jpeg\r\nContent-Length: {len(b)}\r\n\r\n"
                        )
                        self.wfile.write(head.encode() + b + b"\r\n")
                        self.wfile.flush()
                        outer.sent(nth, time.monotonic())
                        i += 1
                        time.sleep(1.0 / outer.fps)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def refuse(self, nth: int) -> bool:
        return False

    def ends(self, nth: int, i: int) -> bool | str:
        return False

    def sent(self, nth: int, t: float) -> None:
        pass

    def close(self) -> None:
        self.done.set()
        self.httpd.shutdown()
        self.httpd.server_close()
