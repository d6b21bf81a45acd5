"""The 3-D filter's transition against central differences of its own propagation."""

import math

import numpy as np
import pytest

import visvec.fuse.attitude as attitude
from visvec.fuse.attitude import (
    BIAS,
    DRIFT,
    MIS,
    N_STATE,
    SCALE,
    TAU,
    TH,
    AttitudeModel,
)
from visvec.fuse.inputs import Fix
from visvec.rotations import expmap, logmap


def _state(rng):
    m = AttitudeModel()
    s = m.init(Fix(0.0, 0.0, expmap(rng.normal(0, 1, 3)), None, 0))
    return m, s._replace(b=rng.normal(0, 0.02, 3), Rm=expmap(rng.normal(0, 0.03, 3)),
                         k=rng.normal(0, 0.01, 3), tau=0.004, drift=1e-4)  # fmt: skip


def _perturbed(s, dx):
    """The true state that the error dx (15,) describes about the estimate s."""
    return s._replace(R=s.R @ expmap(dx[TH]), b=s.b + dx[BIAS], Rm=expmap(dx[MIS]) @ s.Rm,
                      k=s.k + dx[SCALE], tau=s.tau + dx[TAU],
                      drift=s.drift + dx[DRIFT])  # fmt: skip


def _error(s, t):
    """The error state (15,) of t about s (the jitter left out: it is considered)."""
    e = np.zeros(N_STATE)
    e[TH] = logmap(s.R.T @ t.R)
    e[BIAS] = t.b - s.b
    e[MIS] = logmap(t.Rm @ s.Rm.T)
    e[SCALE] = t.k - s.k
    e[TAU] = t.tau - s.tau
    e[DRIFT] = t.drift - s.drift
    return e


def _residual(m, s, g, gdot, dt):
    """The largest difference, per error-state column, between F and the central
    differences of the propagated mean (the jitter's row and column left out)."""
    reading = np.stack([g, gdot, np.zeros(3)])
    _, F = attitude.transition(s, g, gdot, dt, m.jitter_time)
    s1 = m.propagate(s, reading, None, dt)
    rows = [*range(13), DRIFT]
    out = np.zeros(N_STATE)
    h = 1e-6
    for i in rows:
        d = np.zeros(N_STATE)
        d[i] = h
        plus = _error(s1, m.propagate(_perturbed(s, d), reading, None, dt))
        minus = _error(s1, m.propagate(_perturbed(s, -d), reading, None, dt))
        out[i] = np.abs(F[rows, i] - ((plus - minus) / (2 * h))[rows]).max()
    return out, F


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_transition_is_the_propagation_s_derivative(seed):
    """F from `transition` is the derivative of the propagated mean with respect to
    each error-state component to the first order in dt: what differs is second order
    (it shrinks fourfold when the step is halved), at up to 3 rad/s and 35 rad/s^2."""
    rng = np.random.default_rng(seed)
    m, s = _state(rng)
    g = rng.normal(0, 2.0, 3)
    gdot = rng.normal(0, 20.0, 3)
    r1, F = _residual(m, s, g, gdot, 0.004)
    r2, _ = _residual(m, s, g, gdot, 0.002)
    assert np.all(r2 <= r1 / 3.0 + 1e-8), (r1, r2)
    assert r1.max() < 1e-3
    # the jitter enters as the time offset does, and decays
    np.testing.assert_allclose(F[TH, 13], F[TH, TAU])
    assert F[13, 13] == pytest.approx(math.exp(-0.004 / m.jitter_time))


def test_a_wrong_transition_would_be_found():
    """The check above fails on a transition with a first-order error (the
    misalignment's block transposed)."""
    rng = np.random.default_rng(0)
    m, s = _state(rng)
    g, gdot = rng.normal(0, 2.0, 3), rng.normal(0, 20.0, 3)
    orig = attitude.transition

    def wrong(*a):
        w, F = orig(*a)
        F = F.copy()
        F[TH, MIS] = F[TH, MIS].T
        return w, F

    attitude.transition = wrong
    try:
        r1, _ = _residual(m, s, g, gdot, 0.004)
        r2, _ = _residual(m, s, g, gdot, 0.002)
    finally:
        attitude.transition = orig
    assert not np.all(r2 <= r1 / 3.0 + 1e-8)


def test_warm_up_loads_the_propagation_for_the_first_fix():
    """A live run's first fix must not wait for Numba (half a second from its cache):
    warm_up calls the kernels with a filter's argument types, so the code for them is
    there, and a filter's own call adds no other."""
    from visvec.fuse import kernels
    from visvec.fuse.gate import warm_up

    warm_up()
    if not kernels.ON or not hasattr(kernels.propagate, "signatures"):
        pytest.skip("the numpy path: nothing to load")
    before = len(kernels.propagate.signatures)
    assert before >= 1
    m, s = _state(np.random.default_rng(0))
    m.propagate(s, np.stack([np.ones(3), np.zeros(3), np.zeros(3)]), None, 0.01)
    assert len(kernels.propagate.signatures) == before


@pytest.mark.parametrize("saturated_at", [None, 3])
def test_a_run_of_samples_gives_the_states_one_by_one_gives(saturated_at):
    """A replay propagates its runs of stored samples in one call (propagate_run): the
    states must be those of propagate on each interval in turn, to the bit (the fused
    rows may not depend on how the samples were grouped)."""
    rng = np.random.default_rng(4)
    m, s = _state(rng)
    s = s._replace(acc=(0.3, 0.02, 1e-6), fade=1.7)
    n = 7
    G = np.zeros((n, 3, 3))
    G[:, 0] = rng.normal(0, 2.0, (n, 3))
    G[:, 1] = rng.normal(0, 20.0, (n, 3))
    if saturated_at is not None:
        G[saturated_at, 2] = [0.0, 0.4, 0.0]
    dts = list(rng.uniform(0.002, 0.004, n))
    run = m.propagate_run(s, list(G), dts)
    one = s
    for i in range(n):
        one = m.propagate(one, G[i], None, dts[i])
        got = run[i]
        for name in ("R", "P", "b", "Rm", "k"):
            assert np.array_equal(getattr(got, name), getattr(one, name)), (i, name)
        assert (got.tau, got.acc, got.saturated) == (one.tau, one.acc, one.saturated), i
    assert run[-1].saturated is (saturated_at is not None)
