"""A camera pipeline as the live source of fixes: `visvec track --imu`."""

import csv
import math
import time

import numpy as np
import pytest
from click.testing import CliRunner
from fusion_cases import (
    _free_udp_port,
    _send_paced,
    truth_table,
)

from visvec.cli.main import cli
from visvec.output import PLANAR_COLUMNS
from visvec.rotations import logmap


def _track_live(tmp_path, rig, sim_args, n_frames, serve=False, foxglove=None, extra=()):
    """`track --imu` on a simulated recording played at its own pace, the recording's
    imu.csv sent over UDP at its real rate by this thread: (fused rows, camera rows,
    IMU samples sent, stderr). With ``serve``, a live view too: the stderr has the
    live page's last state as JSON appended, read before the run is ended by Ctrl-C."""
    import socket
    import subprocess
    import sys
    import time

    rec = tmp_path / "rec"
    r = CliRunner().invoke(cli, ["simulate", "--rig", str(rig), "--out", str(rec), "--frames",
                                 str(n_frames), "--imu", *sim_args])  # fmt: skip
    assert r.exit_code == 0, r.output
    port = _free_udp_port()
    out, cam = tmp_path / "fused.csv", tmp_path / "camera.csv"
    if foxglove is not None:
        # imported before the run starts: on a loaded machine the imports alone took the
        # client past the camera's 45 frames (1.5 s), whose rows nobody watched then
        import websockets.sync.client  # noqa: F401
        from foxglove_client import Client
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "track", "--rig", str(rig), "--camera", str(rec),
         "--realtime", "--imu", f"udp://127.0.0.1:{port}", "--out", str(out), "--camera-out",
         str(cam), *(["--serve", "0", "--keep-view"] if serve else []),
         *(["--foxglove", "127.0.0.1:0"] if foxglove is not None else []), *extra],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    url = None
    try:
        deadline = time.monotonic() + 30
        got = set()
        t0 = None
        while len(got) < 2 and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if "live view at " in line:
                url = line.split("live view at ")[1].strip()
            if foxglove is not None and "Foxglove live at ws://" in line:
                # a client that subscribes to every channel as it is advertised
                fox_port = int(line.split("ws://127.0.0.1:")[1].split()[0])
                foxglove.append(Client(fox_port, auto=True))
            got |= {w for w in ("listening", "first frame") if w in line}
            if "first frame" in line:
                # the camera's first frame on this machine's monotonic clock: the IMU
                # samples are sent on the same time base, as a live IMU would be
                t0 = float(line.split("clock ")[1].split(" s)")[0])
        assert got == {"listening", "first frame"}
        lines = (rec / "imu.csv").read_text().splitlines()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(lines[0].encode(), ("127.0.0.1", port))
            _send_paced(s, lines[1:], port, t0)
        state = None
        if serve:
            import json
            import signal
            import urllib.request

            assert url, "no live view address"
            while time.monotonic() < deadline + 30:
                with urllib.request.urlopen(url + "api/state", timeout=5) as resp:
                    state = json.loads(resp.read())
                if state["run"]["ended"]:
                    break
                time.sleep(0.2)
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        if state is not None:
            err += "\n" + json.dumps(state)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    with open(cam) as fh:
        cam_rows = list(csv.DictReader(fh))
    assert len(cam_rows) == n_frames and "row latency median" in err
    return rows, cam_rows, len(lines) - 1, rec, err


