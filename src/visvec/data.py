"""Data passed between the pipeline stages (frozen dataclasses, documented shapes)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np


class Status(StrEnum):
    """Outcome of one frame, as written in the ``status`` column.

    Attributes
    ----------
    OK : "ok"
        Values with their sigma.
    NO_TARGET : "no_target"
        Nothing of the target found (or, fused, no fix yet).
    REJECTED : "rejected"
        Found but refused (its warnings say why: occluded, out of view, ...).
    NOT_CONVERGED : "not_converged"
        The fit did not converge.
    READ_ERROR : "read_error"
        The frame could not be read or decoded.
    """

    OK = "ok"
    NO_TARGET = "no_target"
    REJECTED = "rejected"
    NOT_CONVERGED = "not_converged"
    READ_ERROR = "read_error"


# codecs that code every frame alone (FOURCCs, upper case, as cv2.CAP_PROP_FOURCC gives
# them): JPEG and lossless ones, and raw pixel formats (a camera's YUYV, a Bayer mosaic).
# Every other codec named is taken to predict frames from earlier ones (mp4v reads as
# FMP4, H.264 as h264 or avc1, HEVC, VP8/9, AV1): their errors move with the image
# (benchmarks/triangle_compression.py)
INTRA_CODECS = frozenset(
    "MJPG JPEG MJPA MJPB LJPG JPGL AVRN MPNG PNG FFV1 FFVH HFYU MJ2C MJP2 DVSD DV25 DV50 "
    "APCN APCH APCS APCO AP4H UTVD ULRG ULRA ULY0 ULY2 ULY4 ULH0 ULH2 ULH4 "
    "RAW RGB BGR RGB3 BGR3 RGBA BGRA ARGB DIB Y800 GREY GRAY Y8 Y16 Y10 Y12 YUYV YUY2 YVYU "
    "UYVY VYUY I420 IYUV YV12 NV12 NV21 422P BA81 GBRG GRBG RGGB BGGR".split()
)


def inter_frame(codec: str) -> bool:
    """Whether frames of ``codec`` (a FOURCC, see
    :func:`visvec.sources.video.codec_of`) may be predicted
    from earlier frames (motion-compensated: mp4v, H.264, HEVC, VP9, AV1): any codec
    named that is not in INTRA_CODECS. An empty name (an image file, a source that does
    not say) is not."""
    return bool(codec) and codec.upper() not in INTRA_CODECS


@dataclass(frozen=True)
class Frame:
    """One image from a source.

    Attributes
    ----------
    index : int
        0-based index of the frame in its source.
    time_s : float
        Exposure time of the frame in seconds.
    image : (H, W) uint8 ndarray or None
        Grey image; None when the frame could not be read (see ``error``).
    name : str
        File name or a description of where the frame came from.
    error : str
        Why the frame could not be read (empty when ``image`` is set).
    time_unix : float or None
        Its absolute time (s since 1970, UTC) where the source knows it: a live
        source's capture clock, a recording's times.csv with a time_unix column.
    codec : str
        The video codec the frame was decoded from, as its FOURCC (``"FMP4"`` for
        mp4v, ``"h264"``, ``"MJPG"``), where the source knows it; empty for image files
        and sources that do not say (see :func:`inter_frame`).
    read_late : threading.Event or None
        Set (by a live source's reader, possibly after the frame was handed out) when
        the frame's time is the moment it was read and it had waited in a queue
        first, so its exposure was earlier by an unknown amount (see :attr:`late`);
        None where the time does not depend on when the frame was read.
    """

    index: int
    time_s: float
    image: np.ndarray | None
    name: str = ""
    error: str = ""
    time_unix: float | None = None
    codec: str = ""
    read_late: threading.Event | None = None

    @property
    def late(self) -> bool:
        """Whether ``time_s`` is later than the exposure by an unknown amount (the
        frame was read late): its row is warned ``read_late``, and it is no fix."""
        return self.read_late is not None and self.read_late.is_set()


@dataclass(frozen=True)
class Detection:
    """Triangle vertices found in one image.

    Attributes
    ----------
    status : Status
        ``OK`` when the vertices may be used.
    points_px : (3, 2) float ndarray
        Vertices in distorted pixel coordinates (u, v), the most acute first, the
        other two in the order of the rig file.
    points_n : (3, 2) float ndarray
        The same vertices undistorted, in normalised image coordinates (x/z, y/z).
    cov_n : (6, 6) float ndarray
        Covariance of ``points_n.ravel()``.
    consider_n : (6, 6) float ndarray or None
        Covariance of ``points_n.ravel()`` from an error the detector could not take
        out (a rolling shutter's unknown rate, or its readout's error at a known rate),
        added to ``cov_n`` in the fit's weights.
    shutter_gain_n : (6, 3) float ndarray or None
        For a rolling-shutter rig: how ``points_n.ravel()`` move per rad/s of camera
        rate (camera axes) when the rows are taken to the centre row's exposure.
    warnings : tuple of str
        Warning codes (for the ``warnings`` column).
    reason : str
        Why a non-ok detection was refused (also one of the warnings).
    mean_brightness : float
        Mean grey level of the image.
    contour_px : (K, 2) float ndarray
        Outline of the bright region found (for overlays).
    """

    status: Status
    points_px: np.ndarray = field(default_factory=lambda: np.full((3, 2), np.nan))
    points_n: np.ndarray = field(default_factory=lambda: np.full((3, 2), np.nan))
    cov_n: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    consider_n: np.ndarray | None = None
    shutter_gain_n: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    reason: str = ""
    mean_brightness: float = float("nan")
    contour_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True)
class AttitudeSolution:
    """An attitude estimate.

    Attributes
    ----------
    status : Status
    R_nb : (3, 3) ndarray
        Body-to-lab rotation, x_N = R_nb x_B.
    cov_b : (3, 3) ndarray
        Covariance (rad^2) of the small rotation error eps in R_nb_true = R_nb exp([eps]x),
        eps in body axes.
    rms_px : float
        RMS reprojection residual in pixels.
    n_points : int
        Number of image points used.
    iterations : int
        Solver iterations.
    warnings : tuple of str
    chi2 : float
        Mahalanobis residual of the fit (NaN where the estimator has none).
    height_mm : float
        Triangle: the target's height against the rig's as the fit estimated it (0 when
        the rig holds it, ``height_sigma_mm = 0``).
    height_sigma_mm : float
        Its 1-sigma (NaN when not estimated).
    dof : int
        Degrees of freedom of ``chi2`` (0 where the estimator has none).
    residual : object, optional
        Triangle "full": the fit's vertex residuals and what the fit could absorb of a
        pattern of vertex shifts (``estimate.triangle_full.VertexResidual``).
    """

    status: Status
    R_nb: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    cov_b: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    rms_px: float = float("nan")
    n_points: int = 0
    iterations: int = 0
    warnings: tuple[str, ...] = ()
    chi2: float = float("nan")
    height_mm: float = 0.0
    height_sigma_mm: float = float("nan")
    dof: int = 0
    residual: object | None = None
