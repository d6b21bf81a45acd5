"""Import first in a timing benchmark: BLAS and OpenMP on one thread (set before numpy
is imported, which is when they read it), and `one_core()` for OpenCV's own threads, so
that a speed figure is one core's."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def one_core() -> None:
    """OpenCV on one thread too (call once the script runs)."""
    import cv2

    cv2.setNumThreads(1)