@pytest.mark.slow  # 8-9 s: the default run stays under 5 minutes
def test_track_with_imu_lamps_live(tmp_path):
    """A lamps recording played as a camera at its own pace while a thread sends the
    matching IMU samples over UDP at 100 Hz in real time: `track --imu` writes fused
    rows at the IMU's rate within 5 mm of the truth, and the camera's own rows."""
    from conftest import ROOT

    rows, cam_rows, n_imu, rec, err = _track_live(
        tmp_path, ROOT / "configs" / "lamps.toml", ["--motion", "perimeter"], 120
    )
    # at the end, what the filter learned: the camera's time offset first
    assert "learned: fixes' time offset" in err, err
    assert sum(r["status"] == "ok" for r in cam_rows) > 80
    assert len(rows) > 0.9 * n_imu
    assert list(rows[0]) == list(PLANAR_COLUMNS)
    tt = truth_table(rec / "imu_truth.csv")
    # the filter itself starts once it has aligned the camera's clock with the IMU's
    # (from their headings, 1-2 s: two tries in a row find the same offset); the rows
    # before are provisional, from the first fix on: they say so, and their sigma holds
    # their error (the pose's rate times the offsets the alignment allows)
    first = next(i for i, r in enumerate(rows)
                 if r["status"] == "ok" and "aligning_clocks" not in r["warnings"])  # fmt: skip
    assert 0 < first < 0.6 * len(rows)
    assert all("aligning_clocks" in r["warnings"] for r in rows[first - 10 : first])
    provisional = [r for r in rows[:first] if r["status"] == "ok"]
    assert provisional  # the rows do not wait for the alignment
    for r in provisional:
        for k, col in ((0, "x"), (1, "y")):
            err = abs(float(r[f"{col}_mm"]) - tt[int(r["frame"]), k])
            assert err < 5.0 * float(r[f"sigma_{col}_mm"]), (r["frame"], col, err)
    ok = [r for r in rows[first:] if r["status"] == "ok"]
    assert len(ok) > 0.95 * len(rows[first:])
    e = [math.hypot(float(r["x_mm"]) - tt[int(r["frame"]), 0],
                    float(r["y_mm"]) - tt[int(r["frame"]), 1]) for r in ok]  # fmt: skip
    assert np.sqrt(np.mean(np.square(e))) < 5.0, np.sqrt(np.mean(np.square(e)))


def test_track_with_imu_live_view(tmp_path):
    """`track --imu --serve`: the live page has the camera's rows and the fused ones,
    each exactly as written."""
    import json

    from conftest import ROOT

    rows, cam_rows, n_imu, rec, err = _track_live(
        tmp_path, ROOT / "configs" / "lamps.toml", ["--motion", "perimeter"], 30, serve=True
    )
    state = json.loads(err.rstrip().splitlines()[-1])
    assert [h["frame"] for h in state["history"]] == [int(r["frame"]) for r in cam_rows]
    fused = state["fused"]
    # the page keeps the last minute of the fused rows: all of this short run's
    assert len(fused) == len(rows) > 0.9 * n_imu
    for f, r in zip(fused, rows, strict=True):
        assert f["status"] == r["status"] and f["frame"] == int(r["frame"])
        if r["status"] == "ok":
            assert f["x_mm"] == pytest.approx(float(r["x_mm"]), abs=1e-9)
    assert state["run"]["ended"] and state["values"] == ["x_mm", "y_mm", "heading_deg"]


@pytest.mark.slow  # 12 s on a slow host
def test_track_with_imu_triangle_live(tmp_path):
    """The same for an attitude rig: a triangle sweep at 20 deg/s with a 3-D gyro over
    UDP; the fused attitude within 0.05 deg of the truth at every IMU sample, and
    within 3 sigma on nearly every row."""
    from visvec.rotations import quat_to_matrix

    from conftest import ROOT

    rows, cam_rows, n_imu, rec, _ = _track_live(
        tmp_path, ROOT / "configs" / "triangle.toml",
        ["--motion", "sweep", "--yaw-rate-dps", "20"], 60,
    )  # fmt: skip
    assert sum(r["status"] == "ok" for r in cam_rows) > 55
    assert len(rows) > 0.9 * n_imu
    with open(rec / "imu_truth.csv") as fh:
        truth = [quat_to_matrix(np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]))
                 for r in csv.DictReader(fh)]  # fmt: skip
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) > 0.8 * len(rows)
    e = []
    for r in ok:
        Rf = quat_to_matrix(np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]))
        e.append(np.degrees(np.linalg.norm(logmap(truth[int(r["frame"])].T @ Rf))))
    assert np.sqrt(np.mean(np.square(e))) < 0.05, np.sqrt(np.mean(np.square(e)))


