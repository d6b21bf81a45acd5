"""Pick the source for a command-line PATH / camera argument."""

from __future__ import annotations

from pathlib import Path

from visvec.errors import SourceError
from visvec.imageio import opencv_path
from visvec.sources.folder import IMAGE_SUFFIXES, FolderSource, natural_key
from visvec.sources.video import VideoSource


def open_source(
    spec: str | int,
    fps: float = 30.0,
    max_frames: int | None = None,
    retry_s: float = 5.0,
    size: tuple[int, int] | None = None,
    controls=None,
):
    """A camera index ("0"), a folder of images, a single image, a video file or a URL.

    Parameters
    ----------
    spec : str or int
        What to open: a camera index, a folder (its images in natural order, times
        from a ``times.csv`` beside them), an image, a video, or an ``http://`` or
        ``rtsp://`` stream.
    fps : float
        The frame rate (Hz) a source without its own times is timed by.
    max_frames : int, optional
        Stop after this many frames.
    retry_s : float
        How long (s) a camera or stream that stops delivering is retried.
    size : (int, int), optional
        The (width, height) in px a camera is asked for.
    controls : optional
        The rig's camera controls (exposure, gain, focus).

    Returns
    -------
    iterable of Frame
        Each with its ``index``, ``time_s`` (s from the first), grey ``image``
        (uint8, H x W) or an ``error``.

    Raises
    ------
    SourceError
        A source that cannot be opened (exit 3 on the command line).

    A camera is asked for ``size`` (width, height) and ``fps``, and refused if it cannot
    deliver that size (see :class:`VideoSource`), and set to ``controls`` (the rig's
    exposure, gain and focus)."""
    if isinstance(spec, int) or (isinstance(spec, str) and spec.isdigit()):
        return VideoSource(int(spec), fps=fps, retry_s=retry_s, max_frames=max_frames, size=size,
                           controls=controls)  # fmt: skip
    if "://" in spec:
        return VideoSource(spec, fps=fps, retry_s=retry_s, max_frames=max_frames)
    p = Path(spec)
    if p.is_dir():
        return FolderSource(p, fps=fps)
    if not p.exists() and any(c in spec for c in "*?["):
        # a pattern the shell did not expand (quoted): its images, in natural order
        files = sorted(
            (f for f in p.parent.glob(p.name) if f.suffix.lower() in IMAGE_SUFFIXES),
            key=lambda f: natural_key(f.name),
        )
        if not files:
            raise SourceError(f"{spec}: no image matches the pattern")
        return FolderSource(p.parent, fps=fps, files=files)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    if p.suffix.lower() in IMAGE_SUFFIXES:
        return FolderSource(p.parent, fps=fps, files=[p])
    if not p.is_file():
        # a FIFO or a device: OpenCV's reader would block on it for ever, deaf to Ctrl-C
        raise SourceError(
            f"{p}: not a regular file (a pipe or a device); give a video file, a folder, a "
            "camera index or a stream URL"
        )
    if opencv_path(p) is None:
        raise SourceError(
            f"{p}: the file name is not UTF-8, which OpenCV's video reader cannot take; "
            "rename the file"
        )
    return VideoSource(str(p), fps=fps, retry_s=retry_s, max_frames=max_frames)
