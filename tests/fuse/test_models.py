"""The filters: the planar Kalman filter's target and biases; the 3-D filter's learned bias,
misalignment, time offset and noise, its clock jitter, disputes and bursts."""

import math
from dataclasses import replace

import numpy as np
import pytest
from fusion_cases import (
    _err,
    _fixes,
    _run_engine,
    _sim3d,
    planar_case,
    run,
    truth_table,
)

from visvec.fuse.attitude import AttitudeModel
from visvec.fuse.inputs import Fix, ImuData
from visvec.fuse.planar import PlanarJitter, PlanarModel
from visvec.fuse.replay import Limits, fuse
from visvec.rotations import expmap, logmap
from visvec.sim.lamps import ImuModel


def test_planar_kalman_meets_the_fusion_target_and_learns_the_biases(tmp_path):
    imu, truth, fixes = planar_case(tmp_path)
    out = run(imu, fixes)
    tt = truth_table(truth)
    ok = [s for s in out if s.state is not None]
    # causal: nothing before the first fix is available (0.2 s + 0.6 s)
    assert out[0].state is None and ok[0].time_s >= 0.8 - 1e-9
    err = np.array([PlanarModel.values(s.state)[0][:2] - tt[s.index, :2] for s in ok])
    late = err[len(err) // 4 :]
    assert np.sqrt(np.mean(late**2)) < 2.0  # mm; the issue asks <= 5 mm
    x = ok[-1].state.x
    m = ImuModel()
    assert abs(math.degrees(x[5]) - m.gyro_bias_dps) < 0.05
    np.testing.assert_allclose(x[6:8] / 1000.0, m.accel_bias_mps2, atol=1.5e-3)
    # the paper's reset rule works too, but without bias estimates it is worse
    paper = run(imu, fixes, PlanarModel(method="paper"))
    e_paper = np.array([PlanarModel.values(s.state)[0][:2] - tt[s.index, :2]
                        for s in paper if s.state is not None])  # fmt: skip
    assert np.sqrt(np.mean(e_paper[len(e_paper) // 4 :] ** 2)) > np.sqrt(np.mean(late**2))


def test_planar_kalman_learns_the_fixes_time_offset(tmp_path):
    """Fixes stated 30 ms after their exposure (a camera's frames stamped when read):
    the filter learns the offset (within 2 ms) and the rows stay honest and within
    0.2 mm; with the offset held at 0 they were 2.7 mm off, most rows beyond 5 sigma."""
    from visvec.fuse.inputs import read_fixes, read_imu

    imu_p, truth, fixes_p = planar_case(tmp_path, duration=40.0, latency_ms=50.0, fix_hz=30.0)
    tt = truth_table(truth)
    late = [replace(f, time_s=f.time_s + 0.03, available_s=f.available_s + 0.03)
            for f in read_fixes(fixes_p).fixes]  # fmt: skip
    imu = read_imu(imu_p, planar=True)

    def rows(model):
        out = [s for s in fuse(imu, late, model) if s.state is not None]
        out = out[len(out) // 2 :]
        err = np.array([PlanarModel.values(s.state)[0][:2] - tt[s.index, :2] for s in out])
        sig = np.array([PlanarModel.values(s.state)[1][:2] for s in out])
        return out[-1].state, np.sqrt(np.mean(err**2)), np.abs(err) / sig

    state, rms, z = rows(PlanarModel())
    assert abs(state.x[8] - 0.03) < 0.002
    assert rms < 0.2 and np.sqrt(np.mean(z**2)) < 1.5 and z.max() < 5.0
    # the offset held at 0, and nothing learned of the fixes' timing (the lateness
    # state would take some of a constant offset too)
    held = PlanarModel(time_offset_sigma=0.0, time_offset_walk=0.0, learn_jitter=False)
    _, rms0, z0 = rows(held)
    assert rms0 > 1.0 and np.mean(z0 > 5.0) > 0.3


def test_planar_lateness_is_what_the_recent_fixes_show_beyond_the_jitter():
    """The lateness's variance (PlanarJitter.lasting) stays below the jitter's (its own
    noise) while the fixes' timing is as the long run's, and after one frame 10 ms late;
    it grows within a few fixes that come 5 ms late, to their lateness within ten, and
    is below the jitter again some tens of fixes after they are on time; the long-run
    jitter hardly moves."""
    rng = np.random.default_rng(1)
    S = np.diag([0.02**2, 0.02**2, math.radians(0.003) ** 2])  # a lamp fix's
    J = np.array([60.0, 20.0, 0.05])  # mm/s, rad/s
    jit = PlanarJitter(0.5e-3)
    cov = S + np.outer(J, J) * 0.5e-3**2

    def fixes(n, late_s):
        nonlocal jit
        for _ in range(n):
            jit = jit.learn(rng.multivariate_normal(J * late_s, cov), S, J)
        return jit

    # on time: what the short fit finds beyond the long is its own noise, of the
    # order of the jitter
    assert fixes(200, 0.0).lasting < 4 * jit.var
    assert abs(math.sqrt(jit.var) - 0.5e-3) < 0.15e-3
    assert fixes(1, 0.01).lasting < 4 * jit.var
    assert fixes(30, 0.0).lasting < 4 * jit.var
    assert math.sqrt(fixes(3, 0.005).lasting) > 1e-3
    assert math.sqrt(fixes(10, 0.005).lasting) > 3e-3
    assert math.sqrt(jit.var) < 1e-3  # the long-run fit, clipped, hardly moves
    assert fixes(60, 0.0).lasting < 4 * jit.var


@pytest.mark.slow  # 8 s on a slow host
def test_3d_fusion_learns_bias_and_misalignment():
    """Simulated gyro with a bias and a 3 deg misalignment; fixes 2 Hz, 0.6 s late."""
    rng = np.random.default_rng(4)
    dt, n = 0.01, 6000
    t = np.arange(n) * dt
    w_b = np.column_stack([0.8 * np.sin(0.7 * t), 0.6 * np.sin(1.1 * t + 1), 0.9 * np.cos(0.5 * t)])
    R = [np.eye(3)]
    for i in range(1, n):
        R.append(R[-1] @ expmap(0.5 * (w_b[i] + w_b[i - 1]) * dt))
    Rm = expmap(np.radians([2.0, -1.5, 1.8]))  # gyro axes -> body axes
    bias = np.radians([0.4, -0.3, 0.2])
    gyro = w_b @ Rm + bias + rng.normal(0, np.radians(0.05), (n, 3))
    imu = ImuData(t, gyro, None, np.arange(n) + 2, (), dt)
    fixes = [Fix(t[i], t[i] + 0.6, R[i] @ expmap(np.radians(0.1) * rng.standard_normal(3)),
                 None, i) for i in range(0, n, 50)]  # fmt: skip
    # the simulated gyro and fixes share one clock: no jitter between them
    model = AttitudeModel(gyro_noise=np.radians(0.05), jitter_sigma=0.0)
    out = list(fuse(imu, fixes, model, limits=Limits(2000.0, None)))
    s = out[-1].state
    assert np.degrees(np.linalg.norm(logmap(s.Rm.T @ Rm))) < 0.3
    np.testing.assert_allclose(np.degrees(s.b), np.degrees(bias), atol=0.03)
    e = np.array([np.degrees(np.linalg.norm(logmap(R[x.index].T @ x.state.R)))
                  for x in out[n // 2 :]])  # fmt: skip
    assert np.sqrt(np.mean(e**2)) < 0.1
    # without the misalignment states the same data fuse clearly worse
    out2 = list(fuse(imu, fixes, replace(model, misalignment_sigma=0.0), limits=Limits(2000, None)))
    e2 = np.array([np.degrees(np.linalg.norm(logmap(R[x.index].T @ x.state.R)))
                   for x in out2[n // 2 :]])  # fmt: skip
    assert np.sqrt(np.mean(e2**2)) > 2 * np.sqrt(np.mean(e**2))


def test_3d_time_offset_and_rest_bias_are_learned():
    """A gyro 20 ms late and at rest for the first 2 s: the filter finds both."""
    t, R, gyro, rng = _sim3d(delay=0.02, rest_s=2.0, amp=2.0)
    from visvec.fuse.replay import Fusion

    eng = Fusion(AttitudeModel(sample_s=0.01), limits=Limits(2000.0, None))
    out = _run_engine(eng, t, gyro, _fixes(t, R, rng))
    assert eng.rest is not None and eng.rest[2] >= 50  # the still start, to the first fix
    np.testing.assert_allclose(np.degrees(eng.rest[0]), [0.4, -0.3, 0.2], atol=0.02)
    assert abs(out[-1].state.tau - 0.02) < 0.003
    late = _err(out, R, len(t) // 2)
    assert np.sqrt(np.mean(late**2)) < 0.15


@pytest.mark.slow  # 4-7 s: the default run stays under 5 minutes
def test_3d_a_drifting_clock_is_followed():
    """The gyro's clock runs 300 ppm slow against the fixes': its time offset grows from
    0 to 18 ms over the minute. The filter learns the clocks' rate difference and ends
    at the offset of the moment, not at the minute's mean."""
    from visvec.fuse.replay import Fusion

    t, R, gyro, rng = _sim3d(drift=3e-4, amp=2.0)
    eng = Fusion(AttitudeModel(sample_s=0.01), limits=Limits(2000.0, None))
    fx = _fixes(t, R, rng)
    out = _run_engine(eng, t, gyro, fx)
    end = out[-1].state
    assert abs(end.drift - 3e-4) < 0.6e-4, end.drift
    assert abs(end.tau - 3e-4 * t[-1]) < 0.003, end.tau
    # without the clock's rate the offset lags behind (the minute's weighted mean)
    eng0 = Fusion(AttitudeModel(sample_s=0.01, clock_drift_sigma=0.0), limits=Limits(2000.0, None))
    out0 = _run_engine(eng0, t, gyro, fx)
    assert out0[-1].state.tau < end.tau - 0.003
    late = _err(out, R, len(t) // 2)
    assert np.sqrt(np.mean(late**2)) < np.sqrt(np.mean(_err(out0, R, len(t) // 2) ** 2))


def test_3d_a_fix_after_a_saturated_reading_corrects_only_the_attitude():
    """The interval before the fix held a reconstructed (clipped) reading: its error is
    the reconstruction's, and the fix must not read it as bias, misalignment, scale or
    clock."""
    model = AttitudeModel(sample_s=0.01)
    fix0 = Fix(0.0, 0.0, np.eye(3), np.eye(3) * np.radians(0.1) ** 2, 0)
    s = model.init(fix0)
    w = np.radians([450.0, -80.0, 300.0])
    for i in range(50):
        sat = np.radians([40.0, 0.0, 0.0]) if 20 <= i < 25 else np.zeros(3)
        s = model.propagate(s, np.array([w, np.radians([500.0, -300.0, 800.0]), sat]), None,
                            0.01)  # fmt: skip
    assert s.saturated
    fix = Fix(0.5, 0.5, s.R @ expmap(np.radians([2.0, -1.0, 0.5])), fix0.cov, 1)
    new, taken, _ = model.update(s, fix)
    assert taken
    assert np.degrees(np.linalg.norm(logmap(new.R.T @ fix.value))) < 0.3
    np.testing.assert_array_equal(new.b, s.b)
    np.testing.assert_array_equal(new.k, s.k)
    np.testing.assert_array_equal(new.Rm, s.Rm)
    assert (new.tau, new.drift) == (s.tau, s.drift)


def test_3d_clock_jitter_keeps_the_sigma_honest():
    """A gyro whose clock wanders against the fixes' (a Gauss-Markov time error of
    10 ms, 0.2 s) on a body that rests and swings in short bursts (a hand, a bump):
    with the default jitter (one sample period, a considered state) the rows' errors
    stay within their sigma as a Gaussian's would; a filter told that the clocks agree
    is overconfident in the bursts."""
    rng = np.random.default_rng(7)
    dt, n = 0.01, 3000
    t = np.arange(n) * dt
    w_b = np.zeros((n, 3))
    for c in np.arange(0.7, t[-1] - 0.5, 0.9):
        # a swing out and back: a 0.3 s sine of up to 4 rad/s about a random axis
        axis = rng.standard_normal(3)
        m = (t >= c) & (t < c + 0.3)
        w_b[m] = np.outer(4.0 * np.sin(2 * np.pi * (t[m] - c) / 0.3), axis / np.linalg.norm(axis))
    R = [np.eye(3)]
    for i in range(1, n):
        R.append(R[-1] @ expmap(0.5 * (w_b[i] + w_b[i - 1]) * dt))
    a = np.exp(-dt / 0.2)
    d = np.zeros(n)
    for i in range(1, n):
        d[i] = a * d[i - 1] + 0.010 * np.sqrt(1 - a * a) * rng.standard_normal()
    # each reading is the body rate at its own, wandering time
    w_at = np.column_stack([np.interp(t + d, t, w_b[:, k]) for k in range(3)])
    gyro = w_at + rng.normal(0, np.radians(0.05), (n, 3))
    imu = ImuData(t, gyro, None, np.arange(n) + 2, (), dt)
    fixes = [Fix(t[i], t[i] + 0.6, R[i] @ expmap(np.radians(0.1) * rng.standard_normal(3)),
                 None, i) for i in range(0, n, 50)]  # fmt: skip

    def beyond(model):
        z = []
        for x in fuse(imu, fixes, model, limits=Limits(2000.0, None)):
            if x.state is None or x.index < 500:
                continue
            e = logmap(x.state.R.T @ R[x.index])
            z.extend(np.abs(e) / np.sqrt(np.diag(x.state.P[:3, :3])))
        z = np.array(z)
        return float(np.mean(z > 3.0)), int(np.sum(z > 5.0))

    model = AttitudeModel(sample_s=dt)
    assert model.jitter == dt
    share, over5 = beyond(model)
    assert share <= 2 * 0.0027 and over5 == 0
    share0, over5_0 = beyond(replace(model, jitter_sigma=0.0))
    assert share0 > 3 * max(share, 0.0027) and over5_0 > 0


def test_3d_a_fix_after_a_dispute_is_unconfirmed_until_the_next_agrees():
    """The gyro misses a 40 deg turn (a dropout): the filter refuses the fixes that see
    it, widening its prediction by the disagreement, takes the next one through that
    wide gate, and says `fix_unconfirmed` until a fix agrees through a narrow gate;
    then the rows are accurate and unwarned again."""
    rng = np.random.default_rng(11)
    dt, n = 0.01, 2500
    t = np.arange(n) * dt
    w_b = np.column_stack([0.3 * np.sin(0.9 * t), 0.2 * np.cos(1.3 * t), 0.25 * np.sin(0.4 * t)])
    turn = (t >= 8.0) & (t < 8.2)
    w_b[turn, 2] += np.radians(40.0) / 0.2
    R = [np.eye(3)]
    for i in range(1, n):
        R.append(R[-1] @ expmap(0.5 * (w_b[i] + w_b[i - 1]) * dt))
    gyro = w_b + rng.normal(0, np.radians(0.05), (n, 3))
    gyro[turn, 2] -= np.radians(40.0) / 0.2  # the dropout: the gyro never saw the turn
    imu = ImuData(t, gyro, None, np.arange(n) + 2, (), dt)
    fixes = [Fix(t[i], t[i] + 0.6, R[i] @ expmap(np.radians(0.1) * rng.standard_normal(3)),
                 None, i) for i in range(0, n, 50)]  # fmt: skip
    out = list(fuse(imu, fixes, AttitudeModel(sample_s=dt), limits=Limits(2000.0, None)))
    disputed = [x.index for x in out if "fix_disputed" in x.warnings]
    unconfirmed = [x.index for x in out if "fix_unconfirmed" in x.warnings]
    assert disputed and 8.0 < t[disputed[0]] < 9.0
    # the wide gate's fix follows the dispute at once, and the next fix confirms it
    assert unconfirmed and unconfirmed[0] == disputed[-1] + 1
    assert t[unconfirmed[-1]] - t[unconfirmed[0]] <= 0.5 + 1e-9
    after = [x for x in out if t[x.index] > t[unconfirmed[-1]]]
    assert after and not any(x.warnings for x in after)
    e = [np.degrees(np.linalg.norm(logmap(R[x.index].T @ x.state.R))) for x in after]
    assert max(e) < 1.0


def test_3d_a_burst_moves_the_attitude_not_the_gyro_calibration():
    """A fix taken though far off (NIS between the burst level and the gate): the
    attitude goes to the fix, and the gyro's scale factors, bias, misalignment and time
    offset take much less than a plain Kalman gain would give them, since the model has
    no account of a burst (a swing beyond the gyro's linear range)."""
    from visvec.chi2 import ppf
    from visvec.fuse.gate import BURST_P, NIS_P

    model = AttitudeModel(sample_s=0.01, jitter_sigma=0.0)
    fix0 = Fix(0.0, 0.0, np.eye(3), np.eye(3) * np.radians(0.1) ** 2, 0)
    s = model.init(fix0)
    w = np.radians([120.0, -80.0, 300.0])  # a fast turn correlates attitude and calibration
    reading = np.array([w, np.radians([500.0, -300.0, 800.0]), np.zeros(3)])  # rate, its change
    for _ in range(50):
        s = model.propagate(s, reading, None, 0.01)
    S = s.P[0:3, 0:3] + fix0.cov
    # an innovation of NIS 20 along the attitude's largest-sigma axis
    ev, V = np.linalg.eigh(S)
    r = V[:, -1] * np.sqrt(20.0 * ev[-1])
    fix = Fix(0.5, 0.5, s.R @ expmap(r), fix0.cov, 1)
    new, taken, nis = model.update(s, fix)
    assert taken and ppf(1.0 - BURST_P, 3) < nis < ppf(1.0 - NIS_P, 3)
    assert np.degrees(np.linalg.norm(logmap(new.R.T @ fix.value))) < 3 * 0.1  # at the fix
    K = np.linalg.solve(S, s.P[0:3, :]).T  # the plain gain
    plain = K @ r
    for sl, got in ((slice(9, 12), new.k - s.k), (slice(3, 6), new.b - s.b),
                    (slice(12, 13), np.array([new.tau - s.tau]))):  # fmt: skip
        assert np.linalg.norm(plain[sl]) > 0.0
        assert np.linalg.norm(got) < 0.5 * np.linalg.norm(plain[sl]), (sl, got, plain[sl])


def test_3d_a_glitched_fix_leaves_the_rows_honest_and_unconfirmed():
    """A fix 0.45 deg off (a motion capture's glitch: BROAD 18 at 154.2 s, 0.57 deg) on
    a still platform, about 4.5 of its filter's sigmas: taken as a burst, the attitude
    goes to it, but the rows' covariance holds both the filter's old attitude and the
    fix (each within 2-3 sigma of the truth) and they say fix_unconfirmed until the next
    fix, which agrees with the truth and ends it."""
    t = np.arange(1500) * 0.01
    R = [np.eye(3)] * len(t)
    rng = np.random.default_rng(2)
    gyro = rng.normal(0, np.radians(0.05), (len(t), 3))
    fixes = _fixes(t, R, rng)
    bad = 12
    fixes[bad] = replace(fixes[bad], value=expmap(np.radians([0.45, 0.0, 0.0])))
    imu = ImuData(t, gyro, None, np.arange(len(t)) + 2, (), 0.01)
    out = list(fuse(imu, fixes, AttitudeModel(sample_s=0.01), limits=Limits(2000.0, None)))
    k0 = int(np.searchsorted(t, fixes[bad].available_s))
    k1 = int(np.searchsorted(t, fixes[bad + 1].available_s))
    # the glitch is taken, not refused (its NIS is below the gate)
    assert "fix_rejected" not in out[k0].warnings
    between = out[k0 + 1 : k1]
    assert between and all("fix_unconfirmed" in x.warnings for x in between)
    for x in between:
        err = logmap(x.state.R)  # the truth is the identity
        assert float(err @ np.linalg.solve(x.state.P[0:3, 0:3], err)) < 14.2  # 3 sigma, 3 dof
    after = out[k1 + 5 :]
    assert all("fix_unconfirmed" not in x.warnings for x in after[:100])
    assert np.degrees(np.linalg.norm(logmap(after[100].state.R))) < 0.25
