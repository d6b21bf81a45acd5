"""A folder of images: read ahead by a thread on more than one CPU, in turn on one; the
same frames either way, a bad file a frame with its error."""

import cv2
import numpy as np
import pytest

from visvec.sources import folder
from visvec.sources.folder import FolderSource


@pytest.mark.parametrize("cpus", [1, 2])
def test_frames_come_in_order_whole_and_a_bad_file_is_a_frame(tmp_path, monkeypatch, cpus):
    monkeypatch.setattr(folder, "_cpus", lambda: cpus)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (24, 32), dtype=np.uint8) for _ in range(7)]
    for i, im in enumerate(images):
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), im)
    (tmp_path / "frame3.png").write_bytes(b"not a png")  # broken on disk
    frames = list(FolderSource(tmp_path, fps=10.0))
    assert [f.index for f in frames] == list(range(7))
    assert [f.time_s for f in frames] == pytest.approx([i / 10.0 for i in range(7)])
    assert frames[3].image is None and "frame3.png" in frames[3].error
    for i in (0, 1, 2, 4, 5, 6):
        np.testing.assert_array_equal(frames[i].image, images[i])


def test_a_caller_that_stops_early_is_not_held(tmp_path, monkeypatch):
    monkeypatch.setattr(folder, "_cpus", lambda: 2)
    for i in range(20):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), np.full((8, 8), i, np.uint8))
    it = iter(FolderSource(tmp_path))
    first = [next(it) for _ in range(3)]
    it.close()  # the reading thread is shut down with the files it had in hand
    assert [int(f.image[0, 0]) for f in first] == [0, 1, 2]
