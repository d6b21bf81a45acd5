"""The rolling shutter's geometry (visvec.shutter): unroll and its linearisations."""

import numpy as np

from visvec.rotations import euler_to_matrix


def test_rolling_shutter_covariance_is_the_linearised_correction(rig640):
    """shutter_matrix's A omega is the first-order shift unroll makes for a rate omega
    at the vertices (finite differences); shutter_shift gives A omega itself."""
    from visvec.shutter import shutter_matrix, shutter_shift, unroll

    cam = rig640.camera
    xy = np.array([[0.31, -0.12], [-0.22, 0.25], [-0.05, -0.33]])
    rows = cam.cy + xy[:, 1] * cam.fy
    readout, h = 25.0, 1e-4  # ms, rad/s
    A = np.zeros((6, 3))
    for j in range(3):
        w = np.zeros(3)
        w[j] = h
        A[:, j] = (
            (unroll(xy, rows, cam, w, readout) - unroll(xy, rows, cam, -w, readout)) / (2 * h)
        ).ravel()
    np.testing.assert_allclose(shutter_matrix(xy, rows, cam, readout), A, rtol=1e-6, atol=1e-12)
    lever = np.array([0.12, -0.05, -0.07])  # a camera off the axis: b / Z
    for j in range(3):
        w = np.zeros(3)
        w[j] = h
        plus, minus = (unroll(xy, rows, cam, s * w, readout, lever) for s in (1, -1))
        A[:, j] = ((plus - minus) / (2 * h)).ravel()
    got = shutter_matrix(xy, rows, cam, readout, lever)
    np.testing.assert_allclose(got, A, rtol=1e-6, atol=1e-12)
    # and shutter_shift, A omega for one rate, is the same linearisation
    omega = np.array([0.03, -0.02, 0.35])
    got = shutter_shift(xy, rows, cam, readout, omega, lever)
    np.testing.assert_allclose(got, A @ omega, rtol=1e-6, atol=1e-12)


def test_rolling_shutter_correction_follows_a_camera_off_the_axis(rig640):
    """A lab point seen t after the centre row by a camera 250 mm off the rotation axis,
    the platform turning at 20 deg/s about a tilted axis: unroll with the lever arm
    b / Z takes its image back to the centre row's to second order in the rotation
    and the depth's spread (under 0.005 px), where the rotation alone leaves 0.2-0.3 px
    of a 0.5-0.8 px shift."""
    from visvec.rotations import expmap
    from visvec.shutter import unroll

    t_b = np.array([250.0, -40.0, 150.0])
    R_bc = rig640.R_bc
    P_n = np.array([[300.0, 120.0, 2150.0], [-150.0, -200.0, 2150.0]])
    R0 = euler_to_matrix(0.4, 0.03, -0.02)
    w_b = np.radians([3.0, -2.0, 20.0])

    def seen(t):
        R = R0 @ expmap(w_b * t)
        p_c = (P_n @ R - t_b) @ R_bc  # P_C = R_BC^T (R_NB^T P_N - t_B)
        return p_c[:, :2] / p_c[:, 2:3], p_c[:, 2]

    cam = rig640.camera
    xy0, depth = seen(0.0)
    lever = (R_bc.T @ t_b) / depth.mean()
    for t in (-0.012, 0.008):
        xy_t, _ = seen(t)
        rows = np.full(2, cam.cy + t / 0.025 * cam.height)  # rows read t after the centre
        w_c = R_bc.T @ w_b
        fixed = unroll(xy_t, rows, cam, w_c, 25.0, lever)
        rot_only = unroll(xy_t, rows, cam, w_c, 25.0)
        assert np.abs(fixed - xy0).max() * cam.fx < 0.005
        assert np.abs(rot_only - xy0).max() * cam.fx > 0.1
