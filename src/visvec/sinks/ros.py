"""Rows as ROS 2 messages in an MCAP file (`--out run.mcap`), for Foxglove and
`ros2 bag play`, without a ROS installation.

rosbags (Ternaris) holds the standard ROS 2 message definitions and their CDR
serialisation; mcap (Foxling's reference writer) writes the file. Each row is written
and flushed at once (no chunking), so a run that is cut short keeps every row it made
(MCAP readers read such a file without its closing index).

Messages (ROS conventions, REP 103 / 105: right-handed, z up, quaternions x y z w,
SI units):

- attitude rows (triangle, markers, fused attitude): ``/visvec/attitude``,
  ``sensor_msgs/msg/Imu`` with the orientation q_NB (the body frame B in the lab frame
  N; N has n3 up, so it is a z-up world frame) and its 3x3 covariance about the lab's
  axes (rad^2, from the rows' yaw, pitch and roll sigmas through the Euler rates'
  Jacobian; the rows carry no correlations), the rates and accelerations marked unknown
  (covariance[0] = -1); and ``/visvec/attitude/quaternion``,
  ``geometry_msgs/msg/QuaternionStamped``;
- rate rows (starfield): ``/visvec/rate``, ``geometry_msgs/msg/TwistWithCovarianceStamped``,
  the angular rate in rad/s in the camera's optical frame (x right, y down, z out of
  the lens: OpenCV's, which is ROS's ``*_optical_frame``), the linear part unknown
  (zero with a covariance of 1e9);
- planar pose rows (lamps, fused pose): ``/visvec/pose``,
  ``geometry_msgs/msg/PoseWithCovarianceStamped``, x, y in m, the heading as a turn
  about z, the covariance of x, y and heading (m^2, rad^2), z, roll and pitch held by
  the planar model (zero);
- every row: ``/visvec/status``, ``diagnostic_msgs/msg/DiagnosticArray`` with one status
  (level OK for an ok row, WARN for an ok row with warnings, ERROR otherwise; the
  message the status code, the values frame, time_s, warnings, rms_px, n_points,
  latency_ms).

Stamps: the computer's clock when the run started plus the row's ``time_s``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from visvec.errors import ConfigError, OutputError

LAB_FRAME = "visvec_lab"
BODY_FRAME = "visvec_body"
CAMERA_FRAME = "visvec_camera_optical_frame"
UNKNOWN_COV = 1e9
STATUS_KEYS = ("frame", "time_s", "warnings", "rms_px", "n_points", "latency_ms")
# (topic, message type) of each kind of row's value, of every row's status, of the overlay
TOPICS = {
    "attitude": (("/visvec/attitude", "sensor_msgs/msg/Imu"),
                 ("/visvec/attitude/quaternion", "geometry_msgs/msg/QuaternionStamped")),
    "rate": (("/visvec/rate", "geometry_msgs/msg/TwistWithCovarianceStamped"),),
    "pose": (("/visvec/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),),
}  # fmt: skip
STATUS_TOPIC = ("/visvec/status", "diagnostic_msgs/msg/DiagnosticArray")
OVERLAY_TOPIC = ("/visvec/overlay/compressed", "sensor_msgs/msg/CompressedImage")


def _need():
    try:
        from mcap.writer import Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ConfigError(
            'an MCAP output needs the ROS 2 extra: pip install "visvec[ros]" (rosbags and mcap)'
        ) from None
    return Writer, get_typestore(Stores.ROS2_HUMBLE)


def check_available() -> None:
    """ConfigError (exit 2, before any frame) when the libraries are not installed."""
    _need()


def euler_cov_to_rotation_cov(yaw, pitch, sigmas_rad) -> np.ndarray:
    """The 3x3 covariance of a small rotation about the lab's axes from the sigmas of
    intrinsic Z-Y-X Euler angles: with R = Rz(yaw) Ry(pitch) Rx(roll), a change of the
    angles turns the body by d_omega = e_z d_yaw + Rz(yaw) e_y d_pitch +
    Rz(yaw) Ry(pitch) e_x d_roll (lab axes), so Cov = J diag(sigma^2) J^T."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    J = np.array([[0.0, -sy, cy * cp], [0.0, cy, sy * cp], [1.0, 0.0, -sp]])
    return J @ np.diag(np.square(sigmas_rad)) @ J.T


