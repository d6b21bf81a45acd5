"""The replay engine: late and out-of-order fixes, causal rows, faults and gaps, a
saturated gyro rebuilt, no lock-out."""

from dataclasses import replace

import numpy as np
import pytest
from fusion_cases import _err, _fixes, _sim3d, planar_case, truth_table

from visvec.fuse.attitude import AttitudeModel
from visvec.fuse.inputs import ImuData, read_fixes, read_imu
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import Limits, fuse
from visvec.rotations import expmap, logmap


def test_out_of_order_fixes_give_the_same_state_as_in_order(tmp_path):
    imu_p, _, fixes_p = planar_case(tmp_path, duration=20.0)
    fx = read_fixes(fixes_p)
    imu = read_imu(imu_p, planar=True)
    rng = np.random.default_rng(1)
    shuffled = [replace(f, available_s=f.time_s + rng.uniform(0.1, 3.0))
                for f in fx.fixes if f.time_s < 15.0]  # fmt: skip
    # in order: each 3 s late (as late as the latest shuffled one, and within the
    # history: a fix older than it is dropped, fix_too_old)
    in_order = [replace(f, available_s=f.time_s + 3.0) for f in shuffled]
    last = max(f.available_s for f in shuffled + in_order)
    a = list(fuse(imu, shuffled, PlanarModel()))
    b = list(fuse(imu, in_order, PlanarModel()))
    k = int(np.searchsorted(imu.t, last)) + 1
    for i in (k, len(imu) - 1):
        np.testing.assert_allclose(a[i].state.x, b[i].state.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a[i].state.P, b[i].state.P, rtol=1e-7, atol=1e-12)
    # arrival order really differed
    assert [f.time_s for f in sorted(shuffled, key=lambda f: f.available_s)] != sorted(
        f.time_s for f in shuffled
    )


def test_rows_are_causal(tmp_path):
    imu_p, _, fixes_p = planar_case(tmp_path, duration=15.0)
    fx = read_fixes(fixes_p)
    imu = read_imu(imu_p, planar=True)
    full = list(fuse(imu, fx.fixes, PlanarModel()))
    t_cut = 8.0
    early = [f for f in fx.fixes if f.available_s <= t_cut]
    part = list(fuse(imu, early, PlanarModel()))
    k = int(np.searchsorted(imu.t, t_cut, side="right")) - 1
    for i in range(k - 5, k + 1):
        np.testing.assert_array_equal(full[i].state.x, part[i].state.x)
    assert not np.array_equal(full[-1].state.x, part[-1].state.x)


def test_faults_are_not_integrated_and_gaps_restart(tmp_path):
    imu_p, truth, fixes_p = planar_case(tmp_path, duration=20.0)
    fx = read_fixes(fixes_p)
    imu = read_imu(imu_p, planar=True)
    out = list(fuse(imu, fx.fixes, PlanarModel()))
    bad = [s for s in out if "imu_fault" in s.warnings]
    assert bad and len(bad) == int(np.sum(np.abs(np.degrees(imu.gyro[:, 2])) > 50.0))
    none = list(fuse(imu, fx.fixes, PlanarModel(), limits=Limits(None, None)))
    tt = truth_table(truth)

    def rms(o):
        e = [PlanarModel.values(s.state)[0][:2] - tt[s.index, :2] for s in o if s.state]
        return np.sqrt(np.mean(np.square(e)))

    assert rms(out) < rms(none)  # integrating the spikes would hurt
    # cut 1 s out of the samples: the filter stops at the gap and waits for a new fix
    keep = (imu.t < 10.0) | (imu.t >= 11.0)
    gap = replace(imu, t=imu.t[keep], gyro=imu.gyro[keep], accel=imu.accel[keep],
                  lines=imu.lines[keep], gaps=(int(np.sum(imu.t < 10.0)),))  # fmt: skip
    out = list(fuse(gap, fx.fixes, PlanarModel()))
    k = gap.gaps[0]
    assert "imu_gap" in out[k].warnings and out[k].state is None
    first_after = min(f.available_s for f in fx.fixes if f.time_s >= 11.0)
    resumed = next(s for s in out[k:] if s.state is not None)
    assert resumed.time_s >= first_after - 1e-9


