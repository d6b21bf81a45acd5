"""Rows live in Foxglove (--foxglove): a WebSocket client that speaks Foxglove's
protocol subscribes, decodes the messages and compares them with the rows and with
what the MCAP output holds for the same rows (the same topics, schemas and bytes: a
layout made on a recorded file works live). Servers bind 127.0.0.1 and stop with the
test."""

from __future__ import annotations

import csv
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("rosbags")
pytest.importorskip("websockets")

from foxglove_client import Client

from conftest import ROOT, run

RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = ROOT / "data" / "sample_frames"


def _rows(n: int = 6) -> list[dict]:
    """Real attitude rows: the sample frames through the pipeline."""
    from visvec.data import Frame
    from visvec.imageio import read_image
    from visvec.pipeline import make_pipeline
    from visvec.rig import load_rig

    rig = load_rig(RIG)
    pipe = make_pipeline(rig, None)
    files = sorted(SAMPLES.glob("*.png"))[:n]
    rows = [pipe.process(Frame(i, i / 30.0, read_image(f))).as_dict() for i, f in enumerate(files)]
    rows[-1] = {**rows[-1], "status": "no_target", "warnings": "no_triangle"}
    return rows


def test_rows_reach_a_subscribed_client_as_the_mcap_output_holds_them(tmp_path):
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    from visvec.output import ATTITUDE_COLUMNS
    from visvec.sinks.foxglove import FoxgloveLive, FoxgloveServer
    from visvec.sinks.ros import McapSink

    rows = _rows()
    server = FoxgloveServer("127.0.0.1", 0)
    live = FoxgloveLive(server, ATTITUDE_COLUMNS, "rig.toml")
    live.advertise()
    client = Client(server.port)
    try:
        client.subscribe_all(wait_for=4)
        topics = {ch["topic"]: ch for ch in client.channels.values()}
        assert set(topics) == {"/visvec/attitude", "/visvec/attitude/quaternion",
                               "/visvec/status", "/visvec/overlay/compressed"}  # fmt: skip
        for r in rows:
            live.publish(r, (lambda: b"\xff\xd8jpeg\xff\xd9") if r["frame"] == 0 else None)
        deadline = time.monotonic() + 5
        while len(client.got) < 2 * 5 + 6 + 1 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        client.close()
        live.close()
        server.stop()
    # the same rows through the MCAP output, with the same start time
    mcap = tmp_path / "run.mcap"
    sink = McapSink(str(mcap), ATTITUDE_COLUMNS, "rig.toml")
    sink.t0 = live.t0
    for r in rows:
        sink.write(r)
    sink.image(rows[0]["time_s"], b"\xff\xd8jpeg\xff\xd9")
    sink.close()
    with open(mcap, "rb") as fh:
        reader = make_reader(fh)
        recorded = [(ch.topic, m.log_time, m.data, sc) for sc, ch, m in reader.iter_messages()]
    assert len(client.got) == len(recorded) == 2 * 5 + 6 + 1
    key = sorted  # the two may interleave topics differently within a row
    assert key((t, ns, data) for t, ns, data in client.got) == key(
        (t, ns, bytes(data)) for t, ns, data, _ in recorded
    )
    # the schemas a layout made on the file expects
    for topic, _, _, sc in recorded:
        assert topics[topic]["schemaName"] == sc.name
        assert topics[topic]["schemaEncoding"] == "ros2msg" == sc.encoding
        assert topics[topic]["schema"] == sc.data.decode()
        assert topics[topic]["encoding"] == "cdr"
    # a ROS 2 reader given only what the server advertised (the schema's text, as
    # Foxglove parses it): the MCAP library's ROS 2 decoder
    mcap_ros2 = pytest.importorskip("mcap_ros2.decoder")
    by_ros2 = {}
    for topic, _, data in client.got:
        ch = topics[topic]
        decode = mcap_ros2.generate_dynamic(ch["schemaName"], ch["schema"])[ch["schemaName"]]
        by_ros2.setdefault(topic, []).append(decode(data))
    ok_rows = [r for r in rows if r["status"] == "ok"]
    np.testing.assert_allclose(
        [[m.quaternion.w, m.quaternion.x, m.quaternion.y, m.quaternion.z]
         for m in by_ros2["/visvec/attitude/quaternion"]],
        [[r["qw"], r["qx"], r["qy"], r["qz"]] for r in ok_rows],
    )  # fmt: skip
    assert [m.status[0].message for m in by_ros2["/visvec/status"]] == [r["status"] for r in rows]
    # and the values are the rows'
    ts = get_typestore(Stores.ROS2_HUMBLE)
    quats = [ts.deserialize_cdr(d, "geometry_msgs/msg/QuaternionStamped").quaternion
             for t, _, d in client.got if t == "/visvec/attitude/quaternion"]  # fmt: skip
    ok = [r for r in rows if r["status"] == "ok"]
    np.testing.assert_allclose([[q.w, q.x, q.y, q.z] for q in quats],
                               [[r["qw"], r["qx"], r["qy"], r["qz"]] for r in ok])  # fmt: skip
    st = [ts.deserialize_cdr(d, "diagnostic_msgs/msg/DiagnosticArray").status[0]
          for t, _, d in client.got if t == "/visvec/status"]  # fmt: skip
    assert [s.message for s in st] == [r["status"] for r in rows]
    assert live.published == len(rows) and live.dropped == 0


