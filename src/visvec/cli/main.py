"""Entry point: the `visvec` command group and its exit codes (docs/reference.md).

0 success; 2 bad usage, rig or calibration file; 3 a source that cannot be opened or
read at all; 4 a run that gave not one ok row; 1 an output that cannot be written, a
refused calibration, or anything unexpected (one line, the traceback only with
--debug); 130 simulate, or batch over many recordings, stopped by Ctrl-C.
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import sys

import click

from visvec import __version__
from visvec.errors import ConfigError, InputFileError, NoOkRows, OutputError, SourceError


class VisvecGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        if cmd_name not in self.commands:
            self.commands[cmd_name] = _load(cmd_name)
        return self.commands[cmd_name]

    def invoke(self, ctx: click.Context):
        debug = bool(ctx.params.get("debug"))
        try:
            return super().invoke(ctx)
        except (ConfigError, InputFileError) as exc:
            click.echo(f"visvec: error: {exc}", err=True)
            sys.exit(2)
        except SourceError as exc:
            click.echo(f"visvec: error: {exc}", err=True)
            sys.exit(3)
        except OutputError as exc:
            click.echo(f"visvec: error: {exc}", err=True)
            sys.exit(1)
        except NoOkRows as exc:
            click.echo(f"visvec: {exc}", err=True)
            sys.exit(4)
        except (click.ClickException, click.exceptions.Exit, click.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            sys.exit(0)
        except BrokenPipeError:
            # the reader of stdout went away (`visvec track ... | head`): like Ctrl-C, the
            # run ends quietly; stdout goes to devnull so that Python's own flush at exit
            # does not raise again
            import os

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(0)
        except Exception as exc:  # noqa: BLE001 - the last resort the contract promises
            if debug:
                raise
            click.echo(
                f"visvec: unexpected error: {type(exc).__name__}: {exc} "
                "(run with --debug for the traceback)",
                err=True,
            )
            sys.exit(1)


class _EchoHandler(logging.Handler):
    """The library's warnings (logger ``visvec``) as one line on stderr each."""

    def emit(self, record: logging.LogRecord) -> None:
        click.echo(f"visvec: {record.getMessage()}", err=True)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _signals_as_interrupt() -> None:
    """SIGTERM (systemd, kill) and SIGHUP (a closed terminal or ssh session) end a run
    as Ctrl-C does: every row already made is written, then the summary."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _interrupt)


def _route_library_warnings() -> None:
    log = logging.getLogger("visvec")
    if not any(isinstance(h, _EchoHandler) for h in log.handlers):
        log.addHandler(_EchoHandler(logging.WARNING))
        log.propagate = False


def _show_version(ctx: click.Context, _param: click.Parameter, value: bool) -> None:
    """--version: the version, and whether the triangle's compiled kernels run."""
    if not value or ctx.resilient_parsing:
        return
    from visvec import _kernels

    if _kernels.AVAILABLE:
        numba_version = importlib.metadata.version("numba")
        kernels = f"the triangle's edge, pixel and attitude fits compiled (Numba {numba_version})"
    elif _kernels.PURE:
        kernels = "the triangle's edge, pixel and attitude fits in numpy (VISVEC_PURE is set)"
    else:
        kernels = ("the triangle's edge, pixel and attitude fits in numpy (pip install "
                   "\"visvec[fast]\" compiles them)")  # fmt: skip
    click.echo(f"visvec, version {__version__}\n{kernels}")
    ctx.exit()


@click.group(cls=VisvecGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True,
              callback=_show_version, help="Show the version and exit.")  # fmt: skip
