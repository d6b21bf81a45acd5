"""Shared bits of the benchmark scripts: output folder, JSON, figure helpers."""

from __future__ import annotations

import csv
import json
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"
CONFIGS = ROOT / "configs"


def save_json(name: str, data: dict) -> Path:
    OUT.mkdir(exist_ok=True)
    p = OUT / f"{name}.json"
    p.write_text(json.dumps(data, indent=2))
    return p


def command() -> str:
    return "python " + " ".join(
        [
            str(Path(sys.argv[0]).relative_to(ROOT))
            if Path(sys.argv[0]).is_absolute()
            else sys.argv[0],
            *sys.argv[1:],
        ]
    )


def add_refine_option(ap) -> None:
    """--refine: the triangle rig's [detect] refine for the run."""
    ap.add_argument(
        "--refine",
        choices=("lines", "pixels"),
        default="lines",
        help="the rig's [detect] refine (pixels: the edges fitted to the pixels)",
    )


def run_record() -> dict:
    """What every result file starts with: the command, the machine and the date."""
    from visvec.bench.triangle import machine

    return {"command": command(), "machine": machine(), "date": time.strftime("%Y-%m-%d")}


def summarise(out) -> dict:
    """An Outcome's summary with the RMS of error/sigma per axis (ok rows)."""
    s = out.summary()
    if out.n_ok:
        z = np.array(out.err_deg) / np.array(out.sigma_deg)
        rms = np.sqrt(np.mean(z**2, axis=0)).round(2).tolist()
        s["z_rms"] = dict(zip(("yaw", "pitch", "roll"), rms, strict=True))
    return s


def pyplot():
    """matplotlib's pyplot drawing to files (no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 free now (for a sensor's --imu udp://...)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class UdpRows:
    """The CSV rows a sensor sends to udp://127.0.0.1:``port`` (its --out), received in
    a daemon thread: ``on_row(arrival, fields)`` for each row after the header, which
    ``header`` holds once it came, and ``col`` each column's index (arrival:
    time.monotonic())."""

    def __init__(self, on_row: Callable[[float, list[str]], None]):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.settimeout(0.5)
        self.port = self.sock.getsockname()[1]
        self.header: list[str] = []
        self.col: dict[str, int] = {}
        self._on_row = on_row
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            now = time.monotonic()
            fields = next(csv.reader([data.decode()]))
            if fields[0] == "frame":
                self.header[:] = fields
                self.col = {c: i for i, c in enumerate(fields)}
            elif self.header:
                self._on_row(now, fields)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()