def test_nothing_is_encoded_while_no_client_watches():
    from visvec.output import ATTITUDE_COLUMNS
    from visvec.sinks.foxglove import FoxgloveLive, FoxgloveServer

    server = FoxgloveServer("127.0.0.1", 0)
    live = FoxgloveLive(server, ATTITUDE_COLUMNS)
    live.advertise()
    try:
        made = []
        for r in _rows(3):
            live.publish(r, lambda: made.append(1) or b"x")
        time.sleep(0.3)
    finally:
        live.close()
        server.stop()
    assert live.published == 0 and made == []


def test_a_port_in_use_is_refused_before_the_source_opens(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = run(
            "batch",
            SAMPLES,
            "--rig",
            RIG,
            "--out",
            tmp_path / "r.csv",
            "--foxglove",
            f"127.0.0.1:{port}",
        )
    assert r.exit_code == 2
    assert f"--foxglove 127.0.0.1:{port}" in r.output
    assert not (tmp_path / "r.csv").exists()
    r = run("batch", SAMPLES, "--rig", RIG, "--foxglove", "localhost:http")
    assert r.exit_code == 2 and "[HOST:]PORT" in r.output


@pytest.mark.slow
def test_a_live_run_in_foxglove_beside_a_stalled_client(tmp_path):
    """`track --realtime` on a recording with --foxglove: a client that reads gets the
    rows as the CSV has them (each decoded message its row's), the overlays at the rate
    asked; a client that subscribes and never reads holds up no row."""
    from rosbags.typesys import Stores, get_typestore

    rec = tmp_path / "rec"
    assert (
        run("simulate", "--rig", RIG, "--out", rec, "--frames", 90, "--motion", "sweep").exit_code
        == 0
    )
    out = tmp_path / "rows.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera", str(rec),
         "--realtime", "--out", str(out), "--foxglove", "127.0.0.1:0",
         "--foxglove-image-hz", "2"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        port = None
        lines = []
        while port is None:
            line = proc.stderr.readline()
            assert line, "".join(lines)
            lines.append(line)
            if "Foxglove live at ws://" in line:
                port = int(line.split("ws://127.0.0.1:")[1].split()[0])
        stalled = Client(port, read=False)
        reader = Client(port)
        stalled.subscribe_all(wait_for=4)
        reader.subscribe_all(wait_for=4)
        t0 = time.monotonic()
        err = proc.communicate(timeout=60)[1]
        took = time.monotonic() - t0
        time.sleep(0.3)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.close()
    stalled.close()
    assert proc.returncode == 0, err
    assert "rows published" in err
    assert took < 90 / 30.0 + 3.0  # the recording's own pace: no row waited for a client
    with open(out, newline="") as fh:
        rows = {int(r["frame"]): r for r in csv.DictReader(fh)}
    assert len(rows) == 90
    ts = get_typestore(Stores.ROS2_HUMBLE)
    st = [ts.deserialize_cdr(d, "diagnostic_msgs/msg/DiagnosticArray").status[0]
          for t, _, d in reader.got if t == "/visvec/status"]  # fmt: skip
    assert len(st) >= 30  # the rows after the subscription
    imu = [ts.deserialize_cdr(d, "sensor_msgs/msg/Imu") for t, _, d in reader.got
           if t == "/visvec/attitude"]  # fmt: skip
    by_frame = {int({kv.key: kv.value for kv in s.values}["frame"]): s for s in st}
    for f, s in by_frame.items():
        assert s.message == rows[f]["status"]
    ok_frames = [f for f, s in sorted(by_frame.items()) if s.message == "ok"]
    assert len(imu) == len(ok_frames)
    for f, m in zip(ok_frames, imu, strict=True):
        q = m.orientation
        np.testing.assert_allclose([q.w, q.x, q.y, q.z], [float(rows[f][k]) for k in
                                                          ("qw", "qx", "qy", "qz")])  # fmt: skip
    images = [t for t, _, _ in reader.got if t == "/visvec/overlay/compressed"]
    assert 1 <= len(images) <= 2 * (90 / 30.0) + 1
    jpeg = next(d for t, _, d in reader.got if t == "/visvec/overlay/compressed")
    msg = ts.deserialize_cdr(jpeg, "sensor_msgs/msg/CompressedImage")
    assert msg.format == "jpeg" and bytes(msg.data[:2]) == b"\xff\xd8"
