"""Progress of long work on stderr: a bar at a terminal, a status line every few seconds
otherwise (a flight computer's service log, nohup), and nothing with --status-every 0.

The bar is tqdm's: a small, pure-Python, long-kept library whose bar handles terminal
widths, rates and time left, and redraws at most a few times a second whatever the
loop's rate; a hand-written one would have to relearn all of that."""

from __future__ import annotations

import sys
import time

import click

# seconds between status lines when stderr is not a terminal (the default of
# `visvec --status-every`); 0 silences them
STATUS_EVERY_S = 10.0
_every = {"s": STATUS_EVERY_S}


def set_status_every(seconds: float) -> None:
    _every["s"] = seconds


def status_every() -> float:
    return _every["s"]


def _fmt_left(s: float) -> str:
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


class Work:
    """One long piece of work: ``what`` (said first), ``total`` steps if known, each
    a ``unit``. ``bar=False`` when something else already writes to the terminal (rows
    to stdout at the same terminal: the rows are the progress)."""

    def __init__(self, what: str, total: int | None = None, unit: str = "frame",
                 bar: bool = True):  # fmt: skip
        self.what, self.total, self.unit = what, total, unit
        self.done = 0
        self.t0 = time.monotonic()
        self.text = ""
        tty = sys.stderr.isatty()
        self.every = 0.0 if tty else status_every()
        self.next = self.t0 + self.every
        self.bar = None
        if tty and bar and status_every() != 0:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=f"visvec {what}", unit=unit, file=sys.stderr,
                            leave=False, dynamic_ncols=True, mininterval=0.25)  # fmt: skip

    def update(self, n: int = 1, text: str | None = None) -> None:
        self.done += n
        if text is not None:
            self.text = text
        if self.bar is not None:
            if text is not None:
                self.bar.set_postfix_str(text, refresh=False)
            self.bar.update(n)
        elif self.every > 0:
            now = time.monotonic()
            if now >= self.next:
                self.next = now + self.every
                click.echo(self.line(now), err=True)

    def line(self, now: float | None = None) -> str:
        dt = max((time.monotonic() if now is None else now) - self.t0, 1e-9)
        rate = self.done / dt
        if self.total:
            text = (
                f"visvec: {self.what}: {self.done} of {self.total} {self.unit}s "
                f"({100.0 * self.done / self.total:.0f} %), {rate:.1f} {self.unit}s/s"
            )
            if 0 < self.done < self.total and rate > 0:
                text += f", about {_fmt_left((self.total - self.done) / rate)} left"
        else:
            text = f"visvec: {self.what}: {self.done} {self.unit}s, {rate:.1f} {self.unit}s/s"
        return text + (f"; {self.text}" if self.text else "")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Work:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