def test_a_frame_found_late_after_its_row_is_no_fix():
    """The reader may learn that a frame waited only after it was handed out (it was
    read when the hold-up ended, and the next came at once): CameraFixes asks again
    when it would send the fix, so a frame found late while its row was written is no
    fix, though its row (already out) is ok without the warning."""
    import queue
    import threading

    from visvec.data import Frame
    from visvec.fuse.camera import CameraFixes

    class Row:
        ok = True

        def __init__(self, frame):
            self.warnings = "read_late" if frame.late else ""

        def as_dict(self):
            return {"time_s": "0", "status": "ok", "warnings": self.warnings}

    class Pipe:
        def process(self, frame):
            return Row(frame)

    flags = [threading.Event() for _ in range(4)]
    flags[1].set()  # late before its row

    class Sink:  # writing frame 2's row, the reader learns that frame 2 waited
        def __init__(self):
            self.rows = []

        def write(self, d):
            self.rows.append(d)
            if len(self.rows) == 3:
                flags[2].set()

    frames = [Frame(k, k / 30.0, np.zeros((2, 2), np.uint8), read_late=flags[k]) for k in range(4)]
    events = queue.Queue()
    sink = Sink()
    cam = CameraFixes(frames, Pipe(), events, sink=sink)
    cam.run()
    fixes = []
    while not events.empty():
        e = events.get()
        if e.kind == "fix":
            fixes.append(e)
    assert [r["warnings"] for r in sink.rows] == ["", "read_late", "", ""]
    assert len(fixes) == 2 and cam.n_ok == 2


