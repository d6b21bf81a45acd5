"""Finding targets in images: the triangle (triangle, from candidates and its edges),
bright spots (spots) for the markers (markers) and ceiling lamps (lamps), stars and
their flow between frames (stars, flow)."""

from visvec.detect.triangle import TriangleDetector

__all__ = ["TriangleDetector"]