def test_3d_no_lock_out_after_a_bump_and_honest_sigma():
    """A bump the gyro does not see (the platform knocked by 8 deg between two fixes):
    the fixes are taken again within two fixes, and the rows meanwhile are either
    within 3 sigma or flagged."""
    t, R, gyro, rng = _sim3d()
    # the truth after the bump: the old path turned by 8 deg about the lab's n1 at i0
    # (the body rate, and so the gyro, is the same before and after)
    kick = expmap(np.radians([8.0, 0.0, 0.0]))
    i0 = 3025
    Rt = [r if i < i0 else kick @ r for i, r in enumerate(R)]
    imu = ImuData(t, gyro, None, np.arange(len(t)) + 2, (), 0.01)
    fixes = _fixes(t, Rt, rng)
    out = list(fuse(imu, fixes, AttitudeModel(sample_s=0.01), limits=Limits(2000.0, None)))
    e = _err(out, Rt)
    # fixes after the bump: the second one's arrival (0.6 s late) ends the disagreement
    after = [f for f in fixes if f.time_s > t[i0]]
    k_ok = int(np.searchsorted(t, after[1].available_s)) + 1
    assert np.all(e[k_ok + 50 :] < 0.5)
    # from the first fix that disagrees (nothing can see the bump before it)
    k_first = int(np.searchsorted(t, after[0].available_s)) + 1
    bad = [x for x in out[k_first:k_ok] if x.state is not None]
    assert any("fix_disputed" in x.warnings for x in bad)
    for x in bad:
        err = np.degrees(np.linalg.norm(logmap(Rt[x.index].T @ x.state.R)))
        sig = np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(x.state.P[0:3, 0:3]))))
        assert err < 3 * sig or x.warnings, (x.index, err, sig)


def test_declip_restores_a_clipped_swing():
    """A clipped sine's flat top, rebuilt from two samples on either side, is closer
    to the truth than the flat top, and never inside the range."""
    from visvec.fuse.saturation import declip

    t = np.arange(0, 0.5, 0.01)
    v = 6.0 * np.sin(2 * np.pi * 1.3 * t)
    rng = 5.0
    clip = np.abs(v) >= rng
    at = np.nonzero(clip)[0]
    at = at[: np.argmax(np.diff(at) > 1) + 1] if np.any(np.diff(at) > 1) else at  # 1st top
    known = np.r_[at[0] - 3 : at[0], at[-1] + 1 : at[-1] + 4]
    est = declip(t, np.clip(v, -rng, rng), known, t[at], rng, 1.0)
    assert np.all(est >= rng)
    assert np.abs(est - v[at]).mean() < 0.5 * np.abs(rng - v[at]).mean()


@pytest.mark.slow  # 8 s on a slow host
def test_3d_saturated_gyro_is_flagged_and_honest():
    """A gyro clipped at 250 deg/s on a swing that peaks at about 320 deg/s: the flat
    tops are found, the rows flagged, and their sigma covers the error."""
    t, R, gyro, rng = _sim3d(amp=7.0, n=3000, speed=12.0)
    rng_clip = np.radians(250.0)
    clipped = np.clip(gyro, -rng_clip, rng_clip)
    assert np.sum(np.abs(gyro) > rng_clip) > 50
    imu = ImuData(t, clipped, None, np.arange(len(t)) + 2, (), 0.01)
    out = list(fuse(imu, _fixes(t, R, rng), AttitudeModel(sample_s=0.01),
                    limits=Limits(2000.0, None)))  # fmt: skip
    flagged = [x for x in out if "gyro_saturated" in x.warnings]
    assert len(flagged) > 50
    z = []
    for x in out[300:]:
        err = logmap(R[x.index].T @ x.state.R)
        z.append(float(err @ np.linalg.solve(x.state.P[0:3, 0:3], err)))
    # the attitude error's Mahalanobis distance: chi-square with 3 dof when honest
    assert np.mean(np.array(z) > 14.2) < 0.01  # chi2(3) beyond 14.2: 0.27 %


