"""The live view (--serve): its server's routes and refusals, and the page itself in
headless Chromium against a `batch --serve` replay (skipped without a browser)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from visvec.errors import ConfigError
from visvec.view import parse_address
from visvec.view.words import in_words

from conftest import ROOT, wait_until

RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = sorted((ROOT / "data" / "sample_frames").glob("*.png"))
FRAME_GAP_S = 0.4  # the replay's pace: long enough to watch a frame change


def test_parse_address():
    assert parse_address("8080") == ("127.0.0.1", 8080)  # this computer only by default
    assert parse_address("0.0.0.0:80") == ("0.0.0.0", 80)
    assert parse_address("[::1]:0") == ("::1", 0)
    for bad in ("http", "70000", "host:", "-1"):
        with pytest.raises(ConfigError, match=f"^address '{bad}'"):
            parse_address(bad)
        with pytest.raises(ConfigError, match=f"^--serve '{bad}'"):  # as the caller names it
            parse_address(bad, "--serve")


def test_the_view_keeps_a_minute_of_rows_and_a_poll_gets_the_new_ones():
    """Ten minutes of a 100 Hz IMU's fused rows and 30 fps camera rows: the state keeps
    only the last minute of each (what the page plots), so that a page opened late (a
    first poll, since 0) gets one minute, not ten; a poll since its last seq gets
    exactly the rows that came after it, oldest first; the answer's JSON is what one
    json.dumps gives."""
    from visvec.data import Frame, Status
    from visvec.output import AttitudeRow
    from visvec.rig import load_rig
    from visvec.view.state import WINDOW_S, ViewState

    state = ViewState(load_rig(RIG), ["yaw_deg"], ["sigma_yaw_deg"])
    for k in range(60_000):  # 600 s at 100 Hz, a camera row every third
        t = k / 100.0
        state.fused({"frame": k, "time_s": t, "status": "ok"})
        if k % 3 == 0:
            row = AttitudeRow(k // 3, t, Status.OK, 0.2, 3, 1.0, (), euler_deg=np.ones(3),
                              sigma_deg=np.full(3, 0.01))  # fmt: skip
            state.see(Frame(k // 3, t, None), row, None)
    assert len(state._fused) == int(WINDOW_S * 100) + 1
    assert len(state._hist) == int(WINDOW_S * 100 / 3) + 1
    first = state.snapshot(0)
    assert len(first["fused"]) == int(WINDOW_S * 100) + 1
    assert first["fused"][0]["time_s"] == pytest.approx(599.99 - WINDOW_S)
    assert first["fused"][-1]["time_s"] == pytest.approx(599.99)
    # the answer is encoded a chunk of rows at a time (the sensor's threads run between
    # chunks), the same bytes as one json.dumps
    from visvec.view.server import state_json

    assert state_json(first) == json.dumps(first, allow_nan=False).encode()
    seq = first["seq"]
    for k in range(60_000, 60_025):
        state.fused({"frame": k, "time_s": k / 100.0, "status": "ok"})
    new = state.snapshot(seq)
    assert [d["frame"] for d in new["fused"]] == list(range(60_000, 60_025))
    assert new["history"] == []
    assert state.snapshot(new["seq"])["fused"] == []


def recording(folder: Path) -> Path:
    """The sample frames, then one frame with no target, FRAME_GAP_S apart."""
    folder.mkdir()
    names = []
    for i, p in enumerate(SAMPLES):
        names.append(f"f{i:03d}.png")
        shutil.copy(p, folder / names[-1])
    blank = np.full(cv2.imread(str(SAMPLES[0]), cv2.IMREAD_GRAYSCALE).shape, 128, np.uint8)
    names.append(f"f{len(SAMPLES):03d}.png")
    cv2.imwrite(str(folder / names[-1]), blank)
    with open(folder / "times.csv", "w") as fh:
        fh.write("file,time_s\n")
        for i, n in enumerate(names):
            fh.write(f"{n},{i * FRAME_GAP_S:.3f}\n")
    return folder


class Served:
    """`visvec batch REC --serve 0` in a subprocess; its address read from stderr."""

    def __init__(self, rec: Path, out: Path, *extra: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "visvec", "batch", str(rec), "--rig", str(RIG),
             "--out", str(out), "--serve", "0", "--keep-view", *extra],
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.err: list[str] = []
        deadline = time.monotonic() + 30
        self.url = None
        while self.url is None and time.monotonic() < deadline:
            line = self.proc.stderr.readline()
            if not line:
                break
            self.err.append(line)
            if "live view at " in line:
                self.url = line.split("live view at ")[1].strip()
        assert self.url, "".join(self.err)

    def get(self, path: str) -> tuple[int, dict, bytes]:
        try:
            with urllib.request.urlopen(self.url + path.lstrip("/"), timeout=5) as r:
                return r.status, dict(r.headers), r.read()
        except urllib.error.HTTPError as e:
            return e.code, dict(e.headers), e.read()

    def stop(self) -> int:
        """Ctrl-C: the page's linger ends, exit 0."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            rest = self.proc.communicate(timeout=15)[1]
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rest = self.proc.communicate()[1]
        self.err.append(rest)
        return self.proc.returncode

    def wait_ended(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if json.loads(self.get("/api/state")[2])["run"]["ended"]:
                    return
            except OSError:
                pass  # turned away while the server is at its connection limit
            time.sleep(0.1)
        raise AssertionError("the run did not end")


def rows_of(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # 7-8 s: the default run stays under 5 minutes
def test_server_serves_its_page_and_data_only(tmp_path):
    rec = recording(tmp_path / "rec")
    srv = Served(rec, tmp_path / "rows.csv")
    try:
        srv.wait_ended()
        code, head, body = srv.get("/")
        assert code == 200 and b"visvec live view" in body
        assert srv.get("/uPlot.iife.min.js")[0] == 200  # the plots ship in the package
        code, head, body = srv.get("/api/state")
        st = json.loads(body)
        rows = rows_of(tmp_path / "rows.csv")
        assert st["run"]["rows"] == len(rows) == len(SAMPLES) + 1
        assert st["run"]["ok"] == sum(r["status"] == "ok" for r in rows) == len(SAMPLES)
        assert [h["frame"] for h in st["history"]] == [int(r["frame"]) for r in rows]
        # the last frame (no target) is not ok, and said in words
        assert st["last"]["status"] == rows[-1]["status"] != "ok"
        assert st["last"]["words"] == in_words(rows[-1]["status"], rows[-1]["warnings"])
        assert "_" not in st["last"]["words"]
        code, head, body = srv.get("/frame.jpg")
        assert code == 200 and head["Content-Type"] == "image/jpeg"
        img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[1] >= 640
        assert head["X-Visvec-Frame"] == str(len(SAMPLES))
        # nothing else: no file from disk, nothing writable
        assert srv.get("/../pyproject.toml")[0] == 404
        assert srv.get("/static/view.js")[0] == 404
        req = urllib.request.Request(srv.url + "api/state", data=b"x", method="POST")
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(req, timeout=5)
        assert e.value.code in (405, 501)
        # a later poll gets only the rows after the ones it has
        later = json.loads(srv.get(f"/api/state?since={st['seq']}")[2])
        assert later["history"] == [] and later["run"]["rows"] == len(rows)
    finally:
        assert srv.stop() == 0
    assert "stays at" in "".join(srv.err)


def test_port_in_use_is_refused_before_the_camera_opens(tmp_path):
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen(1)
    port = taken.getsockname()[1]
    try:
        r = subprocess.run(
            [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera",
             str(tmp_path / "no-such-video.avi"), "--serve", str(port)],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    finally:
        taken.close()
    assert r.returncode == 2, r.stderr
    assert f"127.0.0.1:{port}" in r.stderr and "in use" in r.stderr
    assert "no-such-video" not in r.stderr  # refused before the camera was opened


@pytest.mark.slow  # 4-7 s: the default run stays under 5 minutes
def test_many_browsers_do_not_stop_the_rows(tmp_path):
    """Forty clients polling as fast as they can while a replay runs: every row is
    written, each once, and the run ends on time."""
    import http.client
    import threading

    rec = recording(tmp_path / "rec")
    out = tmp_path / "rows.csv"
    t0 = time.monotonic()
    srv = Served(rec, out)
    stop = threading.Event()

    def hammer():
        while not stop.is_set():
            for path in ("/frame.jpg", "/api/state", "/"):
                try:
                    srv.get(path)
                except (OSError, http.client.HTTPException):
                    # refused beyond the connection limit, or cut off mid-answer as the
                    # run ends: fine
                    pass

    clients = [threading.Thread(target=hammer, daemon=True) for _ in range(40)]
    for c in clients:
        c.start()
    try:
        srv.wait_ended()
        took = time.monotonic() - t0
    finally:
        stop.set()
        assert srv.stop() == 0
    rows = rows_of(out)
    assert [int(r["frame"]) for r in rows] == list(range(len(SAMPLES) + 1))
    # the replay's own length plus the start-up, not more
    assert took < len(SAMPLES) * FRAME_GAP_S + 10.0


def _browser():
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("no Chromium and chromedriver installed (Debian: chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    args = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--window-size=1300,1000")  # fmt: skip
    for a in args:
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(driver), options=opts)


READ_PAGE = """
const values = {};
for (const tr of document.querySelectorAll('#values tr'))
  values[tr.dataset.col] = tr.cells[1].textContent;
return {frame: document.body.dataset.frame || '',
        status: document.getElementById('status').dataset.status || '',
        rowframe: document.getElementById('rowframe').textContent,
        runstate: document.getElementById('runstate').textContent, values: values};
"""


@pytest.mark.slow  # 11 s on a slow host
def test_page_in_a_real_browser(tmp_path):
    from selenium.webdriver.common.by import By

    browser = _browser()
    rec = recording(tmp_path / "rec")
    out = tmp_path / "rows.csv"
    srv = Served(rec, out)
    seen_frames: set[str] = set()
    shown: dict[int, dict[str, str]] = {}
    try:
        browser.get(srv.url)
        deadline = time.monotonic() + 30
        ended = False
        while time.monotonic() < deadline and not ended:
            # read in one script: the page rebuilds its table on every poll
            got = browser.execute_script(READ_PAGE)
            if got["frame"]:
                seen_frames.add(got["frame"])
            if got["status"] == "ok" and got["rowframe"][:1].isdigit():
                shown[int(got["rowframe"].split()[0])] = got["values"]
            ended = got["runstate"] == "run ended"
            time.sleep(0.1)
        assert ended
        # the page's last poll after the end: every row plotted, the last frame shown
        n_rows = len(rows_of(out))

        def caught_up() -> bool:
            body = browser.find_element(By.TAG_NAME, "body")
            last_frame = browser.execute_script(READ_PAGE)["frame"]
            return body.get_attribute("data-points") == str(n_rows) and last_frame == str(
                len(SAMPLES)
            )

        wait_until(caught_up, "the page showing the last frame and every row", timeout=15)
        seen_frames.add(browser.execute_script(READ_PAGE)["frame"])
        # the frame updated as the replay went on, up to the last one
        assert len(seen_frames) >= 2, seen_frames
        assert str(len(SAMPLES)) in seen_frames, seen_frames
        # the values shown are the rows written
        rows = {int(r["frame"]): r for r in rows_of(out)}
        assert shown
        for frame, vals in shown.items():
            for col, text in vals.items():
                assert float(text) == pytest.approx(float(rows[frame][col]), abs=1e-9)
        # the plots have points
        assert int(browser.find_element(By.TAG_NAME, "body").get_attribute("data-points")) == len(
            rows
        )
        assert len(browser.find_elements(By.CSS_SELECTOR, "#plots canvas")) == 3
        # the last frame has no target: its status in words
        status = browser.find_element(By.ID, "status")
        last = rows[max(rows)]
        assert status.get_attribute("data-status") == last["status"] != "ok"
        assert status.text == in_words(last["status"], last["warnings"])
        assert "rig: " in browser.find_element(By.ID, "info").text
        shot = tmp_path / "live-view.png"
        browser.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000
        if os.environ.get("VISVEC_SCREENSHOT"):
            shutil.copy(shot, os.environ["VISVEC_SCREENSHOT"])
    finally:
        browser.quit()
        assert srv.stop() == 0


@pytest.mark.slow  # 6 s: the default run stays near 3 minutes
def test_a_served_recording_ends_with_its_run(tmp_path):
    """`batch REC --serve 0` without --keep-view: the run ends by itself (a script that
    adds --serve is not held up), exit 0, the view said stopped, its port free again."""
    rec = recording(tmp_path / "rec")
    p = subprocess.run(
        [sys.executable, "-m", "visvec", "batch", str(rec), "--rig", str(RIG), "--out",
         str(tmp_path / "rows.csv"), "--serve", "0"], capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "and so has the live view" in p.stderr and "--keep-view" in p.stderr
    url = p.stderr.split("live view at ")[1].split()[0]
    port = int(url.rstrip("/").rsplit(":", 1)[1])
    with socket.socket() as s:  # the port is free again
        s.bind(("127.0.0.1", port))