@click.option("--debug", is_flag=True, help="Show tracebacks of unexpected errors.")
@click.option(
    "--status-every",
    type=click.FloatRange(min=0),
    default=10.0,
    show_default=True,
    metavar="S",
    help="Long work shows a progress bar at a terminal; otherwise (a service's log, nohup) "
    "a status line every S seconds. 0: neither.",
)
def cli(debug: bool, status_every: float) -> None:
    """visvec: camera attitude sensor for air-bearing spacecraft simulators.

    Units are mm and degrees; see docs/reference.md for the frames and the rig file.
    """
    _route_library_warnings()
    _signals_as_interrupt()
    from visvec.cli.common import forget_inputs

    forget_inputs()  # a new command (tests run many in one process)
    from visvec.cli.progress import set_status_every

    set_status_every(status_every)
    if not debug:
        # OpenCV's own warnings (for instance every backend it tried on a camera that
        # cannot be opened) would bury visvec's one-line message; --debug keeps them.
        # OpenCV reads the level when it is imported: a command that never imports it
        # (fuse, plot) does not pay for the import here
        if "cv2" in sys.modules:
            import cv2

            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        else:
            os.environ["OPENCV_LOG_LEVEL"] = "ERROR"


# the commands, in the order `visvec --help` lists them, each imported when it is run
# (or listed): `visvec fuse` starts without the camera pipelines' imports
COMMANDS = {
    "track": "visvec.cli.track:track",
    "batch": "visvec.cli.batch:batch",
    "calibrate": "visvec.cli.calibrate:calibrate",
    "simulate": "visvec.cli.simulate:simulate",
    "montecarlo": "visvec.cli.montecarlo:montecarlo",
    "rate": "visvec.cli.rate:rate",
    "catalog": "visvec.cli.catalog:catalog",
    "fuse": "visvec.cli.fuse:fuse",
    "check": "visvec.cli.check:check",
    "plot": "visvec.cli.plot:plot",
}


def _load(name: str) -> click.Command:
    """The command ``name``, imported, its help ending with the exit codes it can give
    (every subcommand of a group with its group's)."""
    import importlib

    module, attr = COMMANDS[name].split(":")
    cmd = getattr(importlib.import_module(module), attr)
    todo = [cmd]
    while todo:
        c = todo.pop()
        c.epilog = exit_codes(name)
        if isinstance(c, click.Group):
            todo += list(c.commands.values())
    return cmd


def _register() -> None:
    cli.epilog = exit_codes(None)


# what each exit code means (the module doc), and which a command can give
CODE_TEXT = {
    0: "0 done",
    2: "2 a bad option, rig, calibration or data file, refused before any work",
    3: "3 a source that cannot be opened or read",
    4: "4 not one ok row",
    1: "1 an output that cannot be written, or an unexpected error",
    130: "130 stopped by Ctrl-C",
}
COMMAND_CODES = {
    "track": (0, 2, 3, 4, 1),
    "batch": (0, 2, 3, 4, 1, 130),
    "rate": (0, 2, 3, 4, 1),
    "fuse": (0, 2, 4, 1),
    "calibrate": (0, 2, 3, 1),
    "simulate": (0, 2, 1, 130),
    "montecarlo": (0, 2, 1, 130),
}


# a command's own wording of a code
CODE_OWN = {
    ("track", 0): "0 done (also after Ctrl-C, SIGTERM, SIGHUP)",
    ("rate", 0): "0 done (also after Ctrl-C, SIGTERM, SIGHUP)",
    ("fuse", 0): "0 done (also after Ctrl-C, SIGTERM, SIGHUP)",
    ("batch", 0): "0 done (one recording: also after Ctrl-C, SIGTERM, SIGHUP)",
    ("batch", 130): "130 several recordings (--out-dir) stopped by Ctrl-C",
    ("simulate", 130): "130 stopped by Ctrl-C (the recording is incomplete)",
    ("calibrate", 1): "1 an output that cannot be written, a refused calibration, or an "
    "unexpected error",
    (None, 0): "0 done (track, batch, rate, fuse: also after Ctrl-C, SIGTERM, SIGHUP)",
    (None, 1): "1 an output that cannot be written, a refused calibration, or an unexpected error",
    (None, 130): "130 simulate, montecarlo, or batch over several recordings, stopped by Ctrl-C",
}


def exit_codes(command: str | None) -> str:
    """The help's closing line: the exit codes ``command`` can give (every one for the
    group's own help)."""
    codes = COMMAND_CODES.get(command, (0, 2, 1)) if command else tuple(CODE_TEXT)
    parts = [CODE_OWN.get((command, c), CODE_TEXT[c]) for c in codes]
    return "Exit codes: " + "; ".join(parts) + "."


_register()


def main() -> None:
    cli(prog_name="visvec")
