"""A Foxglove WebSocket client for the tests (Foxglove's own protocol: the server's
advertisements, subscriptions, and message data frames: opcode 1, the subscription id,
the log time, the payload)."""

from __future__ import annotations

import json
import struct
import threading
import time


class Client:
    """A Foxglove WebSocket client: the channels advertised, and the messages of those
    it subscribed to, decoded, in a thread of its own (``read=False``: a client that
    subscribes and never reads, as a stalled viewer does)."""

    def __init__(self, port: int, read: bool = True, auto: bool = False):
        from websockets.sync.client import connect

        self._conn = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                             open_timeout=10)  # fmt: skip
        self.ws = self._conn.__enter__()
        self.channels: dict[int, dict] = {}
        self.subs: dict[int, dict] = {}
        self.got: list[tuple[str, int, bytes]] = []  # topic, log time, payload
        self.read = read
        self.auto = auto  # subscribe to every channel as it is advertised
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from websockets.exceptions import ConnectionClosed

        while not self._stop.is_set():
            if not self.read and self.subs:
                time.sleep(0.05)
                continue
            try:
                m = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except ConnectionClosed:
                return
            if isinstance(m, str):
                msg = json.loads(m)
                if msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        self.channels[ch["id"]] = ch
                    if self.auto:
                        self._subscribe([ch["id"] for ch in msg["channels"]])
                continue
            if m[0] == 1:  # message data: opcode, subscription, log time, payload
                sub, t = struct.unpack_from("<IQ", m, 1)
                self.got.append((self.subs[sub]["topic"], t, bytes(m[13:])))

    def subscribe_all(self, wait_for: int) -> None:
        deadline = time.monotonic() + 10
        while len(self.channels) < wait_for and time.monotonic() < deadline:
            time.sleep(0.02)
        assert len(self.channels) >= wait_for, self.channels
        self._subscribe(sorted(self.channels))
        time.sleep(0.3)  # the server has taken the subscription

    def _subscribe(self, channel_ids) -> None:
        subs = []
        for cid in channel_ids:
            k = len(self.subs) + 1
            self.subs[k] = self.channels[cid]
            subs.append({"id": k, "channelId": cid})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decoded(self, topic: str, typename: str) -> list:
        """The messages received on ``topic``, decoded (rosbags' CDR reader)."""
        from rosbags.typesys import Stores, get_typestore

        ts = get_typestore(Stores.ROS2_HUMBLE)
        return [ts.deserialize_cdr(d, typename) for t, _, d in self.got if t == topic]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._conn.__exit__(None, None, None)
