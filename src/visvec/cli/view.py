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
