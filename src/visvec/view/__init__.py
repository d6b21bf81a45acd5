"""The live view: a web page served from the sensor's process, showing the newest frame
with its detection, the last row in words, the last minute's values with their sigmas,
and set-up aids (histogram, clipping, edge sharpness, the target's margin to the
border). ``visvec track|batch|rate --serve [HOST:]PORT``.

The sensor's loop hands each frame to :class:`ViewState` after its row is written (a
reference, no copy); the page's threads draw and encode at most 10 frames a second,
whatever the number of browsers, so the page never holds up a row.
"""

from __future__ import annotations

from visvec.view.server import LiveServer, parse_address
from visvec.view.state import ViewState

__all__ = ["LiveServer", "ViewState", "parse_address", "start"]


def start(spec: str, rig, row_type, info: list[str], option: str = "address") -> LiveServer:
    """A live view of rows of ``row_type`` for ``rig``, bound to ``spec`` ([HOST:]PORT)
    and serving; raises ConfigError for an address that cannot be served."""
    host, port = parse_address(spec, option)
    values = list(row_type.value_columns)
    sigmas = [f"sigma_{c}" for c in values]
    state = ViewState(rig, values, sigmas, info)
    server = LiveServer(host, port, state, option)
    server.start()
    return server
