"""Video files through cv2.VideoCapture: what each frame says of its codec."""

import cv2
import numpy as np
import pytest

from visvec.data import inter_frame
from visvec.sources.open import open_source


def _video(path, fourcc: str, n: int = 4) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (160, 120))
    assert w.isOpened(), fourcc
    for k in range(n):
        img = np.full((120, 160, 3), 40, np.uint8)
        cv2.circle(img, (40 + 20 * k, 60), 15, (200, 200, 200), -1)
        w.write(img)
    w.release()


def test_each_frame_names_the_codec_it_came_through(tmp_path):
    """An mp4v file's frames say FMP4 (a codec that predicts frames from earlier ones),
    a Motion-JPEG file's MJPG (each frame alone), an FFV1 file's ffv1 (lossless, each
    frame alone); image files say nothing."""
    seen = {}
    for fourcc, name in (("mp4v", "a.mp4"), ("MJPG", "b.avi"), ("FFV1", "c.mkv")):
        _video(tmp_path / name, fourcc)
        frames = list(open_source(str(tmp_path / name), fps=10.0, retry_s=0.0))
        assert len(frames) == 4 and all(f.image is not None for f in frames)
        (seen[fourcc],) = {f.codec for f in frames}
    assert seen == {"mp4v": "FMP4", "MJPG": "MJPG", "FFV1": "ffv1"}
    assert [inter_frame(seen[k]) for k in ("mp4v", "MJPG", "FFV1")] == [True, False, False]
    cv2.imwrite(str(tmp_path / "f.png"), np.zeros((20, 30), np.uint8))
    (frame,) = open_source(str(tmp_path / "f.png"))
    assert frame.codec == "" and not inter_frame(frame.codec)


def test_which_codecs_predict_frames_from_earlier_ones():
    """H.264, HEVC, VP9, AV1 and MPEG-4 do, under any of their names and cases; JPEG,
    PNG, the lossless codecs and a camera's raw pixel formats do not; an unnamed codec is
    not taken to."""
    for codec in ("FMP4", "h264", "avc1", "H264", "hev1", "hvc1", "VP90", "av01", "XVID"):
        assert inter_frame(codec), codec
    for codec in ("", "MJPG", "mjpg", "jpeg", "MPNG", "ffv1", "HFYU", "YUYV", "GREY", "Y800"):
        assert not inter_frame(codec), codec


def test_an_h264_recording_names_its_codec_and_keeps_its_frames():
    """The benchmarks' H.264 round trip (PyAV's libx264, the bench extra): every frame
    back, within a few grey levels on a flat board (4:2:0 at the video range), and the
    codec OpenCV's reader names is one that predicts frames from earlier ones."""
    pytest.importorskip("av")
    from visvec.bench.codecs import h264

    images = []
    for k in range(12):
        img = np.full((96, 128), 70, np.uint8)
        cv2.circle(img, (30 + 5 * k, 48), 15, 98, -1)
        images.append(img)
    frames, codec = h264(images, fps=10.0)
    assert codec == "h264" and inter_frame(codec)
    assert len(frames) == 12 and frames[0].shape == (96, 128)
    assert abs(float(np.median(frames[5][:, 100:])) - 70.0) <= 2.0