@pytest.mark.slow  # 8 s
def test_track_with_imu_in_foxglove(tmp_path):
    """`track --imu --foxglove`: a Foxglove client sees the fused rows under /visvec and
    the camera's under /visvec/camera, each message its row's (the CSV outputs)."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websockets")
    from conftest import ROOT

    clients: list = []
    rows, cam_rows, n_imu, rec, err = _track_live(
        tmp_path, ROOT / "configs" / "triangle.toml", ["--motion", "sweep"], 45, foxglove=clients
    )
    time.sleep(0.3)
    (client,) = clients
    client.close()
    assert "Foxglove /visvec: " in err and "Foxglove /visvec/camera: " in err
    topics = {ch["topic"] for ch in client.channels.values()}
    assert {"/visvec/attitude", "/visvec/status", "/visvec/camera/attitude",
            "/visvec/camera/status", "/visvec/camera/overlay/compressed"} <= topics  # fmt: skip
    for topic, table in (("/visvec", rows), ("/visvec/camera", cam_rows)):
        by_frame = {int(r["frame"]): r for r in table}
        st = client.decoded(topic + "/status", "diagnostic_msgs/msg/DiagnosticArray")
        imu = client.decoded(topic + "/attitude", "sensor_msgs/msg/Imu")
        assert len(st) > 0.5 * len(table), (topic, len(st), len(table))
        frames = [int({kv.key: kv.value for kv in a.status[0].values}["frame"]) for a in st]
        assert [a.status[0].message for a in st] == [by_frame[f]["status"] for f in frames]
        ok = [f for f, a in zip(frames, st, strict=True) if a.status[0].message == "ok"]
        assert len(imu) == len(ok) > 0
        for f, m in zip(ok, imu, strict=True):
            q = m.orientation
            np.testing.assert_allclose(
                [q.w, q.x, q.y, q.z], [float(by_frame[f][k]) for k in ("qw", "qx", "qy", "qz")]
            )


def _same_but_latency(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b) > 0
    for x, y in zip(a, b, strict=True):
        x, y = dict(x), dict(y)
        x.pop("latency_ms"), y.pop("latency_ms")
        assert x == y, (x, y)


@pytest.mark.slow  # 8 s
def test_a_recorded_live_run_replays_to_its_own_rows(tmp_path):
    """`track --imu --record DIR` on a camera stream with an IMU over UDP keeps the run;
    `batch DIR` gives its fused rows and its camera's rows again, every column but
    latency_ms; a replay with another rig says so before the first row, and a folder
    that holds a recording is not recorded over."""
    from conftest import ROOT, run

    rig = ROOT / "configs" / "triangle.toml"
    rec = tmp_path / "flight"
    rows, cam_rows, n_imu, _, err = _track_live(
        tmp_path, rig, ["--motion", "sweep", "--yaw-rate-dps", "20"], 45,
        extra=["--record", str(rec)],
    )  # fmt: skip
    assert f"recorded in {rec}" in err
    for name in ("rig.toml", "recording.json", "events.jsonl", "imu.csv", "times.csv",
                 "rows.csv", "camera.csv"):  # fmt: skip
        assert (rec / name).is_file(), name
    assert len(list(rec.glob("frame_*.png"))) == len(cam_rows)
    replay, cam_replay = tmp_path / "replay.csv", tmp_path / "replay_camera.csv"
    r = run("batch", rec, "--rig", rig, "--out", replay, "--camera-out", cam_replay)
    assert r.exit_code == 0, r.output
    assert "not the one recorded" not in r.output

    def rows_of(p):
        with open(p) as fh:
            return list(csv.DictReader(fh))

    _same_but_latency(rows_of(cam_replay), cam_rows)
    _same_but_latency(rows_of(replay), rows)
    _same_but_latency(rows_of(rec / "rows.csv"), rows)
    # another rig: said before the first row
    other = tmp_path / "other.toml"
    other.write_text(rig.read_text().replace("fps = 30.0", "fps = 25.0"))
    r = run("batch", rec, "--rig", other, "--out", tmp_path / "other.csv")
    assert r.exit_code == 0 and "is not the one recorded" in r.output, r.output
    # a folder that holds a recording: refused before the camera opens
    r = run(
        "track",
        "--rig",
        rig,
        "--camera",
        tmp_path / "rec",
        "--record",
        rec,
        "--out",
        tmp_path / "x.csv",
    )
    assert r.exit_code == 2 and "already holds a recording" in r.output


def test_a_recorded_camera_run_replays_to_its_own_rows(tmp_path):
    """`track --record DIR` without an IMU: the frames with their times, numbers and
    read-late flags, the rig, the rows; `batch DIR` gives the run's rows again."""
    from conftest import ROOT, run

    rig = ROOT / "configs" / "triangle.toml"
    sim = tmp_path / "sim"
    assert run("simulate", "--rig", rig, "--out", sim, "--frames", 20, "--motion",
               "sweep").exit_code == 0  # fmt: skip
    rec, live, replay = tmp_path / "flight", tmp_path / "live.csv", tmp_path / "replay.csv"
    r = run("track", "--rig", rig, "--camera", sim, "--record", rec, "--out", live)
    assert r.exit_code == 0, r.output
    assert f"recorded in {rec}: 20 frames" in r.output
    assert (rec / "recording.json").is_file() and (rec / "rig.toml").read_bytes() == (
        rig.read_bytes()
    )
    r = run("batch", rec, "--rig", rig, "--out", replay)
    assert r.exit_code == 0, r.output

    def rows_of(p):
        with open(p) as fh:
            return list(csv.DictReader(fh))

    assert len(rows_of(live)) == 20
    _same_but_latency(rows_of(replay), rows_of(live))
    _same_but_latency(rows_of(rec / "rows.csv"), rows_of(live))


def test_a_recording_is_begun_only_once_the_camera_opens(tmp_path):
    """A camera that cannot be opened (exit 3) leaves no recording: the same --record
    folder is taken on the next try."""
    from conftest import ROOT, run

    rig = ROOT / "configs" / "triangle.toml"
    rec = tmp_path / "flight"
    r = run("track", "--rig", rig, "--camera", tmp_path / "no_such.avi", "--record", rec)
    assert r.exit_code == 3
    assert not (rec / "recording.json").exists()
    sim = tmp_path / "sim"
    assert run("simulate", "--rig", rig, "--out", sim, "--frames", 3).exit_code == 0
    r = run("track", "--rig", rig, "--camera", sim, "--record", rec, "--out", tmp_path / "r.csv")
    assert r.exit_code == 0, r.output
    assert (rec / "recording.json").is_file() and len(list(rec.glob("frame_*.png"))) == 3
