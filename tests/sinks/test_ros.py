"""Rows as ROS 2 messages in an MCAP file (--out run.mcap), read back with the same
libraries and checked message by message against the CSV rows."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from conftest import ROOT, run

RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = ROOT / "data" / "sample_frames"


def messages(path: Path) -> list[tuple[str, str, int, object]]:
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    out = []
    with open(path, "rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages():
            out.append((channel.topic, schema.name, msg.log_time,
                        ts.deserialize_cdr(msg.data, schema.name)))  # fmt: skip
    return out


def rows_of(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_attitude_rows_as_ros2_messages(tmp_path):
    # the sample frames and a frame with no target
    import shutil

    import cv2

    rec = tmp_path / "rec"
    shutil.copytree(SAMPLES, rec, ignore=shutil.ignore_patterns("truth.csv"))
    cv2.imwrite(str(rec / "frame_0012.png"), np.full((480, 640), 128, np.uint8))
    assert run("batch", rec, "--rig", RIG, "--out", tmp_path / "rows.csv").exit_code == 0
    r = run("batch", rec, "--rig", RIG, "--out", tmp_path / "run.mcap")
    assert r.exit_code == 0, r.output
    rows = rows_of(tmp_path / "rows.csv")
    msgs = messages(tmp_path / "run.mcap")
    imu = [m for m in msgs if m[0] == "/visvec/attitude"]
    quat = [m for m in msgs if m[0] == "/visvec/attitude/quaternion"]
    status = [m for m in msgs if m[0] == "/visvec/status"]
    ok = [x for x in rows if x["status"] == "ok"]
    assert len(imu) == len(quat) == len(ok) == len(rows) - 1 and len(status) == len(rows)
    assert {m[1] for m in imu} == {"sensor_msgs/msg/Imu"}
    t0 = imu[0][2] / 1e9 - float(ok[0]["time_s"])
    for (_, _, t_ns, m), (_, _, _, q), x in zip(imu, quat, ok, strict=True):
        # ROS order x, y, z, w; the same quaternion as the row's qw, qx, qy, qz
        got = [m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w]
        want = [float(x[k]) for k in ("qx", "qy", "qz", "qw")]
        assert got == pytest.approx(want, abs=1e-12)
        assert [q.quaternion.x, q.quaternion.w] == pytest.approx([want[0], want[3]], abs=1e-12)
        assert t_ns / 1e9 - t0 == pytest.approx(float(x["time_s"]), abs=1e-6)
        cov = np.array(m.orientation_covariance).reshape(3, 3)
        # a small rotation's covariance from the Euler sigmas: symmetric, positive, and
        # (the Jacobian's columns being unit vectors) its trace the sum of the variances
        s2 = sum(math.radians(float(x[f"sigma_{k}"])) ** 2 for k in ("yaw_deg", "pitch_deg",
                                                                     "roll_deg"))  # fmt: skip
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        assert np.trace(cov) == pytest.approx(s2, rel=1e-9)
        assert m.angular_velocity_covariance[0] == -1.0  # not measured
        assert m.header.frame_id == "visvec_body"
    for (_, _, _, a), x in zip(status, rows, strict=True):
        (st,) = a.status
        assert st.message == x["status"]
        assert st.level == (0 if x["status"] == "ok" and not x["warnings"] else
                            1 if x["status"] == "ok" else 2)  # fmt: skip
        assert dict((kv.key, kv.value) for kv in st.values)["frame"] == x["frame"]


def test_planar_pose_rows_as_ros2_messages(tmp_path):
    lamps = ROOT / "configs" / "lamps.toml"
    rec = tmp_path / "rec"
    assert run("simulate", "--rig", lamps, "--out", rec, "--frames", 8).exit_code == 0
    assert run("batch", rec, "--rig", lamps, "--out", tmp_path / "rows.csv").exit_code == 0
    assert run("batch", rec, "--rig", lamps, "--out", tmp_path / "run.mcap").exit_code == 0
    rows = [x for x in rows_of(tmp_path / "rows.csv") if x["status"] == "ok"]
    poses = [m for m in messages(tmp_path / "run.mcap") if m[0] == "/visvec/pose"]
    assert len(poses) == len(rows) > 0
    for (_, name, _, m), x in zip(poses, rows, strict=True):
        assert name == "geometry_msgs/msg/PoseWithCovarianceStamped"
        p = m.pose.pose
        assert p.position.x == pytest.approx(float(x["x_mm"]) / 1000, abs=1e-12)
        assert p.position.y == pytest.approx(float(x["y_mm"]) / 1000, abs=1e-12)
        heading = math.degrees(2 * math.atan2(p.orientation.z, p.orientation.w))
        assert heading == pytest.approx(float(x["heading_deg"]), abs=1e-9)
        cov = np.array(m.pose.covariance).reshape(6, 6)
        assert cov[0, 0] == pytest.approx((float(x["sigma_x_mm"]) / 1000) ** 2)
        assert cov[5, 5] == pytest.approx(math.radians(float(x["sigma_heading_deg"])) ** 2)


def test_mcap_without_its_libraries_is_refused_before_any_frame(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mcap.writer", None)  # as if not installed
    r = run("batch", SAMPLES, "--rig", RIG, "--out", tmp_path / "run.mcap")
    assert r.exit_code == 2 and 'pip install "visvec[ros]"' in r.output
    assert not (tmp_path / "run.mcap").exists()


@pytest.mark.slow  # 4-5 s: the default run stays near 3 minutes
def test_fused_rows_as_ros2_messages(tmp_path):
    lamps = ROOT / "configs" / "lamps.toml"
    rec = tmp_path / "rec"
    # 5 s: the fusion first aligns the camera's clock with the IMU's (1-2 s here)
    assert run("simulate", "--rig", lamps, "--out", rec, "--frames", 150, "--imu").exit_code == 0
    args = ("batch", rec, "--rig", lamps, "--imu", rec / "imu.csv")
    # (one run: a replay's fixes are available after their measured processing time,
    # so two runs need not fuse alike)
    assert run(*args, "--out", tmp_path / "fused.mcap").exit_code == 0
    n_imu = len((rec / "imu.csv").read_text().splitlines()) - 1
    msgs = messages(tmp_path / "fused.mcap")
    poses = [m for m in msgs if m[0] == "/visvec/pose"]
    status = [m[3].status[0] for m in msgs if m[0] == "/visvec/status"]
    assert len(status) == n_imu  # a row per IMU sample
    assert len(poses) == sum(st.message == "ok" for st in status) > 0.5 * n_imu


def test_rows_as_a_ros2_bag_folder(tmp_path):
    """--format rosbag2: a bag folder (metadata.yaml and its MCAP file) that rosbags'
    reader (as `ros2 bag play`) opens, with every row's messages."""
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "run"
    r = run("batch", SAMPLES, "--rig", RIG, "--format", "rosbag2", "--out", bag)
    assert r.exit_code == 0, r.output
    assert (bag / "metadata.yaml").is_file()
    with Reader(bag) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        n = sum(1 for _ in reader.messages())
    assert topics["/visvec/attitude"] == "sensor_msgs/msg/Imu"
    assert n == 3 * 12  # the Imu, the quaternion and the status of each of the 12 rows
    r = run("batch", SAMPLES, "--rig", RIG, "--format", "rosbag2")
    assert r.exit_code == 2 and "bag folder" in r.output