def test_the_engines_state_after_a_step_cut_short(tmp_path):
    """Ctrl-C in the middle of a step (a live run stopped) leaves that sample's state
    unfilled: the engine's state, from which a live run's closing line says what the
    filter learned, is then the newest one filled, not None."""
    from dataclasses import dataclass

    from visvec.fuse.replay import Fusion

    imu_p, _, fixes_p = planar_case(tmp_path, duration=6.0)
    fx = read_fixes(fixes_p)
    imu = read_imu(imu_p, planar=True)

    @dataclass(frozen=True)
    class Stopped(PlanarModel):
        calls: list = None

        def propagate(self, s, gyro, accel, dt):
            self.calls.append(1)
            if len(self.calls) == 450:
                raise KeyboardInterrupt
            return super().propagate(s, gyro, accel, dt)

    eng = Fusion(Stopped(calls=[]))
    fixes = sorted(fx.fixes, key=lambda f: f.available_s)
    last = None
    with pytest.raises(KeyboardInterrupt):
        for j, t in enumerate(imu.t):
            while fixes and fixes[0].available_s <= t:
                eng.add_fix(fixes.pop(0))
            fs = eng.step(t, imu.gyro[j], imu.accel[j] if imu.accel is not None else None)
            last = fs.state if fs.state is not None else last
    assert last is not None and eng.history.states[-1] is None
    assert eng.state is last


@pytest.mark.parametrize("gyro_range_dps", [None, 250.0])
def test_a_replay_s_runs_give_the_states_step_by_step_gives(gyro_range_dps):
    """A file replay takes the samples between two fixes' arrivals in one Fusion.run
    (their states propagated in one call): every state, warning and index must be
    those of Fusion.step taken sample by sample, to the bit, through a clipping gyro
    whose flat tops are rebuilt as they end (readings rewritten behind the newest
    sample), a faulty sample, a clock that steps back and a gap."""
    t, R, gyro, _ = _sim3d(amp=7.0, n=2500, speed=12.0, rest_s=3.0)
    g = np.clip(gyro, -np.radians(250.0), np.radians(250.0))
    g[1700] = [np.nan, 0.0, 0.0]  # a fault
    t = t.copy()
    t[1900] = t[1899] - 0.001  # the clock steps back
    fixes = _fixes(t, R, np.random.default_rng(3), every=37)
    imu = ImuData(t, g, None, np.arange(len(t)), (2100,), 0.01)
    model = AttitudeModel()
    limits = Limits(max_rate_dps=None, max_accel_mps2=None)
    runs = list(fuse(imu, fixes, model, limits=limits, gyro_range_dps=gyro_range_dps))
    from visvec.fuse.replay import Fusion

    eng = Fusion(model, limits=limits, gyro_range_dps=gyro_range_dps)
    arrivals = sorted(fixes, key=lambda f: (f.available_s, f.time_s))
    nxt, one = 0, []
    for k in range(len(t)):
        while nxt < len(arrivals) and arrivals[nxt].available_s <= t[k]:
            eng.add_fix(arrivals[nxt])
            nxt += 1
        one.append(eng.step(float(t[k]), g[k], None, gap=k == 2100, index=k))
    assert len(runs) == len(one) == len(t)
    for a, b in zip(runs, one, strict=True):
        assert (a.index, a.time_s, a.warnings, a.n_fixes, a.nis) == (
            b.index, b.time_s, b.warnings, b.n_fixes, b.nis)  # fmt: skip
        if b.state is None:
            assert a.state is None
            continue
        assert np.array_equal(a.state.R, b.state.R) and np.array_equal(a.state.P, b.state.P)
    warned = {w for s in one for w in s.warnings}
    assert {"imu_fault", "imu_time_back", "imu_gap"} <= warned
    if gyro_range_dps is not None:
        assert sum("gyro_saturated" in s.warnings for s in one) > 50
