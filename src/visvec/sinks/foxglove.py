"""Rows published live to Foxglove (`--foxglove [HOST:]PORT`): a Foxglove WebSocket
server (the ``foxglove-sdk`` package, the ``foxglove`` extra) whose channels are the
MCAP output's (visvec.sinks.ros: the same topics, the same ROS 2 message definitions,
CDR-encoded), so that a Foxglove layout made on a recorded ``run.mcap`` works on the
live run, and the frame with its detection drawn as ``/visvec/overlay/compressed`` at
a rate the user sets.

Live rules: a row is published after it is written, by a thread of its own, through a
bounded queue: a slow client, or a burst of rows, drops the oldest waiting rows (they
are counted), never holds up a row; with no client subscribed nothing is encoded. The
server binds 127.0.0.1 unless told otherwise (docs/lab-guide.md says what to expose).
"""

from __future__ import annotations

import collections
import threading
import time

from visvec.errors import ConfigError
from visvec.sinks.ros import OVERLAY_TOPIC, STATUS_TOPIC, TOPICS, RosMessages

QUEUE_ROWS = 256  # rows waiting for the publishing thread; beyond, the oldest go


def parse_address(text: str, option: str = "--foxglove") -> tuple[str, int]:
    """``[HOST:]PORT`` as (host, port); HOST defaults to 127.0.0.1.

    Raises
    ------
    ConfigError
        Not a port in 1..65535 (0: any free port, said at the start), or an empty host.
    """
    host, _, port = text.rpartition(":")
    host = host or "127.0.0.1"
    try:
        p = int(port)
    except ValueError:
        raise ConfigError(f"{option} {text!r}: expected [HOST:]PORT, PORT a number") from None
    if not 0 <= p <= 65535:
        raise ConfigError(f"{option} {text!r}: the port must be in 0..65535")
    return host.strip("[]"), p


def _need():
    try:
        import foxglove
    except ImportError:
        raise ConfigError(
            '--foxglove needs the foxglove extra: pip install "visvec[foxglove]" '
            "(foxglove-sdk, rosbags)"
        ) from None
    return foxglove


class FoxgloveServer:
    """A Foxglove WebSocket server on (host, port), started here (a port in use: a
    ConfigError, exit 2, before any source opens), with a context of its own (channels
    of another server never mix in); `FoxgloveLive` publishes on it."""

    def __init__(self, host: str, port: int):
        fg = _need()
        self.fg = fg
        self.ctx = fg.Context()
        try:
            self.server = fg.start_server(name="visvec", host=host, port=port, context=self.ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK's own error names the cause
            raise ConfigError(f"--foxglove {host}:{port}: cannot serve there ({exc})") from None
        self.host, self.port = host, self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def stop(self) -> None:
        self.server.stop()


class FoxgloveLive(RosMessages):
    """Rows of ``columns`` published on ``server`` as the MCAP output's messages, and
    overlay frames. ``topic_prefix`` puts the topics under another root (the camera's
    own rows beside the fused ones: ``/visvec/camera``)."""

    def __init__(self, server: FoxgloveServer, columns, rig_name: str = "",
                 topic_prefix: str = "/visvec", image_hz: float = 5.0):  # fmt: skip
        super().__init__(columns, rig_name)
        self.srv = server
        self._fg, self.ctx = server.fg, server.ctx
        self.prefix = topic_prefix.rstrip("/")
        self.image_hz = image_hz
        self._channels: dict[str, object] = {}
        self._queue: collections.deque = collections.deque(maxlen=QUEUE_ROWS)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.dropped = 0  # rows that waited too long (the queue was full)
        self.published = 0
        self._last_image = -float("inf")
        self._thread = threading.Thread(target=self._run, name="visvec-foxglove", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ the sensor's side
    def publish(self, row, image=None) -> None:
        """Queue a row (a dict of its columns, or a `visvec.output.Row`, made into one on
        the publishing thread) and, optionally, ``image()``: a callable that makes its
        overlay's JPEG bytes, called on the publishing thread when an image is due
        (``image_hz``) and a client watches. Returns at once."""
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append((row, image))
        self._wake.set()

    def image_due(self, time_s: float) -> bool:
        """Whether a frame at ``time_s`` (s, the rows' clock) should carry its overlay:
        at most ``image_hz`` a second, and only while a client subscribes to it."""
        if self.image_hz <= 0 or time_s - self._last_image < 1.0 / self.image_hz:
            return False
        ch = self._channels.get(self.prefix + OVERLAY_TOPIC[0].removeprefix("/visvec"))
        if ch is not None and not ch.has_sinks():
            return False
        self._last_image = time_s
        return True

    def close(self) -> None:
        """Publish what is queued (for up to a second), then stop publishing (the
        server stops with its owner: `FoxgloveServer.stop`)."""
        deadline = time.monotonic() + 1.0
        while self._queue and time.monotonic() < deadline:
            self._wake.set()
            time.sleep(0.01)
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)

    # ------------------------------------------------------------ the thread's side
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while self._queue:
                row, image = self._queue.popleft()
                if not self._watched():
                    continue
                d = row if isinstance(row, dict) else row.as_dict()
                self.messages(d)
                if image is not None:
                    jpeg = image()
                    if jpeg is not None:
                        self.image_message(d["time_s"], jpeg)
                self.published += 1

    def _watched(self) -> bool:
        """Whether any client subscribes to a channel (before the first row every
        channel is made, so that a client sees them advertised)."""
        if not self._channels:
            return True
        return any(ch.has_sinks() for ch in self._channels.values())

    def _channel(self, topic: str, typename: str):
        topic = self.prefix + topic.removeprefix("/visvec")
        ch = self._channels.get(topic)
        if ch is None:
            # the ROS 2 definition, as the MCAP output registers it (ros.McapSink)
            msgdef, _ = self.ts.generate_msgdef(typename, ros_version=2)
            schema = self._fg.Schema(name=typename, encoding="ros2msg", data=msgdef.encode())
            ch = self._fg.Channel(topic, schema=schema, message_encoding="cdr", context=self.ctx)
            self._channels[topic] = ch
        return ch

    def _put(self, topic: str, typename: str, msg, stamp_ns: int) -> None:
        ch = self._channel(topic, typename)
        if ch.has_sinks():
            ch.log(bytes(self.ts.serialize_cdr(msg, typename)), log_time=stamp_ns)

    def advertise(self, image: bool = True) -> None:
        """Make every channel this kind of row publishes now, so that a client that
        connects before the first row sees them all and can subscribe (the overlay's
        with ``image``)."""
        for topic, typename in (*TOPICS[self.kind], STATUS_TOPIC, *((OVERLAY_TOPIC,) * image)):
            self._channel(topic, typename)


class Published:
    """A row sink whose rows are also published (`FoxgloveLive.publish`) after they
    are written: a live fusion's rows (`fuse`, `track --imu`)."""

    def __init__(self, sink, live: FoxgloveLive):
        from visvec.sinks.writers import row_writer

        self.sink = sink
        self.live = live
        self._write_row = row_writer(sink)

    def write(self, row: dict) -> None:
        self.sink.write(row)
        self.live.publish(row)

    def write_row(self, row) -> None:
        self._write_row(row)
        self.live.publish(row)
