import cv2
import numpy as np

from visvec.camera import CameraModel


def _cam():
    return CameraModel(
        640, 480, 610.0, 605.0, 322.0, 241.0, np.array([-0.28, 0.08, 0.001, -0.0005, 0.02])
    )


def test_distort_matches_cv2_project_points(rng):
    cam = _cam()
    p = np.column_stack(
        [rng.uniform(-400, 400, 50), rng.uniform(-300, 300, 50), rng.uniform(800, 2000, 50)]
    )
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(p), ref.reshape(-1, 2), atol=1e-9)


def test_undistort_inverts_distort(rng):
    cam = _cam()
    xy = rng.uniform(-0.4, 0.4, (100, 2))
    np.testing.assert_allclose(cam.undistort(cam.distort(xy)), xy, atol=1e-9)


def test_points_behind_camera_are_nan():
    cam = _cam()
    uv = cam.project(np.array([[0.0, 0.0, -100.0], [0.0, 0.0, 100.0]]))
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


def test_scaled_keeps_pixel_centre_convention():
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    big = cam.scaled(2.0)
    assert (big.width, big.height, big.fx) == (640, 480, 600.0)
    assert big.cx == 319.5 and big.cy == 239.5
