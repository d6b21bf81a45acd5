"""`track` as a service (deploy/visvec-track.service): the unit file that systemd reads,
and what it relies on: a camera that disappears ends the run with a failure, which the
unit restarts, while a stop (SIGTERM) ends it cleanly, which it does not. systemd does
not run in the tests: its restart rule is played by the test, with the unit's own
command line (its paths and ports put where the test has them)."""

from __future__ import annotations

import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest
from mjpeg import MjpegServer

from conftest import ROOT

UNIT = ROOT / "deploy" / "visvec-track.service"
RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = sorted((ROOT / "data" / "sample_frames").glob("*.png"))


def unit() -> dict[str, dict[str, str]]:
    """The unit's sections and keys (a key given twice: its last value), continuation
    lines joined, as systemd reads them."""
    out: dict[str, dict[str, str]] = {}
    section = None
    text = UNIT.read_text().replace("\\\n", " ")
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = out.setdefault(line.strip("[]"), {})
            continue
        key, _, value = line.partition("=")
        section[key.strip()] = value.strip()
    return out


def test_the_unit_restarts_on_failure_and_not_on_a_refused_rig():
    u = unit()
    s = u["Service"]
    assert s["Restart"] == "on-failure"
    assert "2" in s["RestartPreventExitStatus"].split()  # a refused rig: no restart loop
    assert s["KillSignal"] == "SIGTERM"
    assert u["Unit"]["StartLimitIntervalSec"] == "0"
    args = shlex.split(s["ExecStart"])
    assert args[0].endswith("/visvec") and "track" in args
    # the live view and Foxglove on this computer only, unless the lab decides
    for opt in ("--serve", "--foxglove"):
        assert args[args.index(opt) + 1].startswith("127.0.0.1:")
    assert u["Install"]["WantedBy"] == "multi-user.target"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_systemd_reads_the_unit(tmp_path):
    """systemd's own check of the unit, its visvec put where this machine has one."""
    text = UNIT.read_text().replace("/opt/visvec/bin/visvec", sys.executable)
    (tmp_path / "visvec-track.service").write_text(text)
    r = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "visvec-track.service")],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Unknown key" not in r.stderr and "ignoring" not in r.stderr, r.stderr


class Camera(MjpegServer):
    """A network camera that can go away and come back: while ``away`` it closes every
    stream after ``frames`` frames and answers no new one."""

    def __init__(self, frames: int):
        self.frames = frames
        self.away = threading.Event()
        super().__init__()

    def refuse(self, nth: int) -> bool:
        return self.away.is_set()

    def ends(self, nth: int, i: int) -> bool:
        return self.away.is_set() and i >= self.frames


def _command(camera_url: str) -> list[str]:
    """The unit's ExecStart with this machine's visvec and the test's rig, camera and
    free ports (its options and their values otherwise as written)."""
    args = shlex.split(unit()["Service"]["ExecStart"])
    args = [sys.executable, "-m", "visvec", *args[1:]]
    swap = {"/etc/visvec/lab.toml": str(RIG), "127.0.0.1:8080": "127.0.0.1:0",
            "127.0.0.1:8765": "127.0.0.1:0", "10": "1"}  # fmt: skip
    args = [swap.get(a, a) for a in args]
    k = args.index("--calibration")  # the lab's zero-tilt file: none here
    del args[k : k + 2]
    try:
        import foxglove  # noqa: F401
    except ImportError:  # (the foxglove extra not installed)
        k = args.index("--foxglove")
        del args[k : k + 2]
    return [*args, "--camera", camera_url]


@pytest.mark.slow  # two runs of track: 8-12 s
def test_a_camera_that_disappears_is_restarted_and_a_stop_is_clean(tmp_path):
    """The unit's command on a network camera: when the camera goes away the run ends
    with exit 3 after --retry-s (a failure: systemd starts it again after RestartSec);
    started again with the camera back, it runs until SIGTERM (systemctl stop), then
    writes its summary and exits 0 (no restart)."""
    restart_s = float(unit()["Service"]["RestartSec"])
    prevent = {int(x) for x in unit()["Service"]["RestartPreventExitStatus"].split()}
    cam = Camera(frames=20)
    codes, logs = [], []
    try:
        cam.away.set()  # the first run sees 20 frames, then the camera is gone
        first = subprocess.run(_command(cam.url), capture_output=True, text=True, timeout=60)
        codes.append(first.returncode)
        logs.append(first.stderr)
        # Restart=on-failure: a non-zero exit not in RestartPreventExitStatus
        assert first.returncode != 0 and first.returncode not in prevent, first.stderr
        cam.away.clear()  # the camera is back
        time.sleep(restart_s)
        proc = subprocess.Popen(_command(cam.url), stderr=subprocess.PIPE, text=True)
        seen = []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            seen.append(line)
            if "frame" in line and ("frames/s" in line or "%" in line):
                break  # frames are flowing (a status line)
            if not line:
                break
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)  # systemctl stop
        err = "".join(seen) + proc.communicate(timeout=30)[1]
        codes.append(proc.returncode)
        logs.append(err)
    finally:
        cam.close()
    assert codes[0] == 3, logs[0]
    assert "--retry-s" in logs[0]
    assert codes[1] == 0, logs[1]  # a clean stop: systemd does not restart it
    assert "ok (" in logs[1]  # the closing summary, logged
    assert "live view at http://127.0.0.1:" in logs[1]
