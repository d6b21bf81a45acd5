"""Finding targets in images."""

from visvec.detect.triangle import TriangleDetector

__all__ = ["TriangleDetector"]
