"""The live view's web server: the page, its assets and the live data, nothing else.

The standard library's ThreadingHTTPServer: a page for a handful of browsers on a lab
network needs GET of a few fixed routes and nothing a framework adds, and it keeps the
sensor free of a server dependency. Each connection has its own daemon thread; what
they serve is drawn at most every FRAME_EVERY_S and cached (view/state.py), so many
browsers cost what one does. Nothing is read from disk after start (the assets are
loaded from the package once) and nothing is writable: only GET and HEAD are answered.
"""

from __future__ import annotations

import errno
import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

from visvec.errors import ConfigError
from visvec.view.state import ViewState

# at most this many connections are served at once; more are closed at once
MAX_CONNECTIONS = 32
# a connection that sends nothing for this long is closed (s)
IDLE_TIMEOUT_S = 15.0
# the rows of a state answer are encoded this many at a time (see state_json)
JSON_CHUNK_ROWS = 200

ASSETS = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/view.js": ("view.js", "text/javascript; charset=utf-8"),
    "/view.css": ("view.css", "text/css; charset=utf-8"),
    "/uPlot.iife.min.js": ("uPlot.iife.min.js", "text/javascript; charset=utf-8"),
    "/uPlot.min.css": ("uPlot.min.css", "text/css; charset=utf-8"),
}


def state_json(snap: dict) -> bytes:
    """The page's data as JSON, its rows encoded JSON_CHUNK_ROWS at a time.

    json.dumps holds the interpreter's lock for the whole of one call: a page's first
    request (a minute of a 100 Hz IMU's fused rows and the camera's) took it for
    50-130 ms at once, and every row of the sensor waited that long. Between two
    chunks' calls (a few ms each) the sensor's threads get their turn."""
    parts = []
    for key, value in snap.items():
        if key in ("history", "fused"):
            chunks = (json.dumps(value[i : i + JSON_CHUNK_ROWS], allow_nan=False)[1:-1]
                      for i in range(0, len(value), JSON_CHUNK_ROWS))  # fmt: skip
            value_json = "[" + ", ".join(chunks) + "]"
        else:
            value_json = json.dumps(value, allow_nan=False)
        parts.append(json.dumps(key) + ": " + value_json)
    return ("{" + ", ".join(parts) + "}").encode()


def parse_address(spec: str, option: str = "address") -> tuple[str, int]:
    """``[HOST:]PORT`` (an IPv6 host in brackets) -> (host, port); the host defaults
    to 127.0.0.1, this computer only."""
    host, sep, port = spec.rpartition(":")
    if not sep:
        host, port = "127.0.0.1", spec
    host = host.strip("[]") or "127.0.0.1"
    try:
        p = int(port)
    except ValueError:
        raise ConfigError(f"{option} {spec!r}: expected [HOST:]PORT, a port number 0-65535 "
                          "(0: any free port)") from None  # fmt: skip
    if not 0 <= p <= 65535:
        raise ConfigError(f"{option} {spec!r}: the port must be 0-65535 (0: any free port)")
    return host, p


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = False  # a port in use is refused, not shared

    def __init__(self, address, handler, state: ViewState, assets: dict[str, bytes]):
        self.state = state
        self.assets = assets
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "visvec"
    timeout = IDLE_TIMEOUT_S

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        pass  # a browser's requests are not the operator's business

    def _send(self, code: int, body: bytes, ctype: str, extra: dict | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_HEAD(self):  # noqa: N802 - the base class's name
        self.do_GET()

    def do_GET(self):  # noqa: N802
        url = urlsplit(self.path)
        srv: _Server = self.server  # type: ignore[assignment]
        try:
            if url.path in ASSETS:
                name, ctype = ASSETS[url.path]
                self._send(200, srv.assets[name], ctype)
            elif url.path == "/api/state":
                q = parse_qs(url.query)
                try:
                    since = int(q.get("since", ["0"])[0])
                except ValueError:
                    since = 0
                body = state_json(srv.state.snapshot(since))
                self._send(200, body, "application/json")
            elif url.path == "/frame.jpg":
                got = srv.state.frame_jpeg()
                if got is None:
                    self._send(204, b"", "image/jpeg")
                else:
                    self._send(200, got[1], "image/jpeg", {"X-Visvec-Frame": str(got[0])})
            else:
                self._send(404, b"not found\n", "text/plain; charset=utf-8")
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True  # the browser went away


def _load_assets() -> dict[str, bytes]:
    pkg = resources.files("visvec.view") / "static"
    return {name: (pkg / name).read_bytes() for name, _ in ASSETS.values()}


class LiveServer:
    """The live view's server for ``state``, bound at once (so a port in use or not
    allowed is refused before the camera opens), serving from :meth:`start` in a
    daemon thread until :meth:`stop`."""

    def __init__(self, host: str, port: int, state: ViewState, option: str = "address"):
        try:
            self.httpd = _Server((host, port), _Handler, state, _load_assets())
        except OSError as e:
            where = f"{option} {host}:{port}"
            if e.errno == errno.EADDRINUSE:
                why = (
                    "the port is in use (another visvec or server?); choose another, or 0 "
                    "for any free port"
                )
            elif e.errno in (errno.EACCES, errno.EPERM):
                why = "not allowed (ports below 1024 need root); choose a port from 1024"
            elif e.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT) or isinstance(
                e, socket.gaierror
            ):
                why = (
                    "this computer has no such address (127.0.0.1: this computer only; "
                    "0.0.0.0: every network)"
                )
            else:
                why = e.strerror or str(e)
            raise ConfigError(f"{where}: {why}") from None
        self.state = state
        self.thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        shown = f"[{host}]" if ":" in host else host
        return f"http://{shown}:{port}/"

    def start(self) -> None:
        self.thread = threading.Thread(
            target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2},
            name="visvec-view", daemon=True,
        )  # fmt: skip
        self.thread.start()

    def stop(self) -> None:
        if self.thread is not None:
            self.httpd.shutdown()
            self.thread.join(timeout=2.0)
        self.httpd.server_close()
