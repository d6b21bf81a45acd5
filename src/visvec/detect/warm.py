"""The triangle's compiled kernels loaded (or, the first time on a machine, compiled)
before a camera's first frame: :func:`warm_up`, which the triangle detector calls."""

from __future__ import annotations

import sys
import threading

import cv2
import numpy as np

from visvec._kernels import edge_fit as kernels
from visvec._kernels import jit
from visvec._kernels import readout as readout_kernels
from visvec._kernels import rotation as rotation_kernels
from visvec.camera import CameraModel
from visvec.detect.edges import fit_edges
from visvec.detect.photometric import refine

# the kernels loaded so far: "edges" (the edge fit's and the attitude fit's, every
# triangle rig's), "pixels" (the pixel fit's)
_warm: set[str] = set()
# warm_up says it is compiling at once when Numba has no cache of the kernels; with a
# cache (loaded in one to three seconds, more on a busy machine), only if it takes longer
# than this (s): a cache that no longer fits the code is compiled again
COMPILE_NOTICE_S = 10.0


def _compile_notice() -> None:
    print("visvec: compiling the triangle's kernels (the fast extra), once on this "
          "machine: about half a minute", file=sys.stderr, flush=True)  # fmt: skip


def _kernels_cached(modules=("edge_fit", "rotation", "readout")) -> bool:
    """Whether Numba's cache holds the triangle's kernels (the index files of the
    ``modules`` of visvec._kernels: by default the edge fit's, the attitude fit's and
    the readout's; beside them or under NUMBA_CACHE_DIR)."""
    import glob
    import os

    places = [os.path.join(os.path.dirname(kernels.__file__), "__pycache__")]
    if os.environ.get("NUMBA_CACHE_DIR"):
        places.append(os.path.join(os.environ["NUMBA_CACHE_DIR"], "**"))
    return all(
        any(glob.glob(os.path.join(p, f"{m}.*.nbi"), recursive=True) for p in places)
        for m in modules
    )


def warm_up(pixel_fit: bool = False) -> None:
    """Load (or, the first time on a machine, compile) the compiled kernels now, not on
    a camera's first frame: an edge fit, cold and tracked, of a triangle drawn on a small
    image, which calls each kernel with each kind of argument a frame gives it, and an
    attitude fit of three points and its rolling-shutter evidence (visvec.estimate);
    with ``pixel_fit`` the pixel fit's too (visvec.detect.photometric: a rig with
    refine = "pixels"). A few milliseconds once they are loaded; the first time on a
    machine about 25 s (30 s with the pixel fit), announced on stderr when Numba has no
    cache of them (or loading takes over COMPILE_NOTICE_S); without Numba, nothing.
    Kernels that do not load (a Numba that cannot compile here, no writable place for
    its cache: NUMBA_CACHE_DIR names one) leave the numpy path on, with a line on
    stderr."""
    todo = {"edges", "pixels"} if pixel_fit else {"edges"}
    todo -= _warm
    if not todo or not jit.ON:
        return
    _warm.update(todo)
    img = np.full((96, 96), 60, np.uint8)
    corners = np.array([[80.0, 48.0], [20.0, 20.0], [20.0, 76.0]])
    cv2.fillPoly(img, [np.rint(corners).astype(np.int32)], 120)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    cam = CameraModel(96, 96, 80.0, 80.0, 47.5, 47.5, np.zeros(5))
    # loaded from the cache in a fraction of a second; compiling takes long enough that
    # the operator is told why nothing happens
    cached = _kernels_cached(
        ("edge_fit", "rotation", "readout", "pixel_fit")
        if "pixels" in todo
        else ("edge_fit", "rotation", "readout")
    )
    if not cached:
        _compile_notice()  # said before the work, not raced against it
    notice = threading.Timer(COMPILE_NOTICE_S, _compile_notice)
    notice.daemon = True
    if cached:
        notice.start()
    try:
        fit = fit_edges(img, corners, cam)
        fit_edges(img, corners, cam, width=fit.width)
        # the triangle's attitude fit (visvec.estimate.rotation._fit_with_shift)
        X = np.array([[0.0, 0.0, 1000.0], [100.0, 0.0, 1000.0], [0.0, 100.0, 1000.0]])
        xy = X[:, :2] / X[:, 2:]
        rotation_kernels.closed_form(np.zeros(3), X, xy)
        rotation_kernels.gn_shift(np.eye(3), np.zeros(3), X, xy, np.eye(6),
                                  np.array([0.0, 0.0, 1.0]), 0.0, 1.0, 15, 1e-12,
                                  1e-3)  # fmt: skip
        # and its frame's rolling-shutter evidence (visvec.estimate.shear)
        readout_kernels.readout_frame(np.eye(6)[:, :4].copy(), np.eye(6), np.zeros(6), xy,
                                      np.ones(3), np.zeros(3), np.zeros(3), 1.0, 2.0, 1.0,
                                      1.0, 0.0, np.zeros((10, 10)), np.zeros(10))  # fmt: skip
        readout_kernels.readout_solve(np.eye(10), np.eye(10), np.zeros(10), 0.0, 0.0)
        if "pixels" in todo:
            if not refine(img, fit.normals, fit.offsets, fit.width, cam).ok:
                raise RuntimeError("the pixel fit's kernels gave no fit on the warm-up image")
    except Exception as exc:  # noqa: BLE001 - any failure of Numba's: numpy instead
        jit.off()
        print(f"visvec: the compiled edge fit did not load ({type(exc).__name__}: {exc}); "
              "the numpy one runs (VISVEC_PURE=1 skips the attempt)", file=sys.stderr)  # fmt: skip
    finally:
        notice.cancel()
