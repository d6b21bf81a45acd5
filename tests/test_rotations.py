import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from visvec.rotations import (
    euler_rates_from_body,
    euler_to_matrices,
    euler_to_matrix,
    expmap,
    logmap,
    matrix_to_euler,
    matrix_to_quat,
    quat_to_matrix,
)

angle = st.floats(-np.pi + 1e-6, np.pi, allow_nan=False)
tilt = st.floats(-1.4, 1.4, allow_nan=False)


@given(angle, tilt, angle)
@example(np.pi, 0.0, 0.0)  # yaw on the wrap boundary is reported as +180
def test_euler_round_trip(yaw, pitch, roll):
    R = euler_to_matrix(yaw, pitch, roll)
    y2, p2, r2 = matrix_to_euler(R)
    assert -np.pi < y2 <= np.pi
    np.testing.assert_allclose(euler_to_matrix(y2, p2, r2), R, atol=1e-12)
    assert abs(p2 - pitch) < 1e-9


@given(angle, tilt, angle)
def test_quaternion_round_trip_scalar_first_nonnegative(yaw, pitch, roll):
    R = euler_to_matrix(yaw, pitch, roll)
    q = matrix_to_quat(R)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)


def test_euler_to_matrices_is_euler_to_matrix_for_each():
    rng = np.random.default_rng(2)
    a = rng.uniform(-np.pi, np.pi, (200, 3))
    R = euler_to_matrices(a[:, 0], a[:, 1], a[:, 2])
    assert R.shape == (200, 3, 3)
    for k in range(200):
        np.testing.assert_allclose(R[k], euler_to_matrix(*a[k]), atol=1e-15)
    # broadcasting: a grid of yaws at one tilt
    G = euler_to_matrices(np.array([[0.1], [0.2]]), 0.3, np.array([0.0, -0.4]))
    assert G.shape == (2, 2, 3, 3)
    np.testing.assert_allclose(G[1, 1], euler_to_matrix(0.2, 0.3, -0.4), atol=1e-15)


def test_euler_convention_is_intrinsic_zyx():
    # a pure yaw of 90 deg maps body x onto lab y
    R = euler_to_matrix(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # quaternion of a 90 deg yaw about z
    np.testing.assert_allclose(matrix_to_quat(R), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15)


def test_expmap_small_and_large_angles():
    w = np.array([1e-10, -2e-10, 3e-10])
    np.testing.assert_allclose(
        expmap(w),
        np.eye(3) + np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]),
        atol=1e-19,
    )
    R = expmap(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(R, euler_to_matrix(np.pi / 2, 0, 0), atol=1e-15)


@pytest.mark.parametrize(
    "theta", [0.0, 1e-12, 1e-7, 1e-3, 0.5, np.pi / 2 - 1e-9, np.pi / 2 + 1e-9, 2.5, np.pi - 1e-6]
)
def test_logmap_inverts_expmap_from_zero_to_pi(theta):
    # the skew-part path (below 90 deg) and the quaternion path (beyond) both invert
    # expmap to rounding, relative to the angle at small angles
    rng = np.random.default_rng(int(theta * 1e6) % 1000)
    for _ in range(50):
        axis = rng.normal(size=3)
        w = axis / np.linalg.norm(axis) * theta
        err = np.linalg.norm(logmap(expmap(w)) - w)
        assert err <= 1e-14 * max(theta, 1e-300) if theta < 1 else err < 1e-9


@pytest.mark.parametrize("e0", [(0.7, 0.08, -0.05), (-2.9, -0.17, 0.15), (1.2, 0.6, 1.1)], ids=str)
def test_euler_rate_jacobian_matches_central_differences(e0):
    e0 = np.array(e0)
    R0 = euler_to_matrix(*e0)
    J = euler_rates_from_body(*e0)
    h = 1e-6
    num = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        ep = np.array(matrix_to_euler(R0 @ expmap(d)))
        em = np.array(matrix_to_euler(R0 @ expmap(-d)))
        num[:, k] = (ep - em) / (2 * h)
    np.testing.assert_allclose(J, num, atol=1e-7)