class RosMessages:
    """Rows (as dicts of their columns) as the ROS 2 messages of the module doc, handed
    to ``_put(topic, typename, message, stamp_ns)``: the one description of what each
    row becomes, for a file (McapSink) and a live server (visvec.sinks.foxglove)."""

    def __init__(self, columns, rig_name: str = ""):
        _, self.ts = _need()
        self.t0 = time.time()
        self.rig_name = rig_name
        self.kind = ("attitude" if "yaw_deg" in columns else "rate" if "wx_dps" in columns
                     else "pose")  # fmt: skip
        self.n = 0

    def _put(self, topic: str, typename: str, msg, stamp_ns: int) -> None:
        raise NotImplementedError

    def _stamp(self, time_s: float):
        """The stamp (ns) and the builtin_interfaces Time of a row's ``time_s``."""
        ns = int(round((self.t0 + float(time_s)) * 1e9))
        T = self.ts.types
        return ns, T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                                     nanosec=ns % 1_000_000_000)  # fmt: skip

    def messages(self, row: dict) -> None:
        """The row's value (an ok row) and its status, each to ``_put``."""
        ns, stamp = self._stamp(row["time_s"])
        T = self.ts.types

        def header(frame):
            return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

        ok = row["status"] == "ok"
        if ok:
            self._value(row, header, T, ns)
        self._status(row, header, T, ns, ok)
        self.n += 1

    def image_message(self, time_s: float, jpeg: bytes) -> None:
        """A frame with its detection drawn, as ``/visvec/overlay/compressed``
        (``sensor_msgs/msg/CompressedImage``, JPEG, ``frame_id`` the camera's optical
        frame), stamped as the frame's row."""
        ns, stamp = self._stamp(time_s)
        T = self.ts.types
        msg = T["sensor_msgs/msg/CompressedImage"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=CAMERA_FRAME),
            format="jpeg", data=np.frombuffer(jpeg, np.uint8),
        )  # fmt: skip
        self._put(*OVERLAY_TOPIC, msg, ns)

    def _value(self, row, header, T, ns) -> None:
        V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        if self.kind == "attitude":
            q = Q(x=float(row["qx"]), y=float(row["qy"]), z=float(row["qz"]), w=float(row["qw"]))
            sig = np.radians(
                [float(row[f"sigma_{k}"]) for k in ("yaw_deg", "pitch_deg", "roll_deg")]
            )
            cov = euler_cov_to_rotation_cov(math.radians(float(row["yaw_deg"])),
                                            math.radians(float(row["pitch_deg"])), sig)  # fmt: skip
            unknown = np.zeros(9)
            unknown[0] = -1.0
            imu = T["sensor_msgs/msg/Imu"](
                header=header(BODY_FRAME), orientation=q,
                orientation_covariance=cov.ravel().astype(np.float64),
                angular_velocity=V3(x=0.0, y=0.0, z=0.0), angular_velocity_covariance=unknown,
                linear_acceleration=V3(x=0.0, y=0.0, z=0.0),
                linear_acceleration_covariance=unknown.copy(),
            )  # fmt: skip
            self._put(*TOPICS["attitude"][0], imu, ns)
            qs = T["geometry_msgs/msg/QuaternionStamped"](header=header(LAB_FRAME), quaternion=q)
            self._put(*TOPICS["attitude"][1], qs, ns)
        elif self.kind == "rate":
            w = np.radians([float(row[k]) for k in ("wx_dps", "wy_dps", "wz_dps")])
            s = np.radians([float(row[f"sigma_{k}"]) for k in ("wx_dps", "wy_dps", "wz_dps")])
            cov = np.zeros((6, 6))
            cov[:3, :3] = np.eye(3) * UNKNOWN_COV
            cov[3:, 3:] = np.diag(s**2)
            tw = T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=V3(x=0.0, y=0.0, z=0.0),
                                                   angular=V3(x=w[0], y=w[1], z=w[2])),
                covariance=cov.ravel(),
            )  # fmt: skip
            msg = T["geometry_msgs/msg/TwistWithCovarianceStamped"](header=header(CAMERA_FRAME),
                                                                   twist=tw)  # fmt: skip
            self._put(*TOPICS["rate"][0], msg, ns)
        else:
            h = math.radians(float(row["heading_deg"]))
            cov = np.zeros((6, 6))
            cov[0, 0] = (float(row["sigma_x_mm"]) / 1000.0) ** 2
            cov[1, 1] = (float(row["sigma_y_mm"]) / 1000.0) ** 2
            cov[5, 5] = math.radians(float(row["sigma_heading_deg"])) ** 2
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(row["x_mm"]) / 1000.0,
                                                      y=float(row["y_mm"]) / 1000.0, z=0.0),
                orientation=Q(x=0.0, y=0.0, z=math.sin(h / 2), w=math.cos(h / 2)),
            )  # fmt: skip
            msg = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=header(LAB_FRAME),
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov.ravel()),
            )  # fmt: skip
            self._put(*TOPICS["pose"][0], msg, ns)

    def _status(self, row, header, T, ns, ok) -> None:
        KV = T["diagnostic_msgs/msg/KeyValue"]
        warnings = str(row.get("warnings") or "")
        level = (0 if not warnings else 1) if ok else 2
        values = [KV(key=k, value="" if row.get(k) is None else str(row.get(k)))
                  for k in STATUS_KEYS]  # fmt: skip
        st = T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=level, name="visvec", message=str(row["status"]),
            hardware_id=self.rig_name, values=values,
        )  # fmt: skip
        arr = T["diagnostic_msgs/msg/DiagnosticArray"](header=header(LAB_FRAME), status=[st])
        self._put(*STATUS_TOPIC, arr, ns)


