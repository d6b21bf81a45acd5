"""The 3-D filter's propagation over one inertial interval, written once: compiled by
Numba with the ``fast`` extra, run as numpy without it (or with ``VISVEC_PURE=1``).

The equations and their sources are the 3-D filter's (visvec.fuse.attitude's module
doc: Markley & Crassidis 2014, Eqs. 6.60-6.63, with the gyro's misalignment, scale
factors, time offset, clock jitter and clock rate as states). A sample's propagation is
the fusion's inner loop, replayed for every late fix: in numpy its sixty-odd small
array operations take about 100 us, compiled a few (benchmarks/fusion_speed.py).

Numba is imported on the first call, not with this module (the command line starts
without it); every kernel is compiled then (or loaded from its cache), helpers first,
so that the others compile against their dispatchers.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np

from visvec._kernels import AVAILABLE
from visvec.rotations import expmap_xyz  # compiled beside the kernels that call it

# the error state's layout: the first index of each 3-vector (attitude dtheta about the
# body axes, the gyro's bias, its misalignment, its scale factors), then the time offset
# tau, the clock jitter and the clock rate (visvec.fuse.attitude names their slices);
# integers, which Numba compiles as constants
TH0, BIAS0, MIS0, SCALE0 = 0, 3, 6, 9
TAU, JIT, DRIFT = 12, 13, 14
N_STATE = 15


def _minus_cross_into(F, r, c, v, s):
    """F's 3x3 block at (r, c) set to -[v]x s (the skew matrix of v, negated, times the
    scalar s; no temporary array: the propagation runs for every inertial sample)."""
    F[r, c + 1] = v[2] * s
    F[r, c + 2] = -v[1] * s
    F[r + 1, c] = -v[2] * s
    F[r + 1, c + 2] = v[0] * s
    F[r + 2, c] = v[1] * s
    F[r + 2, c + 1] = -v[0] * s


def transition(Rm, k, b, tau, g, gdot, dt, jitter_time):
    """The body rate w (rad/s) over the interval and the error state's transition F
    (15, 15): w = R_m (1 + k) (g + tau gdot - b); F = I + the error equation's matrix
    times dt, its attitude block the exact exp(-[w]x dt); the clock jitter decays over
    ``jitter_time``, the time offset drifts with the clock rate."""
    scale = 1.0 + k
    gc = g + tau * gdot - b  # the reading corrected, in gyro axes
    w = Rm @ (scale * gc)
    RmS = Rm * scale
    F = np.eye(N_STATE)
    th = slice(TH0, TH0 + 3)
    F[th, th] = expmap_xyz(-w[0] * dt, -w[1] * dt, -w[2] * dt)
    F[th, BIAS0 : BIAS0 + 3] = -RmS * dt
    _minus_cross_into(F, TH0, MIS0, w, dt)  # the misalignment's: -[w]x dt
    F[th, SCALE0 : SCALE0 + 3] = Rm * gc * dt
    col = RmS @ gdot * dt
    F[th, TAU] = col
    F[th, JIT] = col
    F[JIT, JIT] = math.exp(-dt / jitter_time)
    F[TAU, DRIFT] = dt
    return w, F


def process_noise(RmS, q, gsat, dt, jitter, jitter_time, drift_walk2, bias_walk2):
    """The process noise Q (15, 15) over ``dt``: ``q`` (rad^2) per attitude axis, a
    saturated reading's error ``gsat`` (rad/s per gyro axis) through R_m (1 + k) =
    ``RmS``, the bias's random walk (``bias_walk2``: rad^2/s^3), the clock jitter's
    Gauss-Markov increment and the clock rate's random walk (``drift_walk2``: 1/s)."""
    fade_j = math.exp(-dt / jitter_time)
    Q = np.zeros((N_STATE, N_STATE))
    Q[JIT, JIT] = jitter * jitter * (1.0 - fade_j * fade_j)
    Q[DRIFT, DRIFT] = drift_walk2 * dt
    for i in range(3):
        Q[TH0 + i, TH0 + i] = q
        Q[BIAS0 + i, BIAS0 + i] = bias_walk2 * dt
    if np.any(gsat > 0):
        # a saturated reading's error is the same all through the burst: count it as
        # one (conservatively, the whole interval's worth at once)
        Q[TH0 : TH0 + 3, TH0 : TH0 + 3] += RmS @ np.diag((gsat * dt) ** 2) @ RmS.T
    return Q


