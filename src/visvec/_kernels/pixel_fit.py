"""The pixel fit's named results and settings (visvec.detect.photometric, its compiled
kernels in visvec.detect._compiled): NamedTuples, which Numba builds and reads as it
does plain tuples, so that the numpy and the compiled fit return the same names."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class GaussNewtonSteps(NamedTuple):
    """After the pixel fit's Gauss-Newton steps (photometric._gauss_newton).

    Attributes
    ----------
    n : ndarray, shape (3, 2)
        The lines' unit normals (into the triangle).
    c : ndarray, shape (3, 2)
        The lines' centres (ideal px).
    w : ndarray, shape (3,)
        The edges' blur widths (px, the model's w).
    level : ndarray, shape (6,)
        The level planes' coefficients: the board's (1, x, y), then the contrast's
        (grey levels; x, y about the centroid, scaled).
    H : ndarray, shape (15, 15)
        The last step's normal matrix J^T J.
    b : ndarray, shape (15,)
        The last step's J^T r.
    rss : float
        The residual sum of squares after the last step, as Gauss-Newton predicts it
        (grey levels^2).
    r : ndarray, shape (M,)
        The last pass's residuals (grey levels).
    g : ndarray, shape (M,)
        The last pass's dI / d(distance) (grey levels per px).
    ok : bool
        False where a system was singular.
    """

    n: np.ndarray
    c: np.ndarray
    w: np.ndarray
    level: np.ndarray
    H: np.ndarray
    b: np.ndarray
    rss: float
    r: np.ndarray
    g: np.ndarray
    ok: bool


class PixelSolve(NamedTuple):
    """The pixel fit's answer on a frame's bands (photometric._solve).

    Attributes
    ----------
    ok : bool
        Whether the fit is to be taken.
    V : ndarray, shape (3, 2)
        The vertices (ideal px; the starting ones when it is not taken).
    cov : ndarray, shape (6, 6)
        Their covariance (px^2; NaN, or None from numpy, when not taken).
    w : ndarray, shape (3,)
        The blur widths (px).
    s2 : float
        The residuals' variance (grey levels^2).
    inflation : float
        The covariance's factor for the noise's correlation.
    steps : int
        The Gauss-Newton steps taken on every pixel.
    """

    ok: bool
    V: np.ndarray
    cov: np.ndarray | None
    w: np.ndarray
    s2: float
    inflation: float
    steps: int


class PixelFitSettings(NamedTuple):
    """The pixel fit's constants as its compiled solve takes them (photometric's
    module constants; see there what each does).

    Attributes
    ----------
    steps : int
        GN_STEPS, a run's first fit's Gauss-Newton steps.
    stride : int
        FIRST_STRIDE, the pixels the steps before the last take.
    lags : ndarray, shape (L, 2)
        The half-plane's lags (px) of the noise correlation.
    lag_px : int
        NOISE_LAG_PX.
    min_pairs : int
        NOISE_MIN_PAIRS.
    rms_ratio : float
        EDGE_RMS_RATIO.
    settled : float
        WIDTH_SETTLED.
    warm_steps : int
        WARM_STEPS.
    table : ndarray, shape (N + 1, 4)
        The blurred step's Hermite table (photometric._PHI).
    rng : float
        PHI_RANGE.
    inv_step : float
        1 / PHI_STEP.
    """

    steps: int
    stride: int
    lags: np.ndarray
    lag_px: int
    min_pairs: int
    rms_ratio: float
    settled: float
    warm_steps: int
    table: np.ndarray
    rng: float
    inv_step: float