class McapSink(RosMessages):
    """Rows (as dicts of their columns) to ROS 2 messages in an MCAP file, or with
    ``bag`` in a ROS 2 bag folder (rosbags' writer, MCAP storage: `ros2 bag play DIR`;
    its index and metadata.yaml are written when the run ends)."""

    def __init__(self, path: str, columns, rig_name: str = "", bag: bool = False):
        Writer, _ = _need()
        super().__init__(columns, rig_name)
        self.path = path
        self.bag = None
        self.fh = None
        if bag:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as BagWriter

            try:
                self.bag = BagWriter(path, version=8, storage_plugin=StoragePlugin.MCAP)
                self.bag.open()
            except Exception as exc:  # noqa: BLE001 - rosbags' own errors name the folder
                raise OutputError(f"{path}: cannot write the bag folder ({exc})") from None
            self.bag_conns: dict[str, object] = {}
        else:
            try:
                self.fh = open(path, "wb")  # noqa: SIM115 - closed by close()
            except OSError as exc:
                raise OutputError(f"{path}: cannot write ({exc.strerror})") from None
            self.w = Writer(self.fh, use_chunking=False)
            self.w.start(profile="ros2", library="visvec")
        self.channels: dict[str, int] = {}

    def _channel(self, topic: str, typename: str) -> int:
        if topic not in self.channels:
            # ROS 2 definitions (builtin_interfaces/Time stamp): rosbags writes ROS 1's
            # unless asked, which ROS 2 readers (mcap-ros2-support) cannot parse
            msgdef, _ = self.ts.generate_msgdef(typename, ros_version=2)
            schema = self.w.register_schema(typename, "ros2msg", msgdef.encode())
            self.channels[topic] = self.w.register_channel(topic, "cdr", schema)
        return self.channels[topic]

    def _put(self, topic: str, typename: str, msg, stamp_ns: int) -> None:
        data = bytes(self.ts.serialize_cdr(msg, typename))
        if self.bag is not None:
            if topic not in self.bag_conns:
                self.bag_conns[topic] = self.bag.add_connection(topic, typename,
                                                                typestore=self.ts)  # fmt: skip
            self.bag.write(self.bag_conns[topic], stamp_ns, data)
            return
        self.w.add_message(self._channel(topic, typename), log_time=stamp_ns, data=data,
                           publish_time=stamp_ns)  # fmt: skip

    def write(self, row: dict) -> None:
        try:
            self.messages(row)
            if self.fh is not None:
                self.fh.flush()
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc}); it holds "
                              f"{self.n} rows") from None  # fmt: skip

    def image(self, time_s: float, jpeg: bytes) -> None:
        """A frame with its detection drawn (`RosMessages.image_message`)."""
        try:
            self.image_message(time_s, jpeg)
            if self.fh is not None:
                self.fh.flush()
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    def close(self) -> None:
        if self.bag is not None:
            self.bag.close()
            return
        try:
            self.w.finish()
        finally:
            self.fh.close()
