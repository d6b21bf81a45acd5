"""Images read and written through bytes.

OpenCV's path-taking readers and writers (cv2.imread, cv2.imwrite) take a C string:
a file name that is not valid UTF-8 (a byte such as 0xff, which Linux allows) crashes
them in some builds and fails in others. Reading the file's bytes in Python and
decoding them with cv2.imdecode (and cv2.imencode for writing) works for any name.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import cv2
import numpy as np

MAX_IMAGE_BYTES = 512 * 1024 * 1024  # a bigger "image" (say /dev/zero) is not read


def read_image(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """The decoded image, or None when the file cannot be read or decoded."""
    return read_image_why(path, flags)[0]


def read_image_why(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED):
    """(the decoded image, "") or (None, why not). A JPEG cut short (no end-of-image
    marker) is refused: libjpeg would fill its missing rows with grey, with a warning
    that names no file."""
    try:
        with open(path, "rb") as fh:
            data = _read_at_most(fh, MAX_IMAGE_BYTES + 1)
    except OSError as exc:
        return None, f"cannot read ({exc.strerror})"
    if not data:
        return None, "an empty file"
    if len(data) > MAX_IMAGE_BYTES:
        return None, f"over {MAX_IMAGE_BYTES >> 20} MiB: not an image"
    if data[:2] == b"\xff\xd8" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        return None, "a JPEG cut short (no end-of-image marker)"
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        return None, "cannot decode the image"
    return img, ""


def _read_at_most(fh, limit: int) -> bytes:
    """Up to ``limit`` bytes of the open file ``fh``. A regular file is read at its own
    size (and on, should it have grown): asking for ``limit`` bytes at once allocates
    them (0.1 ms a frame for a 512 MiB limit, on a 140 kB PNG that reads in 0.016 ms).
    A device or pipe, whose size is not known, is read up to the limit."""
    st = os.fstat(fh.fileno())
    if not stat.S_ISREG(st.st_mode):
        return fh.read(limit)
    data = fh.read(min(st.st_size + 1, limit))
    if len(data) > st.st_size and len(data) < limit:  # grown since: the rest too
        data += fh.read(limit - len(data))
    return data


def write_image(path: str | Path, img: np.ndarray) -> bool:
    """Write ``img`` in the format its suffix names (.png by default); False if it
    cannot be encoded or written."""
    ext = Path(path).suffix.lower() or ".png"
    ok, buf = cv2.imencode(ext, img)
    if not ok:
        return False
    try:
        with open(path, "wb") as fh:
            fh.write(buf.tobytes())
    except OSError:
        return False
    return True


def opencv_path(path: str | Path) -> str | None:
    """``path`` as OpenCV's C functions can take it, or None if its bytes are not
    UTF-8 (see the module docstring)."""
    raw = os.fsencode(path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
