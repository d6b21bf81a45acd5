"""Studies on Dask (visvec.distribute, `visvec montecarlo --scheduler/--workers`): the
same numbers as a serial run, a worker that dies, a scheduler that does not answer, a
worker with another visvec, Ctrl-C keeping the finished runs. Clusters bind 127.0.0.1
and are closed by the tests."""

from __future__ import annotations

import json
import os
import threading

import pytest
from click.testing import CliRunner

import visvec
from visvec.bench.markers import RunSpec, run_one
from visvec.cli.main import cli
from visvec.distribute import TaskPool
from visvec.errors import SourceError
from visvec.rig import load_rig

from conftest import CONFIGS

distributed = pytest.importorskip("distributed")

SMALL = ["--rig", str(CONFIGS / "markers.toml"), "--runs", "3", "--centroid-noise", "0.1",
         "--marker-error", "0,0.1", "--frames", "20", "--poses", "20"]  # fmt: skip


def _study(tmp_path, name, *extra):
    out = tmp_path / name
    r = CliRunner().invoke(cli, ["montecarlo", *SMALL, "--out", str(out), *extra])
    assert r.exit_code == 0, r.output
    return (out / "montecarlo.json").read_bytes(), r.output


@pytest.fixture
def cluster():
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=40) as c:  # fmt: skip
        yield c


@pytest.mark.slow  # 10 s on a slow host
def test_a_study_on_dask_is_the_serial_study_bit_for_bit(tmp_path, cluster):
    serial, out = _study(tmp_path, "serial", "--workers", "1")
    assert "on this process" in out
    local, out = _study(tmp_path, "local", "--workers", "2")
    assert "on a local Dask cluster of 2 workers" in out
    remote, out = _study(tmp_path, "remote", "--scheduler", cluster.scheduler_address)
    assert f"on Dask scheduler {cluster.scheduler_address} (2 workers)" in out
    assert serial == local == remote
    assert len(json.loads(serial)["runs"]) == 6


@pytest.mark.slow  # 7 s on a slow host
def test_a_worker_that_dies_has_its_tasks_rerun(cluster):
    rig = load_rig(CONFIGS / "markers.toml")
    specs = [RunSpec(rig, 0.1, 0.0, 100 + k, 20, 20, True) for k in range(8)]
    expected = [run_one(s) for s in specs]
    killed = threading.Event()

    def kill_one(i, r):
        if not killed.is_set():
            killed.set()
            victim = sorted(pool._client.scheduler_info()["workers"])[0]
            try:
                pool._client.run(lambda: os._exit(1), workers=[victim])
            except Exception:
                pass  # the worker died while answering

    with TaskPool(cluster.scheduler_address) as pool:
        got = pool.map(run_one, specs, kill_one)
    assert killed.is_set()
    assert json.dumps(got) == json.dumps(expected)


def test_a_scheduler_that_does_not_answer_is_exit_3_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setattr("visvec.distribute.CONNECT_TIMEOUT_S", 1.0)
    out = tmp_path / "none"
    r = CliRunner().invoke(cli, ["montecarlo", *SMALL, "--out", str(out),
                                 "--scheduler", "tcp://127.0.0.1:9"])  # fmt: skip
    assert r.exit_code == 3
    assert "Dask scheduler tcp://127.0.0.1:9: no answer within 1 s" in r.output
    assert not (out / "montecarlo.json").exists()
    r = CliRunner().invoke(cli, ["montecarlo", *SMALL, "--out", str(out), "--scheduler", "nope"])
    assert r.exit_code == 2 and "tcp://HOST:PORT" in r.output


def test_workers_with_another_visvec_are_refused_naming_both(cluster, monkeypatch):
    monkeypatch.setattr(visvec, "__version__", "9.9.9")
    with pytest.raises(SourceError) as e:
        TaskPool(cluster.scheduler_address).__enter__()
    msg = str(e.value)
    assert "its workers must run visvec 9.9.9" in msg
    assert msg.count("has visvec 0.1.0") == 2


def test_ctrl_c_keeps_every_finished_run(tmp_path, monkeypatch):
    calls = []

    def interrupted(spec):
        calls.append(spec.seed)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return run_one(spec)

    monkeypatch.setattr("visvec.cli.montecarlo.run_one", interrupted)
    out = tmp_path / "stopped"
    r = CliRunner().invoke(cli, ["montecarlo", *SMALL, "--out", str(out), "--workers", "1"])
    assert r.exit_code == 130
    study = json.loads((out / "montecarlo.json").read_text())
    assert study["interrupted"] and study["runs_finished"] == 2
    assert [x["seed"] for x in study["runs"]] == calls[:2]
    assert "2 of 6 runs finished" in r.output
