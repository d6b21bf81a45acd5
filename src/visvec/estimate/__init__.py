"""Estimators: the triangle's attitude (triangle_full, the default; triangle_paper, the
VVS paper's), the markers' (markers; pnp, OpenCV's baselines), the lamps' planar pose
(planar), the star field's angular rate (rate), and a rolling shutter's readout from
the triangle's shear (shear). ESTIMATORS names the triangle's two."""

from visvec.estimate.triangle_full import solve_full
from visvec.estimate.triangle_paper import solve_paper

ESTIMATORS = {"full": solve_full, "paper": solve_paper}

__all__ = ["ESTIMATORS", "solve_full", "solve_paper"]
