"""`--serve`: the live view of a `track`, `batch` or `rate` run (see visvec.view)."""

from __future__ import annotations

import time

import click

from visvec.pipeline import make_pipeline


def open_view(spec: str | None, rig, rig_path: str, method: str | None, source: str):
    """The live view's server, bound and serving, or None without --serve. Said on
    stderr with its address. A port in use or not allowed: exit 2, before the source
    is opened."""
    if spec is None:
        return None
    from visvec.check import ATTITUDE_KINDS
    from visvec.view import start

    cam = rig.camera
    info = [
        f"source: {source}",
        f"rig: {rig_path}: {rig.kind} target, camera {cam.width}x{cam.height}, fx {cam.fx:g} px",
    ]
    if rig.kind in ATTITUDE_KINDS:
        from visvec.cli.check import geometry_lines

        info += [("warning: " if warn else "") + text.strip() for text, warn in geometry_lines(rig)]
    row_type = make_pipeline(rig, method).row_type
    server = start(spec, rig, row_type, info, "--serve")  # ConfigError: exit 2
    click.echo(f"visvec: live view at {server.url}", err=True)
    return server


def linger(server) -> None:
    """At the end of a run with a live view: the server stops with the run (a script's
    run ends), said on stderr; with --keep-view the page stays (showing the run ended)
    until Ctrl-C or SIGTERM, then the server stops."""
    if server is None:
        return
    server.state.close()
    ctx = click.get_current_context(silent=True)
    if ctx is None or not ctx.meta.get("visvec.keep_view"):
        server.stop()
        click.echo(f"visvec: the run has ended, and so has the live view at {server.url} "
                   "(--keep-view keeps the page until Ctrl-C)", err=True)  # fmt: skip
        return
    click.echo(f"visvec: the run has ended; the live view stays at {server.url} until Ctrl-C",
               err=True)  # fmt: skip
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()


class FoxgloveWatcher:
    """A `track`, `batch` or `rate` run's rows (and overlays) published to Foxglove
    (visvec.sinks.foxglove.FoxgloveLive) after each row is written."""

    def __init__(self, live, rig):
        self.live = live
        self.rig = rig

    def see(self, frame, row, pipe) -> None:
        image = None
        if frame.image is not None and self.live.image_due(frame.time_s):
            img, det, rig = frame.image, pipe.last_detection, self.rig

            def image():
                import cv2

                from visvec.overlay import draw_overlay

                ok, buf = cv2.imencode(".jpg", draw_overlay(img, det, row, rig),
                                       [cv2.IMWRITE_JPEG_QUALITY, 85])  # fmt: skip
                return buf.tobytes() if ok else None

        self.live.publish(row.as_dict(), image)

    def close(self) -> None:
        self.live.close()
        dropped = f", {self.live.dropped} dropped while a client fell behind" if \
            self.live.dropped else ""  # fmt: skip
        click.echo(f"visvec: Foxglove: {self.live.published} rows published{dropped}; "
                   f"the server at ws://{self.live.host}:{self.live.port} has stopped",
                   err=True)  # fmt: skip


def open_foxglove(rig, method: str | None, topic_prefix: str = "/visvec"):
    """The Foxglove publisher of --foxglove (a FoxgloveWatcher), serving before the
    source opens (a port in use: exit 2), or None without the option. Said on stderr
    with its address."""
    ctx = click.get_current_context(silent=True)
    spec = ctx.meta.get("visvec.foxglove") if ctx is not None else None
    if spec is None:
        return None
    from visvec.sinks.foxglove import FoxgloveLive, parse_address

    host, port = parse_address(spec)
    row_type = make_pipeline(rig, method).row_type
    live = FoxgloveLive(host, port, row_type.columns, str(rig.path or ""), topic_prefix,
                        ctx.meta.get("visvec.foxglove_image_hz", 5.0))  # fmt: skip
    live.advertise(image=live.image_hz > 0)
    click.echo(f"visvec: Foxglove live at ws://{host}:{live.port} (open it in Foxglove: "
               "Open connection, Foxglove WebSocket)", err=True)  # fmt: skip
    return FoxgloveWatcher(live, rig)
