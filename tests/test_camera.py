import cv2
import numpy as np
import pytest

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


@pytest.mark.parametrize(
    "dist", [(-0.28, 0.07, 0.001, -0.0005, 0.0), (-0.42, 0.3, 0.0, 0.0, -0.2)], ids=str
)
def test_undistort_reprojects_to_the_pixel_over_the_whole_image(dist):
    # a webcam's distortion and a strong one, to the image corners: the Newton steps
    # after OpenCV's iteration stop only once every point reprojects
    cam = CameraModel(640, 480, 600.0, 600.0, 319.5, 239.5, np.array(dist))
    u, v = np.meshgrid(np.linspace(0, 639, 17), np.linspace(0, 479, 13))
    uv = np.column_stack([u.ravel(), v.ravel()])
    np.testing.assert_allclose(cam.distort(cam.undistort(uv)), uv, atol=1e-8)


def test_points_behind_camera_are_nan():
    cam = _cam()
    uv = cam.project(np.array([[0.0, 0.0, -100.0], [0.0, 0.0, 100.0]]))
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


def test_scaled_keeps_pixel_centre_convention():
    cam = CameraModel(320, 240, 300.0, 300.0, 159.5, 119.5)
    big = cam.scaled(2.0)
    assert (big.width, big.height, big.fx) == (640, 480, 600.0)
    assert big.cx == 319.5 and big.cy == 239.5
