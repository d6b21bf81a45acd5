"""The planar filter's transition and measurement against central differences."""

import math

import numpy as np
import pytest

from visvec.fuse.inputs import Fix
from visvec.fuse.planar import BG, N_PLANAR, PSI, PlanarModel, transition


def _state(rng):
    m = PlanarModel()
    s = m.init(Fix(0.0, 0.0, np.array([100.0, -50.0, 0.7]), None, 0))
    x = s.x.copy()
    x[2:4] = rng.normal(0, 80.0, 2)
    x[BG] = rng.normal(0, 0.01)
    x[6:8] = rng.normal(0, 5.0, 2)
    x[8], x[9] = 0.03, 0.004
    from dataclasses import replace

    return m, replace(s, x=x, pending=False)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_transition_is_the_propagation_s_derivative(seed):
    """F equals the central differences of the propagated mean, to the first order in
    dt that the filter keeps (the bias's effect on the mid-heading is second order)."""
    rng = np.random.default_rng(seed)
    m, s = _state(rng)
    gyro = np.stack([np.array([0.0, 0.0, 0.4]), np.zeros(3), np.zeros(3)])
    acc = rng.normal(0, 0.05, 2)
    dt = 0.01
    s1 = m.propagate(s, gyro, acc, dt)
    psi_mid = s.x[PSI] + 0.5 * (0.4 - s.x[BG]) * dt
    F = transition(np.array(s1.an), math.cos(psi_mid), math.sin(psi_mid), dt)
    h = 1e-5
    for i in range(N_PLANAR):
        d = np.zeros(N_PLANAR)
        d[i] = h
        from dataclasses import replace

        plus = m.propagate(replace(s, x=s.x + d), gyro, acc, dt).x
        minus = m.propagate(replace(s, x=s.x - d), gyro, acc, dt).x
        col = (plus - minus) / (2 * h)
        np.testing.assert_allclose(F[:, i], col, atol=1e-9 + 0.6 * np.abs(s1.an).max() * dt**2)


def test_the_measurement_jacobian_is_its_derivative():
    """H from _measure equals the central differences of h, with the rate less the
    bias moving with the bias (w = gyro - b_g)."""
    rng = np.random.default_rng(3)
    m, s = _state(rng)
    an, shift, w0 = (12.0, -7.0), 0.01, 0.3

    def h_of(x):
        return PlanarModel._measure(x, w0 - (x[BG] - s.x[BG]), an, shift)[0]

    _, H = PlanarModel._measure(s.x, w0, an, shift)
    eps = 1e-6
    for i in range(N_PLANAR):
        d = np.zeros(N_PLANAR)
        d[i] = eps
        col = (h_of(s.x + d) - h_of(s.x - d)) / (2 * eps)
        np.testing.assert_allclose(H[:, i], col, atol=1e-6)
