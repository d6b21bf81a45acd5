"""Frames through the codecs labs record with: each frame alone through JPEG (as
Motion-JPEG stores it), or the whole sequence through OpenCV's mp4v (MPEG-4 part 2)
writer, or through H.264 as a network camera streams it (PyAV's libx264, the bench
extra), and back through OpenCV's reader (benchmarks/triangle_compression.py, and the
tests of the learned edge correlation)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np

from visvec.sources.video import codec_of


def jpeg(images: list[np.ndarray], quality: int) -> list[np.ndarray]:
    """Each grey frame encoded alone at JPEG ``quality`` and decoded."""
    out = []
    for im in images:
        ok, buf = cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out.append(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
    return out


def mp4v(images: list[np.ndarray], fps: float = 30.0, with_codec: bool = False):
    """The grey frames as OpenCV's mp4v writer stores them at its default quality and
    its reader gives them back; ``with_codec``: and the codec's FOURCC as the reader
    names it (visvec.sources.video.codec_of: "FMP4"), which `visvec batch` puts on each
    frame of such a file (Frame.codec)."""
    h, w = images[0].shape
    with tempfile.TemporaryDirectory() as d:
        path = str(Path(d) / "rec.mp4")
        writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        for im in images:
            writer.write(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))
        writer.release()
        out, codec = _read_back(path, len(images), "mp4v")
    return (out, codec) if with_codec else out


def h264(images: list[np.ndarray], fps: float = 30.0, crf: int = 23, gop: int = 30):
    """The grey frames through H.264 as an IP camera streams it (libx264 through PyAV:
    constant quality ``crf``, 23 being x264's default; a key frame every ``gop`` frames;
    no B-frames, as for low latency; 4:2:0 at the video range 16-235), read back through
    OpenCV, and the codec's FOURCC as its reader names it ("h264"). Needs PyAV (the
    bench extra: OpenCV's own FFmpeg has no H.264 encoder)."""
    import av

    h, w = images[0].shape
    with tempfile.TemporaryDirectory() as d:
        path = str(Path(d) / "rec.mp4")
        with av.open(path, "w") as out:
            st = out.add_stream("libx264", rate=int(round(fps)))
            st.width, st.height, st.pix_fmt = w, h, "yuv420p"
            st.options = {"crf": str(crf), "g": str(gop), "bf": "0", "preset": "veryfast",
                          "tune": "zerolatency"}  # fmt: skip
            for im in images:
                frame = av.VideoFrame.from_ndarray(im, format="gray").reformat(format="yuv420p")
                for packet in st.encode(frame):
                    out.mux(packet)
            for packet in st.encode():
                out.mux(packet)
        return _read_back(path, len(images), "H.264")


def _read_back(path: str, n: int, what: str) -> tuple[list[np.ndarray], str]:
    """The ``n`` grey frames of the video at ``path`` as OpenCV's reader gives them,
    and the codec's FOURCC as it names it (visvec.sources.video.codec_of)."""
    cap = cv2.VideoCapture(path)
    codec = codec_of(cap)
    out = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    cap.release()
    if len(out) != n:
        raise RuntimeError(f"{what} round trip gave {len(out)} of {n} frames")
    return out, codec
