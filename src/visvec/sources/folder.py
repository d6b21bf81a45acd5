"""A folder of images in natural sort order, with times from a sidecar CSV if present."""

from __future__ import annotations

import csv
import math
import os
import re
import threading
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from visvec.data import Frame
from visvec.errors import InputFileError, SourceError
from visvec.imageio import read_image_why

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
# a sidecar with columns file,time_s gives each frame's time; truth.csv from
# `visvec simulate` has them too
SIDECARS = ("times.csv", "truth.csv")
PREFETCH = 2  # files read ahead of the frame being processed


def _cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def natural_key(name: str) -> list:
    """Sort key that orders frame2 before frame10."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def to_gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image from grey, BGR or BGRA input of 8 or 16 bits."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    return image


def read_sidecar(path: Path, unix: dict[str, float] | None = None,
                 live: dict[str, tuple[int, bool]] | None = None) -> dict[str, float]:  # fmt: skip
    """file name -> time_s from a CSV with columns ``file`` and ``time_s``; with a
    ``time_unix`` column too (as `track --save-frames` writes it), file name ->
    time_unix into ``unix`` where it is a finite number; with ``frame`` and ``late``
    columns (`track --record`), file name -> (the frame's number in the live run,
    whether it was read late) into ``live``.

    Raises
    ------
    InputFileError
        A time that is not a finite number, or one that does not increase from line
        to line (the rows' times must be the recording's own), naming the line.
    """
    out: dict[str, float] = {}
    try:
        fh = open(path, newline="", encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc.strerror})") from None
    with fh:
        try:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or not {"file", "time_s"} <= set(reader.fieldnames):
                return out
            last = None
            for line, row in enumerate(reader, start=2):
                raw = row.get("time_s")
                try:
                    t = float(raw)
                except (TypeError, ValueError):
                    t = math.nan
                if not math.isfinite(t):
                    raise InputFileError(
                        f"{path}: line {line}: time_s = {raw!r}, expected a finite number"
                    )
                if last is not None and t <= last[1]:
                    raise InputFileError(
                        f"{path}: line {line}: time_s = {raw} does not increase (line "
                        f"{last[0]} has {last[1]}); a recording's times must increase"
                    )
                last = (line, t)
                out[row["file"]] = t
                if unix is not None and row.get("time_unix"):
                    try:
                        u = float(row["time_unix"])
                    except ValueError:
                        u = math.nan
                    if math.isfinite(u):
                        unix[row["file"]] = u
                if live is not None and (row.get("frame") or "").strip():
                    try:
                        live[row["file"]] = (int(row["frame"]), row.get("late", "").strip() == "1")
                    except ValueError:
                        raise InputFileError(f"{path}: line {line}: frame = {row['frame']!r}, "
                                             "expected a whole number") from None  # fmt: skip
        except UnicodeDecodeError:
            raise InputFileError(f"{path}: not a UTF-8 text file") from None
        except csv.Error as exc:
            raise InputFileError(f"{path}: not a CSV file ({exc})") from None
    return out


class FolderSource:
    """Frames from the image files of a folder (natural sort order).

    Parameters
    ----------
    path : folder
    fps : float
        Frame rate for ``time_s = index / fps`` when there is no sidecar time.
    files : list of Path, optional
        Use these files instead of the folder's listing.

    Raises
    ------
    SourceError
        If the folder does not exist or holds no image.
    """

    def __init__(self, path: str | Path, fps: float = 30.0, files: list[Path] | None = None):
        self.path = Path(path)
        if files is None:
            if not self.path.is_dir():
                raise SourceError(f"{self.path}: no such folder")
            files = [
                p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
            ]
            files.sort(key=lambda p: natural_key(p.name))
        if not files:
            raise SourceError(f"{self.path}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
        self.files = files
        self.fps = fps
        self.times: dict[str, float] = {}
        self.unix: dict[str, float] = {}
        # a live run's recording (`track --record`): each file's frame number in the
        # run and whether it was read late, so that a replay's rows are the run's
        self.live: dict[str, tuple[int, bool]] = {}
        self.times_from: str | None = None  # the sidecar the frames' times come from
        for name in SIDECARS:
            side = self.path / name
            if side.is_file():
                self.times = read_sidecar(side, self.unix, self.live)
                if self.times:
                    self.times_from = name
                    break

    def __len__(self) -> int:
        return len(self.files)

    def _frame(self, i: int, f: Path) -> Frame:
        t = self.times.get(f.name, i / self.fps)
        u = self.unix.get(f.name)
        late = None
        if f.name in self.live:
            i, was_late = self.live[f.name]
            if was_late:
                late = threading.Event()
                late.set()
        img, why = read_image_why(f)
        if img is None:
            return Frame(i, t, None, f.name, error=f"{f.name}: {why}", time_unix=u,
                         read_late=late)  # fmt: skip
        return Frame(i, t, to_gray(img), f.name, time_unix=u, read_late=late)

    def __iter__(self) -> Iterator[Frame]:
        """The frames in order. The next PREFETCH files are read and decoded by a
        thread while the caller works on the current frame (OpenCV's decoding lets go
        of the GIL): on two cores a recording is processed in about the time of the
        slower of the two, not their sum. A caller that stops early waits only for the
        files already being read. On one CPU the thread only adds its switching: the
        files are read in turn there."""
        if _cpus() < 2:
            for i, f in enumerate(self.files):
                yield self._frame(i, f)
            return
        with ThreadPoolExecutor(1, thread_name_prefix="visvec-read") as ex:
            files = iter(enumerate(self.files))
            pending: deque[Future] = deque()

            def ahead() -> None:
                nxt = next(files, None)
                if nxt is not None:
                    pending.append(ex.submit(self._frame, *nxt))

            for _ in range(max(PREFETCH, 1)):
                ahead()
            while pending:
                frame = pending.popleft().result()
                ahead()
                yield frame
