"""Camera intrinsics and distortion from chessboard photos (OpenCV)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from visvec.camera import CameraModel
from visvec.errors import InputFileError
from visvec.imageio import read_image

RECIPES = {
    # OpenCV's own test (modules/python/test/test_calibration.py): default detection
    # flags, a 5x5 sub-pixel window, stop at 30 iterations or 0.1 px
    "opencv-test": dict(flags=None, window=5, criteria=(30, 0.1)),
    # a more precise default: adaptive threshold detection, 11x11 window, 1e-4 px
    "precise": dict(
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE,
        window=11,
        criteria=(30, 1e-4),
    ),
}
OUTLIER_FACTOR = 2.5


@dataclass(frozen=True)
class CameraCalibration:
    """Result of :func:`calibrate_camera`.

    K : (3, 3), dist : (5,), rms_px : overall RMS reprojection error,
    per_view_px : (V,) RMS per used view, files : names of used views,
    skipped : names of photos where the pattern was not found,
    outliers : names of views whose error exceeds 2.5x the median, width, height.
    sigma_px : (4,) 1-sigma of fx, fy, cx, cy (OpenCV's, from the fit's Jacobian and
    its residuals)
    reach_px : how far from the principal point the photos' corners reached (px): the
    distortion polynomial is a fit inside that, an extrapolation beyond
    """

    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    per_view_px: np.ndarray
    files: list[str]
    skipped: list[str]
    outliers: list[str]
    width: int
    height: int
    sigma_px: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    reach_px: float = np.nan

    @property
    def camera(self) -> CameraModel:
        K = self.K
        return CameraModel(
            self.width, self.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.array(self.dist)
        )


def find_corners(
    image: np.ndarray, pattern: tuple[int, int], recipe: str = "precise"
) -> np.ndarray | None:
    """(N, 2) refined inner corners, or None if the pattern is not found."""
    r = RECIPES[recipe]
    if r["flags"] is None:
        ok, corners = cv2.findChessboardCorners(image, pattern)
    else:
        ok, corners = cv2.findChessboardCorners(image, pattern, flags=r["flags"])
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, *r["criteria"])
    w = r["window"]
    corners = cv2.cornerSubPix(image, corners, (w, w), (-1, -1), crit)
    return corners.reshape(-1, 2)


def calibrate_camera(
    files: list[Path],
    pattern: tuple[int, int],
    square_mm: float,
    recipe: str = "precise",
    progress=None,
) -> CameraCalibration:
    """Calibrate from chessboard photos with cv2.calibrateCamera (flags = 0; its
    Extended form, for the intrinsics' standard deviations).

    Parameters
    ----------
    files : list of Path
        The photos (any size, all the same), each showing the whole pattern.
    pattern : (int, int)
        Inner corners per row and per column of the chessboard.
    square_mm : float
        The side of one square (mm).
    recipe : str
        'precise' (default) or another corner-refinement recipe of the command.
    progress : callable, optional
        ``progress(1)`` after each photo is searched.

    Returns
    -------
    CameraCalibration
        fx, fy, cx, cy (px) and the distortion coefficients with their standard
        deviations, the RMS reprojection error (px), the photos used; its TOML is
        a rig's ``[camera]`` section.

    Raises
    ------
    InputFileError
        If fewer than 3 photos show the whole pattern, or the photos differ in size.
    """
    obj = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0 : pattern[0], 0 : pattern[1]].T.reshape(-1, 2) * square_mm
    obj_pts, img_pts, used, skipped = [], [], [], []
    size = None
    for f in files:
        if progress is not None:
            progress(1)
        img = read_image(f, cv2.IMREAD_GRAYSCALE)
        if img is None:
            skipped.append(f"{f.name} (unreadable)")
            continue
        if size is None:
            size = img.shape[::-1]
        elif img.shape[::-1] != size:
            raise InputFileError(
                f"{f}: image is {img.shape[1]}x{img.shape[0]}, the others are {size[0]}x{size[1]}"
            )
        c = find_corners(img, pattern, recipe)
        if c is None:
            skipped.append(f.name)
            continue
        obj_pts.append(obj)
        img_pts.append(c.astype(np.float32))
        used.append(f.name)
    if len(used) < 3:
        raise InputFileError(
            f"the {pattern[0]}x{pattern[1]} pattern was found in "
            f"{len(used)} photo(s); at least 3 are needed"
        )
    rms, K, dist, rvecs, tvecs, sd_in, _, _ = cv2.calibrateCameraExtended(
        obj_pts, img_pts, size, None, None, flags=0
    )
    per_view = []
    for o, p, rv, tv in zip(obj_pts, img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p) ** 2, 1)))))
    per_view = np.array(per_view)
    reach = max(float(np.hypot(*(p.reshape(-1, 2) - K[:2, 2]).T).max()) for p in img_pts)
    med = float(np.median(per_view))
    outliers = [n for n, e in zip(used, per_view, strict=True) if e > OUTLIER_FACTOR * med]
    return CameraCalibration(
        K,
        dist.ravel()[:5],
        float(rms),
        per_view,
        used,
        skipped,
        outliers,
        int(size[0]),
        int(size[1]),
        sd_in.ravel()[:4].astype(float),
        reach,
    )


def camera_section(cal: CameraCalibration) -> dict[str, object]:
    """The rig's [camera] section for this calibration."""
    K = cal.K
    return {
        "width": cal.width,
        "height": cal.height,
        "fx": round(float(K[0, 0]), 6),
        "fy": round(float(K[1, 1]), 6),
        "cx": round(float(K[0, 2]), 6),
        "cy": round(float(K[1, 2]), 6),
        "dist": [round(float(x), 9) for x in cal.dist],
    }
