import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.3, 0.09, 0.001, -0.002, -0.01])])
def test_pixels_per_steradian_is_the_image_area_of_a_small_cone(dist):
    """A cone of 2e-4 rad square about a ray covers pixels_per_steradian times its solid
    angle in the image (the projected square's area), on and off the boresight."""
    cam = CameraModel(640, 480, 250.0, 252.0, 320.0, 240.0, dist)
    rng = np.random.default_rng(0)
    ratios = []
    for _ in range(6):
        d = rng.normal([0.3, -0.2, 1.0], [0.3, 0.3, 0.0])
        d /= np.linalg.norm(d)
        a = np.cross(d, [0.0, 0.0, 1.0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        e = 1e-4
        corners = [d + e * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        uv = cam.project(np.array(corners))
        area = 0.5 * abs(uv[:, 0] @ np.roll(uv[:, 1], 1) - uv[:, 1] @ np.roll(uv[:, 0], 1))
        ratios.append(area / (2 * e) ** 2 / cam.pixels_per_steradian(cam.project(d[None]))[0])
    np.testing.assert_allclose(ratios, 1.0, atol=1e-6)
    # the boresight: fx fy
    assert cam.pixels_per_steradian(np.array([[320.0, 240.0]]))[0] == pytest.approx(250.0 * 252.0)


# at fx 340 this polynomial turns back 345 px out, short of the 400 px corners
FOLDING = np.array([-0.32, 0.12, 0.0, 0.0, -0.02])


def _folding():
    return CameraModel(640, 480, 340.0, 340.0, 319.5, 239.5, FOLDING)


def test_the_field_ends_where_the_image_radius_stops_growing():
    cam = _folding()
    k1, k2, _, _, k3 = FOLDING

    def radius(s):
        return math.sqrt(s) * (1.0 + k1 * s + k2 * s**2 + k3 * s**3)

    s = cam.field_r2
    assert radius(0.99 * s) < radius(s) > radius(1.01 * s)  # the image radius' maximum
    assert all(radius(t * s) < radius(t * s + 1e-3) for t in np.linspace(0.0, 0.99, 50))
    assert cam.field_radius_px == pytest.approx(340.0 * radius(s))
    assert cam.field_radius_px < cam.corner_radius_px == pytest.approx(400.0)
    # lenses whose image radius keeps growing: a webcam's, OpenCV's sample calibration,
    # the same barrel lens without k3, none at all
    for d in (
        _cam().dist,
        [-0.2813, 0.0291, 0.0012, -0.0001, 0.1549],
        [-0.32, 0.12, 0.0, 0.0, 0.0],
        np.zeros(5),
    ):
        cam = CameraModel(640, 480, 340.0, 340.0, 319.5, 239.5, np.array(d))
        assert math.isinf(cam.field_r2) and np.all(cam.in_field(np.array([[0.0, 0.0]])))


def test_no_ray_comes_from_beyond_the_fold():
    """Pixels past the fold have no ray (nan), rather than one from the polynomial's far
    branch; inside it, every pixel's ray reprojects; rays past it project to nan rather
    than to a pixel folded back into the image."""
    cam = _folding()
    u, v = np.meshgrid(np.arange(-0.5, 640, 0.5), np.arange(-0.5, 480, 0.5))
    uv = np.column_stack([u.ravel(), v.ravel()])
    xy = cam.undistort(uv)
    has_ray = np.isfinite(xy).all(axis=1)
    inside = cam.in_field(uv, 1.0)
    assert inside.mean() > 0.9 and has_ray[inside].all()
    np.testing.assert_allclose(cam.distort(xy[inside]), uv[inside], atol=1e-6)
    assert not has_ray[~cam.in_field(uv)].any()
    assert np.all(np.einsum("ij,ij->i", xy[has_ray], xy[has_ray]) < cam.field_r2)
    a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    for t, seen in ((0.97, True), (1.03, False)):
        r = math.sqrt(t * cam.field_r2)
        p = np.column_stack([r * np.cos(a), r * np.sin(a), np.ones(12)])
        assert np.isfinite(cam.project(p)).all(axis=1).tolist() == [seen] * 12


def test_a_strong_pincushion_has_a_ray_at_every_pixel():
    """k2 0.21, k3 0.18 at fx 260: OpenCV's fixed-point iteration diverges towards the
    corners (164 of 1271 grid pixels were left unconverged); the radial start on the
    near branch gives every pixel its ray."""
    cam = CameraModel(640, 480, 260.0, 260.0, 319.5, 239.5, np.array([0.0044, 0.207, 0, 0, 0.1755]))
    assert math.isinf(cam.field_r2)
    u, v = np.meshgrid(np.linspace(-0.5, 639.5, 41), np.linspace(-0.5, 479.5, 31))
    uv = np.column_stack([u.ravel(), v.ravel()])
    np.testing.assert_allclose(cam.distort(cam.undistort(uv)), uv, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    k=st.tuples(
        st.floats(-0.6, 0.3), st.floats(-0.3, 0.3), st.floats(-0.2, 0.2), st.floats(250, 700)
    ),
    p=st.tuples(st.floats(-0.003, 0.003), st.floats(-0.003, 0.003)),
)
def test_undistort_gives_the_near_ray_or_none(k, p):
    """Any lens of these ranges: a pixel's ray reprojects onto it, inside the field; a
    pixel 1 px inside the field has one, without tangential terms (with them, the
    field's edge moves by their share, a few pixels)."""
    k1, k2, k3, f = k
    cam = CameraModel(640, 480, f, f, 319.5, 239.5, np.array([k1, k2, *p, k3]))
    u, v = np.meshgrid(np.linspace(-0.5, 639.5, 21), np.linspace(-0.5, 479.5, 16))
    uv = np.column_stack([u.ravel(), v.ravel()])
    xy = cam.undistort(uv)
    has_ray = np.isfinite(xy).all(axis=1)
    assert np.abs(cam.distort(xy[has_ray]) - uv[has_ray]).max(initial=0.0) < 1e-3
    assert np.all(np.einsum("ij,ij->i", xy[has_ray], xy[has_ray]) < cam.field_r2)
    radial = replace(cam, dist=np.array([k1, k2, 0.0, 0.0, k3]))
    assert np.isfinite(radial.undistort(uv[radial.in_field(uv, 1.0)])).all()
