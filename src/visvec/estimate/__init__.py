"""Attitude estimators for the triangle target."""

from visvec.estimate.triangle_full import solve_full
from visvec.estimate.triangle_paper import solve_paper

ESTIMATORS = {"full": solve_full, "paper": solve_paper}

__all__ = ["ESTIMATORS", "solve_full", "solve_paper"]
