"""Images read through bytes: whole, refused over the size limit, from devices."""

from __future__ import annotations

import os

import cv2
import numpy as np

import visvec.imageio as imageio
from visvec.imageio import read_image_why


def _png(tmp_path, name="a.png"):
    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    p = tmp_path / name
    p.write_bytes(cv2.imencode(".png", img)[1].tobytes())
    return p, img


def test_a_regular_file_is_read_whole_and_decoded(tmp_path):
    p, img = _png(tmp_path)
    got, why = read_image_why(p)
    assert why == "" and np.array_equal(got, img)


def test_a_file_over_the_limit_is_refused_not_decoded(tmp_path, monkeypatch):
    p, _ = _png(tmp_path)
    size = p.stat().st_size
    monkeypatch.setattr(imageio, "MAX_IMAGE_BYTES", size - 1)
    got, why = read_image_why(p)
    assert got is None and "not an image" in why
    monkeypatch.setattr(imageio, "MAX_IMAGE_BYTES", size)
    assert read_image_why(p)[1] == ""


def test_a_device_is_read_only_up_to_the_limit(monkeypatch):
    # /dev/zero has no size and no end: read up to the limit and refused
    monkeypatch.setattr(imageio, "MAX_IMAGE_BYTES", 4096)
    got, why = read_image_why("/dev/zero")
    assert got is None and "over" in why


def test_a_file_grown_since_its_size_was_taken_is_read_to_its_end(tmp_path, monkeypatch):
    p, img = _png(tmp_path)
    real = os.fstat

    class Shrunk:
        def __init__(self, st):
            self.st_mode, self.st_size = st.st_mode, st.st_size // 2

    monkeypatch.setattr(imageio.os, "fstat", lambda fd: Shrunk(real(fd)))
    got, why = read_image_why(p)
    assert why == "" and np.array_equal(got, img)
