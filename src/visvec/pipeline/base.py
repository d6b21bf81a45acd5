"""What every target kind's pipeline shares: frame checks, the safety net for bugs,
the physically-possible tilt check, latency, the closing note on refused frames."""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from typing import Generic, TypeVar

from visvec.data import AttitudeSolution, Frame, Status
from visvec.errors import ConfigError
from visvec.output import AttitudeRow, Row, attitude_row
from visvec.rig import Rig

# the run's closing note on its refused frames: when at least this share of its frames
# and at least this many were not ok
REFUSED_NOTE_SHARE = 0.1
REFUSED_NOTE_MIN = 3
# the reasons the note names (the most frequent first)
REFUSED_NOTE_REASONS = 4


# what a kind's detector finds in a frame, and what its estimator makes of it
DetT = TypeVar("DetT")
SolT = TypeVar("SolT")


class Pipeline(Generic[DetT, SolT]):
    """Shared frame loop of every target kind (make one with `make_pipeline`).
    Subclasses implement :meth:`estimate` (a frame -> status, solution of type SolT or
    None, warnings; the detection of type DetT is kept as ``last_detection`` for the
    overlay) and :meth:`make_row` (-> a row of ``row_type``).

    Parameters
    ----------
    rig : Rig
        The setup (`load_rig`).
    method : str
        The estimator (see `make_pipeline`).
    """

    methods: tuple[str, ...] = ()
    row_type: type[Row] = Row
    # what to check when many frames are refused with a warning code (or a status)
    hints: dict[str, str] = {
        "read_error": "frames unreadable or not the rig's [camera] width x height",
        "internal_error": "a bug met on those frames (each printed above): please report it",
    }

    def __init__(self, rig: Rig, method: str = "full"):
        if method not in self.methods:
            raise ConfigError(
                f"method = {method!r} for a {rig.kind} rig: expected one of {list(self.methods)}"
            )
        self.rig = rig
        self.method = method
        self.last_detection: DetT | None = None
        self.last_solution: SolT | None = None
        self.last_error = ""
        # the run's rows, and its refused ones by reason (their warnings, or the status)
        self.n_rows = 0
        self.refused: Counter[str] = Counter()

    def check_frame(self, frame: Frame) -> str:
        """Why a frame cannot be used at all ("" if it can)."""
        if frame.image is None:
            return frame.error or "unreadable frame"
        img = frame.image
        cam = self.rig.camera
        if img.ndim != 2 or img.size == 0:
            return f"{frame.name}: expected a grey image, got shape {img.shape}"
        if img.shape != (cam.height, cam.width):
            return (
                f"{frame.name}: image is {img.shape[1]}x{img.shape[0]}, expected "
                f"{cam.width}x{cam.height} (the rig's camera)"
            )
        return ""

    def reset(self) -> None:
        """Forget the previous frame."""

    def after_failure(self) -> None:
        """Called after a frame without an ok row (forgets the previous frame)."""
        self.reset()

    def estimate(self, frame: Frame) -> tuple[Status, SolT | None, tuple[str, ...]]:
        """Status, solution (or None) and warnings of one readable frame."""
        raise NotImplementedError

    def make_row(
        self,
        frame: Frame,
        status: Status,
        sol: SolT | None,
        warnings: tuple[str, ...],
        latency_ms: float,
    ) -> Row:
        raise NotImplementedError

    def check_solution(
        self, status: Status, sol: SolT, warnings: tuple[str, ...]
    ) -> tuple[Status, tuple[str, ...]]:
        """A last physical check of an ok solution (none by default)."""
        return status, warnings

    def after_success(self, sol: SolT) -> None:
        """Called with the solution of every row that is ok (nothing by default)."""

    def notes(self) -> list[str]:
        """What the run found out about the rig, for the operator at its end: here, why
        its frames were refused when many were (:meth:`refused_note`)."""
        note = self.refused_note()
        return [note] if note else []

    def refused_note(self) -> str:
        """The refused rows by reason, with what to check for each (``hints``), when
        REFUSED_NOTE_SHARE of the run's rows (at least REFUSED_NOTE_MIN) were not ok;
        "" otherwise."""
        n_bad = sum(self.refused.values())
        if n_bad < max(REFUSED_NOTE_MIN, REFUSED_NOTE_SHARE * self.n_rows):
            return ""
        top = self.refused.most_common(REFUSED_NOTE_REASONS)
        counts = ", ".join(f"{reason} {n}" for reason, n in top)
        if len(self.refused) > len(top):
            counts += ", other reasons " + str(n_bad - sum(n for _, n in top))
        codes = dict.fromkeys(c for reason, _ in top for c in reason.split(";"))
        hints = [f"{c}: {self.hints[c]}" for c in codes if c in self.hints]
        text = f"visvec: {n_bad} of {self.n_rows} frames not ok ({counts})"
        return text + ("; " + "; ".join(hints) if hints else "")

    def process(self, frame: Frame, t_in: float | None = None) -> Row:
        """The row of one frame; never raises on frame content."""
        row = self._process(frame, t_in)
        if frame.time_unix is not None:
            row = replace(row, time_unix=frame.time_unix)
        if row.ok and frame.late:
            # right values of an unknown moment: said, and never taken for a fix
            row = replace(row, warnings=row.warnings + ("read_late",))
        self.n_rows += 1
        if not row.ok:
            self.refused[row.reason] += 1
        return row

    def _process(self, frame: Frame, t_in: float | None) -> Row:
        t_in = time.perf_counter() if t_in is None else t_in
        self.last_detection, self.last_solution, self.last_error = None, None, ""
        if self.check_frame(frame):
            self.reset()
            return self.make_row(frame, Status.READ_ERROR, None, ("read_error",), _ms(t_in))
        try:
            status, sol, warnings = self.estimate(frame)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not end the run
            # a bug met on this frame's content: refuse the frame, keep the run going,
            # and keep the message for the caller to report
            self.last_error = f"{type(exc).__name__}: {exc}"
            self.reset()
            return self.make_row(frame, Status.REJECTED, None, ("internal_error",), _ms(t_in))
        self.last_solution = sol
        if status is Status.OK and sol is not None:
            status, warnings = self.check_solution(status, sol, warnings)
        if status is Status.OK:
            self.after_success(sol)
        else:
            self.after_failure()
        return self.make_row(frame, status, sol, warnings, _ms(t_in))

    def run(
        self, frames: Iterable[Frame], on_frame: Callable[[Frame, Row], None] | None = None
    ) -> Iterator[Row]:
        """Rows of all frames, lazily; ``on_frame`` sees each frame with its row."""
        for frame in frames:
            row = self.process(frame)
            if on_frame is not None:
                on_frame(frame, row)
            yield row


class AttitudePipeline(Pipeline[DetT, AttitudeSolution]):
    """Attitude rows (triangle, markers), with the physically-possible tilt check."""

    row_type = AttitudeRow

    def make_row(self, frame, status, sol, warnings, latency_ms):
        return attitude_row(frame.index, frame.time_s, sol, status, warnings, latency_ms)

    def check_solution(self, status, sol, warnings):
        tilt = math.degrees(math.acos(min(max(float(sol.R_nb[2, 2]), -1.0), 1.0)))
        if tilt > self.rig.max_tilt_deg:
            return Status.REJECTED, warnings + ("impossible_tilt",)
        return status, warnings


def _ms(t_in: float) -> float:
    return (time.perf_counter() - t_in) * 1000.0