def propagate(R, b, Rm, k, tau, P, G, dt, qa, qw, A, fade, jitter, jitter_time, drift_walk2,
              bias_walk2):  # fmt: skip
    """One interval, its reading G (3, 3) (`History.reading`: the mean rate g, its
    rate of change gdot, a saturated reading's extra sigma gsat): the new attitude
    R_NB, covariance P, the turn since the last fix ``A1`` (rad) and the attitude noise
    added (the trace of Q's attitude block). The noise: white qa dt and
    rate-proportional qw ((A + |w| dt)^2 - A^2), held since the last fix, times the
    fading factor."""
    g, gdot, gsat = G[0], G[1], G[2]
    w, F = transition(Rm, k, b, tau, g, gdot, dt, jitter_time)
    Rn = R @ expmap_xyz(w[0] * dt, w[1] * dt, w[2] * dt)
    A1 = A + math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) * dt
    q = (qa * dt + qw * (A1 * A1 - A * A)) * fade
    Q = process_noise(Rm * (1.0 + k), q, gsat, dt, jitter, jitter_time, drift_walk2,
                      bias_walk2)  # fmt: skip
    Pn = F @ P @ np.ascontiguousarray(F.T) + Q
    return Rn, Pn, A1, Q[TH0, TH0] + Q[TH0 + 1, TH0 + 1] + Q[TH0 + 2, TH0 + 2]


def propagate_run(R, b, Rm, k, tau, drift, P, G, dts, qa, qw, A, trq, fade, jitter,
                  jitter_time, drift_walk2, bias_walk2):  # fmt: skip
    """`propagate` over consecutive intervals with no fix between them (a replay's
    run of stored samples): G (n, 3, 3) the readings (`History.reading` each), dts
    (n,) the intervals; the time offset drifts by ``drift`` dt each. Returns the
    attitude (n, 3, 3), covariance (n, 15, 15), turn since the fix (n,), attitude noise
    added since the fix (n,) and time offset (n,) after each interval: the states one
    call of `propagate` per interval gives, to the bit."""
    n = dts.shape[0]
    Rs = np.empty((n, 3, 3))
    Ps = np.empty((n, N_STATE, N_STATE))
    As = np.empty(n)
    trqs = np.empty(n)
    taus = np.empty(n)
    for i in range(n):
        dt = dts[i]
        R, P, A, q = propagate(R, b, Rm, k, tau, P, G[i], dt, qa, qw, A, fade, jitter,
                               jitter_time, drift_walk2, bias_walk2)  # fmt: skip
        trq = trq + q
        tau = tau + drift * dt
        Rs[i] = R
        Ps[i] = P
        As[i] = A
        trqs[i] = trq
        taus[i] = tau
    return Rs, Ps, As, trqs, taus


# ------------------------------------------------------------------ compiled on demand
_PY = {
    "expmap_xyz": expmap_xyz,
    "_minus_cross_into": _minus_cross_into,
    "transition": transition,
    "process_noise": process_noise,
    "propagate": propagate,
    "propagate_run": propagate_run,
}  # fmt: skip  (helpers first: the others call them)
_LOCK = threading.Lock()
ON = AVAILABLE  # whether the compiled kernels run (off without Numba, VISVEC_PURE=1)


def _compile() -> None:
    """Compile every kernel (or load it from the cache), in _PY's order, each put in
    its module name before the next is compiled."""
    global ON
    with _LOCK:
        if globals()["propagate"] is not _lazy_propagate:
            return
        try:
            import numba as nb

            for name, f in _PY.items():
                globals()[name] = nb.njit(cache=True, nogil=True)(f)
        except ImportError as exc:
            ON = False
            for name, f in _PY.items():
                globals()[name] = f
            print(f"visvec: Numba did not import ({exc}); the fusion's numpy path runs",
                  file=sys.stderr)  # fmt: skip


def warm_up() -> None:
    """Compile the kernels (or load them from their cache) now, so that a live run's
    first fix does not wait for it (half a second from the cache): Numba makes a
    kernel's code for the argument types of its first call, so they are called once,
    with the types a filter gives them."""
    if globals()["propagate"] is _lazy_propagate:
        _compile()
    z3, eye, P = np.zeros(3), np.eye(3), np.eye(N_STATE)
    propagate(eye, z3, eye, z3, 0.0, P, np.zeros((3, 3)), 0.01, 1e-6, 1e-6, 0.0, 1.0, 0.01,
              0.2, 1e-8, 1e-8)  # fmt: skip
    propagate_run(eye, z3, eye, z3, 0.0, 0.0, P, np.zeros((2, 3, 3)), np.full(2, 0.01), 1e-6,
                  1e-6, 0.0, 0.0, 1.0, 0.01, 0.2, 1e-8, 1e-8)  # fmt: skip
    transition(eye, z3, z3, 0.0, z3, z3, 0.01, 0.2)
    process_noise(eye, 1e-6, z3, 0.01, 0.01, 0.2, 1e-8, 1e-8)


def _lazy_propagate(*args):
    _compile()
    return globals()["propagate"](*args)


def _lazy_propagate_run(*args):
    _compile()
    return globals()["propagate_run"](*args)


if AVAILABLE:
    propagate = _lazy_propagate  # noqa: F811  (the compiled kernel after the first call)
    propagate_run = _lazy_propagate_run  # noqa: F811
