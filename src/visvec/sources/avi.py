"""Motion-JPEG AVI files read by their own index, so that a damaged file's frames keep
their places.

OpenCV's FFmpeg backend reads an AVI's chunks in turn and numbers the frames it gets: a
chunk lost in a damaged stretch shifts every later frame onto the number (and time) of
the one before (a row claiming another frame's time). An AVI says where each frame is:
its index (``idx1``: each chunk's id, flags, offset and size; Microsoft's AVI RIFF
reference, "AVI Index Entries"), its header the frame rate (``strh`` dwRate / dwScale)
and count. Each Motion-JPEG frame is a JPEG of its own, decoded here by its index
entry: a chunk that cannot be decoded is that frame's read error, and the frames after
it keep their numbers. A file without an index is read in chunk order while its chunks
are whole; where a chunk is not (a damaged header), the frames after it cannot be
placed, and the file is read no further (said, not guessed); where the data end (a file
cut short: its index was at the end), the frames its header still counts are read
errors in their places.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

VIDEO_IDS = (b"dc", b"db")  # compressed and uncompressed video chunks (NNdc, NNdb)


@dataclass(frozen=True)
class AviFrames:
    """Where each video frame of an AVI lies: ``offsets`` and ``sizes`` (bytes, of the
    JPEG data), the frame rate, and, when the file had no index and its chunks broke
    off, the first frame that could not be placed (``lost_from``) and how many frames the
    header says it holds."""

    path: Path
    offsets: tuple[int, ...]
    sizes: tuple[int, ...]
    fps: float
    total: int
    lost_from: int | None = None
    cut: bool = False  # the data end inside a chunk: the frames from lost_from are gone

    def __len__(self) -> int:
        return len(self.offsets)

    def image(self, i: int, fh) -> np.ndarray | None:
        """Frame ``i`` decoded (BGR), or None when its data is not a JPEG that decodes."""
        fh.seek(self.offsets[i])
        data = fh.read(self.sizes[i])
        if len(data) < self.sizes[i] or self.sizes[i] < 4:
            return None
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return img if img is not None and img.size else None


def _chunks(data: bytes, start: int, end: int):
    """(id, data start, size) of the RIFF chunks from ``start`` to ``end`` (or the end
    of the data: a file cut short)."""
    pos = start
    end = min(end, len(data))
    while pos + 8 <= end:
        cid = data[pos : pos + 4]
        (size,) = struct.unpack("<I", data[pos + 4 : pos + 8])
        yield cid, pos + 8, size
        pos += 8 + size + (size & 1)


def read_avi_index(path: str | Path) -> AviFrames | None:
    """The video frames of a Motion-JPEG AVI by its index (or, without one, its chunks
    in order); None for a file that is not one (another codec, another container, a
    header that does not parse): OpenCV reads those."""
    path = Path(path)
    try:
        # mapped, not read: a recording may be gigabytes, of which only the headers
        # and the index are looked at here
        with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            return _parse(path, data)
    except (OSError, ValueError):  # (an empty file cannot be mapped)
        return None


def _parse(path: Path, data) -> AviFrames | None:
    """read_avi_index on the file's bytes ``data``."""
    if len(data) < 12 or data[:4] != b"RIFF" or data[8:12] != b"AVI ":
        return None
    riff_end = 8 + struct.unpack("<I", data[4:8])[0]
    if data[riff_end : riff_end + 4] == b"RIFF":
        return None  # an OpenDML (AVI 2.0) file of several RIFF parts: OpenCV reads it
    movi = idx1 = None
    rate = scale = None
    total = 0
    mjpg = False
    try:
        for cid, start, size in _chunks(data, 12, riff_end):
            if cid == b"LIST" and data[start : start + 4] == b"movi":
                movi = (start, start + size)  # start: the 'movi' fourcc
            elif cid == b"LIST" and data[start : start + 4] == b"hdrl":
                for c2, s2, z2 in _chunks(data, start + 4, start + size):
                    if c2 == b"avih":
                        total = struct.unpack("<I", data[s2 + 16 : s2 + 20])[0]
                    if c2 == b"LIST" and data[s2 : s2 + 4] == b"strl":
                        for c3, s3, _z3 in _chunks(data, s2 + 4, s2 + z2):
                            if c3 == b"indx":
                                return None  # an OpenDML index: OpenCV reads it
                            if c3 == b"strh" and data[s3 : s3 + 4] == b"vids" and rate is None:
                                mjpg = data[s3 + 4 : s3 + 8].upper() in (b"MJPG", b"AVRN")
                                scale, rate = struct.unpack("<II", data[s3 + 20 : s3 + 28])
            elif cid == b"idx1":
                idx1 = (start, min(start + size, len(data)))
    except struct.error:
        return None
    if movi is None or not mjpg or not rate or not scale:
        return None
    fps = rate / scale
    offsets: list[int] = []
    sizes: list[int] = []
    lost = None
    cut = False
    if idx1 is not None:
        entries = [struct.unpack("<4sIII", data[p : p + 16])
                   for p in range(idx1[0], idx1[1] - 15, 16)]  # fmt: skip
        video = [(o, z) for cid, _f, o, z in entries if cid[2:] in VIDEO_IDS]
        if not video:
            return None
        # offsets from the 'movi' fourcc (the common form) or from the file's start
        base = movi[0] if data[movi[0] + video[0][0] : movi[0] + video[0][0] + 2][:1].isdigit() \
            else 0  # fmt: skip
        for o, z in video:
            offsets.append(base + o + 8)
            sizes.append(z)
    else:
        n = 0
        for cid, start, size in _chunks(data, movi[0] + 4, movi[1]):
            if cid[2:] in VIDEO_IDS and cid[:2].isdigit():
                offsets.append(start)
                sizes.append(size)
                n += 1
            elif not (cid.isalnum() or cid in (b"JUNK", b"LIST")):
                lost = n  # a chunk that is not one: the frames after it cannot be placed
                break
        # the file cut short inside a chunk: that frame and those after it are gone
        # (their places known: the header counts them)
        if lost is None and offsets and offsets[-1] + sizes[-1] > len(data):
            offsets.pop()
            sizes.pop()
            lost, cut = len(offsets), True
    return AviFrames(path, tuple(offsets), tuple(sizes), fps, max(total, len(offsets)), lost,
                     cut)  # fmt: skip
