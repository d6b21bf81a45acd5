"""A USB camera's exposure, gain and focus from the rig's [camera] keys: set, read back,
said; a refused control named with the value the camera kept. The camera is a stand-in
for cv2.VideoCapture that behaves as V4L2 does."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from visvec.errors import ConfigError
from visvec.rig import load_rig
from visvec.sources.video import VideoSource

from conftest import ROOT

RIG = ROOT / "configs" / "triangle.toml"


class V4l2Like:
    """V4L2 as OpenCV shows it: auto-exposure a menu (1 manual, 3 aperture priority),
    an exposure kept only in manual mode, a gain this camera does not have (reads 0),
    focus kept only with autofocus off. Starts in auto-exposure and autofocus."""

    def __init__(self, *args, **kwargs):
        self.p = {
            cv2.CAP_PROP_AUTO_EXPOSURE: 3.0,
            cv2.CAP_PROP_EXPOSURE: 156.0,
            cv2.CAP_PROP_GAIN: 0.0,
            cv2.CAP_PROP_AUTOFOCUS: 1.0,
            cv2.CAP_PROP_FOCUS: 40.0,
            cv2.CAP_PROP_FRAME_WIDTH: 640.0,
            cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
            cv2.CAP_PROP_FPS: 30.0,
        }

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE and value not in (1.0, 3.0):
            return False
        if prop == cv2.CAP_PROP_EXPOSURE and self.p[cv2.CAP_PROP_AUTO_EXPOSURE] != 1.0:
            return False
        if prop == cv2.CAP_PROP_GAIN:
            return False
        if prop == cv2.CAP_PROP_FOCUS and self.p[cv2.CAP_PROP_AUTOFOCUS] != 0.0:
            return False
        if prop in self.p:
            self.p[prop] = float(value)
            return True
        return False

    def get(self, prop):
        return self.p.get(prop, 0.0)

    def read(self):
        return True, np.zeros((480, 640, 3), np.uint8)

    def release(self):
        pass


def rig_with(tmp_path: Path, lines: str):
    text = RIG.read_text().replace("[camera]\n", "[camera]\n" + lines + "\n", 1)
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return load_rig(p)


@pytest.fixture
def fake_camera(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", V4l2Like)


def test_controls_set_read_back_and_said(tmp_path, fake_camera):
    rig = rig_with(tmp_path, "exposure = 300\nfocus = 0\nauto_focus = false")
    src = VideoSource(0, controls=rig.controls, size=(640, 480))
    # an exposure turns auto-exposure off first (V4L2 keeps it only in manual mode)
    assert src.cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) == 1.0
    assert src.cap.get(cv2.CAP_PROP_EXPOSURE) == 300.0
    assert src.cap.get(cv2.CAP_PROP_FOCUS) == 0.0
    (line,) = src.settings
    assert "exposure 300 (auto-exposure off)" in line and "focus 0 (autofocus off)" in line
    assert src.settings_warnings == []


def test_refused_control_named_with_the_value_kept(tmp_path, fake_camera):
    rig = rig_with(tmp_path, "gain = 4\nauto_exposure = false\nexposure = 200")
    src = VideoSource(0, controls=rig.controls)
    assert "camera 0: refused [camera] gain = 4; it kept 0" in src.settings_warnings
    # autofocus was left on: said, since a refocus moves the measurement
    assert any("autofocus is on" in w for w in src.settings_warnings)
    assert not any("auto-exposure is on" in w for w in src.settings_warnings)


def test_automatic_settings_left_on_are_warned(fake_camera):
    src = VideoSource(0)
    ws = " ".join(src.settings_warnings)
    assert "auto-exposure is on" in ws and "autofocus is on" in ws
    assert "exposure 156 (auto-exposure on)" in src.settings[0]


@pytest.mark.parametrize(
    "lines, match",
    [
        ("exposure = 300\nauto_exposure = true", "auto_exposure = false"),
        ("focus = 10\nauto_focus = true", "auto_focus = false"),
        ("auto_exposure = 1", "expected true or false"),
        ("gain = -1", "gain"),
    ],
)
def test_contradictory_or_bad_controls_refused(tmp_path, lines, match):
    with pytest.raises(ConfigError, match=match):
        rig_with(tmp_path, lines)


def test_a_file_or_stream_gets_no_controls(fake_camera):
    src = VideoSource("http://127.0.0.1:9/stream.mjpg", retry_s=0.1)
    assert src.controls is None and src.settings == []
