"""The edge fit's named results (visvec.detect.edges, its compiled kernels in
visvec.detect._compiled): NamedTuples, which Numba builds and reads as it does plain
tuples, so that the numpy and the compiled fit return the same names."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class EdgeLines(NamedTuple):
    """The three edges' total-least-squares lines (edges._robust_lines, _lines).

    Attributes
    ----------
    normals : ndarray, shape (3, 2)
        Unit normals (into the triangle, after edges._lines).
    offsets : ndarray, shape (3,)
        n . x on each line (ideal px).
    centres : ndarray, shape (3, 2)
        The mean of each edge's inliers (ideal px).
    spreads : ndarray, shape (3,)
        The sum of the inliers' squared distances along the line from its centre
        (px^2): a line's turn about its centre has the variance sigma^2 / spread.
    sigmas : ndarray, shape (3,)
        A point's 1-sigma across its line (px): the residuals', inflated for the
        profiles' shared pixels, at least the floor.
    keep : ndarray of bool, shape (M,)
        The inliers.
    """

    normals: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray
    spreads: np.ndarray
    sigmas: np.ndarray
    keep: np.ndarray
