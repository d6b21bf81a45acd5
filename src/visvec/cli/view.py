"""`--serve`: the live view of a `track`, `batch` or `rate` run (see visvec.view)."""

from __future__ import annotations

import time

import click


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
    from visvec.pipeline import make_pipeline

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

    def __init__(self, live, rig, stop_server: bool = True):
        self.live = live
        self.rig = rig
        self.stop_server = stop_server

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

        self.live.publish(row, image)  # its dict made on the publishing thread

    def close(self) -> None:
        say_published(self.live, self.stop_server)


def foxglove_server():
    """The Foxglove server of --foxglove, serving (a port in use: exit 2, before any
    source opens), or None without the option. Said on stderr with its address."""
    ctx = click.get_current_context(silent=True)
    spec = ctx.meta.get("visvec.foxglove") if ctx is not None else None
    if spec is None:
        return None
    from visvec.sinks.foxglove import FoxgloveServer, parse_address

    server = FoxgloveServer(*parse_address(spec))
    click.echo(f"visvec: Foxglove live at {server.url} (in Foxglove: Open connection, "
               "Foxglove WebSocket)", err=True)  # fmt: skip
    return server


def foxglove_live(server, columns, rig, topic_prefix: str = "/visvec", image: bool = True):
    """A publisher of rows of ``columns`` on ``server`` (foxglove_server), its channels
    advertised at once; the overlay's at --foxglove-image-hz where ``image``."""
    from visvec.sinks.foxglove import FoxgloveLive

    ctx = click.get_current_context(silent=True)
    hz = ctx.meta.get("visvec.foxglove_image_hz", 5.0) if ctx is not None and image else 0.0
    live = FoxgloveLive(server, columns, str(rig.path or "") if rig is not None else "",
                        topic_prefix, hz)  # fmt: skip
    live.advertise(image=hz > 0)
    return live


def say_published(live, stop_server: bool = True) -> None:
    """The end of a publisher (and of its server): what it published, said."""
    live.close()
    if stop_server:
        live.srv.stop()
    dropped = f", {live.dropped} dropped while a client fell behind" if live.dropped else ""
    click.echo(f"visvec: Foxglove {live.prefix}: {live.published} rows published{dropped}"
               + ("; the server has stopped" if stop_server else ""), err=True)  # fmt: skip


def open_foxglove(rig, method: str | None, topic_prefix: str = "/visvec", server=None):
    """The Foxglove publisher of a frame loop (a FoxgloveWatcher: on ``server``, or on
    a server of --foxglove started here), or None without the option."""
    own = server is None
    server = foxglove_server() if own else server
    if server is None:
        return None
    from visvec.pipeline import make_pipeline

    live = foxglove_live(server, make_pipeline(rig, method).row_type.columns, rig, topic_prefix)
    return FoxgloveWatcher(live, rig, stop_server=own)