def test_overlay_frames_as_compressed_images(tmp_path):
    import cv2

    out = tmp_path / "run.mcap"
    r = run("batch", SAMPLES, "--rig", RIG, "--out", out, "--ros-images")
    assert r.exit_code == 0, r.output
    imgs = [m for m in messages(out) if m[0] == "/visvec/overlay/compressed"]
    assert len(imgs) == 12 and {m[1] for m in imgs} == {"sensor_msgs/msg/CompressedImage"}
    pic = cv2.imdecode(np.asarray(imgs[0][3].data, np.uint8), cv2.IMREAD_COLOR)
    assert imgs[0][3].format == "jpeg" and pic.shape[:2] == (480, 640)
    r = run("batch", SAMPLES, "--rig", RIG, "--ros-images", "--out", tmp_path / "rows.csv")
    assert r.exit_code == 2 and not (tmp_path / "rows.csv").exists()


def _decoded_by_mcap_ros2(path: Path) -> dict[str, int]:
    """Messages per topic as the MCAP library's own ROS 2 decoder reads them (what
    Foxglove and ROS 2's tools parse: ROS 2 message definitions)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    counts: dict[str, int] = {}
    with open(path, "rb") as fh:
        for _schema, channel, _msg, decoded in make_reader(
            fh, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            assert decoded is not None
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_ros2_files_are_read_by_the_mcap_ros2_decoder(tmp_path):
    """The .mcap output and a rosbag2 folder's MCAP file carry ROS 2 message definitions
    (std_msgs/Header's builtin_interfaces/Time stamp, not ROS 1's time): the MCAP
    library's ROS 2 decoder reads every message, the same count rosbags reads."""
    pytest.importorskip("mcap_ros2")
    r = run("batch", SAMPLES, "--rig", RIG, "--out", tmp_path / "run.mcap")
    assert r.exit_code == 0, r.output
    counts = _decoded_by_mcap_ros2(tmp_path / "run.mcap")
    assert counts == {t: sum(m[0] == t for m in messages(tmp_path / "run.mcap")) for t in counts}
    assert counts["/visvec/attitude"] == 12 and counts["/visvec/status"] == 12
    from mcap.reader import make_reader

    with open(tmp_path / "run.mcap", "rb") as fh:
        schemas = make_reader(fh).get_summary().schemas.values()
    assert all(b"builtin_interfaces/Time stamp" in s.data for s in schemas if b"Header" in s.data)
    bag = tmp_path / "bag"
    r = run("batch", SAMPLES, "--rig", RIG, "--format", "rosbag2", "--out", bag)
    assert r.exit_code == 0, r.output
    (inner,) = bag.glob("*.mcap")
    assert sum(_decoded_by_mcap_ros2(inner).values()) == 3 * 12
