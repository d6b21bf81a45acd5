"""Results a lab can plot: --errors and --summary beside --truth, and `visvec plot`."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from conftest import ROOT, run

RIG = ROOT / "configs" / "triangle.toml"
SAMPLES = ROOT / "data" / "sample_frames"


def rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_errors_and_summary_files(tmp_path):
    out, err, summ = tmp_path / "rows.csv", tmp_path / "err.csv", tmp_path / "sum.json"
    r = run("batch", SAMPLES, "--rig", RIG, "--truth", SAMPLES / "truth.csv", "--out", out,
            "--errors", err, "--summary", summ)  # fmt: skip
    assert r.exit_code == 0, r.output
    got, truth = rows(out), {int(t["frame"]): t for t in rows(SAMPLES / "truth.csv")}
    errs = rows(err)
    assert [int(e["frame"]) for e in errs] == [int(g["frame"]) for g in got]
    for e, g in zip(errs, got, strict=True):
        t = truth[int(g["frame"])]
        for k in ("yaw_deg", "pitch_deg", "roll_deg"):
            want = float(g[k]) - float(t[k])
            want = (want + 180) % 360 - 180
            # the rows file holds the values to 1e-6 deg, the errors file to 9 digits
            assert float(e[f"err_{k}"]) == pytest.approx(want, abs=1.5e-6)
            sig = float(g[f"sigma_{k}"])
            assert float(e[f"z_{k}"]) == pytest.approx(want / sig, abs=2e-6 / sig)
    s = json.loads(summ.read_text())
    assert s["rows"] == len(got) and s["ok"] == sum(g["status"] == "ok" for g in got)
    rms_yaw = math.sqrt(sum(float(e["err_yaw_deg"]) ** 2 for e in errs) / len(errs))
    assert s["truth"]["rms"]["yaw_deg"] == pytest.approx(rms_yaw, rel=1e-6)
    z = [abs(float(e[f"z_{k}"])) for e in errs for k in ("yaw_deg", "pitch_deg", "roll_deg")]
    assert s["truth"]["beyond_3sigma_share"] == pytest.approx(sum(x > 3 for x in z) / len(z))
    assert s["truth"]["beyond_5sigma_count"] == sum(x > 5 for x in z)


def test_errors_needs_truth_and_a_writable_place(tmp_path):
    r = run("batch", SAMPLES, "--rig", RIG, "--errors", tmp_path / "e.csv")
    assert r.exit_code == 2 and "--errors needs --truth" in r.output
    (tmp_path / "a-file").write_text("x")
    where = tmp_path / "a-file" / "s.json"  # under a file: can never be written
    r = run("batch", SAMPLES, "--rig", RIG, "--truth", SAMPLES / "truth.csv", "--summary",
            where, "--out", tmp_path / "rows.csv")  # fmt: skip
    # refused before any frame: no rows written
    assert r.exit_code == 2 and "--summary" in r.output
    assert not (tmp_path / "rows.csv").exists()


def test_plot_draws_a_run_and_its_truth(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "rows.csv"
    assert run("batch", SAMPLES, "--rig", RIG, "--out", out).exit_code == 0
    fig = tmp_path / "run.png"
    r = run("plot", out, "--truth", SAMPLES / "truth.csv", "--out", fig)
    assert r.exit_code == 0, r.output
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and fig.stat().st_size > 30_000
    assert "12 of 12 attitude rows ok" in r.output and "RMS error yaw_deg" in r.output
    svg = tmp_path / "run.svg"
    assert run("plot", out, "--out", svg).exit_code == 0 and b"<svg" in svg.read_bytes()[:500]


def test_plot_refuses_a_file_that_is_not_rows(tmp_path):
    pytest.importorskip("matplotlib")
    bad = tmp_path / "other.csv"
    bad.write_text("a,b\n1,2\n")
    r = run("plot", bad, "--out", tmp_path / "f.png")
    assert r.exit_code == 2 and "other.csv: not visvec rows: needs the columns" in r.output
    assert "yaw_deg" in r.output and not (tmp_path / "f.png").exists()
    r = run("plot", bad, "--out", tmp_path / "f.jpg")
    assert r.exit_code == 2 and ".png, .svg or .pdf" in r.output


def test_covariance_columns(tmp_path):
    """--covariance: each ok row's 3x3 covariance, its diagonal the sigmas squared."""
    out = tmp_path / "rows.csv"
    assert run("batch", SAMPLES, "--rig", RIG, "--covariance", "--out", out).exit_code == 0
    got = rows(out)
    names = ("yaw", "pitch", "roll")
    for g in got:
        for n in names:
            sig = float(g[f"sigma_{n}_deg"])
            assert float(g[f"cov_{n}_{n}"]) == pytest.approx(sig**2, rel=2e-3)
        c = [[float(g[f"cov_{min(a, b, key=names.index)}_{max(a, b, key=names.index)}"])
              for b in names] for a in names]  # fmt: skip
        import numpy as np

        assert np.all(np.linalg.eigvalsh(np.array(c)) > 0)  # a covariance
    lamps = ROOT / "configs" / "lamps.toml"
    rec = tmp_path / "rec"
    assert run("simulate", "--rig", lamps, "--out", rec, "--frames", 4).exit_code == 0
    assert run("batch", rec, "--rig", lamps, "--covariance", "--out", out).exit_code == 0
    for g in rows(out):
        # the sigmas are written to 5 decimals: their squares are known to 2 sigma 5e-6
        for cov, sig in (("cov_x_x", "sigma_x_mm"), ("cov_heading_heading", "sigma_heading_deg")):
            s = float(g[sig])
            assert float(g[cov]) == pytest.approx(s**2, rel=1e-3, abs=2 * s * 5e-6)


def test_time_unix_from_a_recording_with_it(tmp_path):
    """A recording whose times.csv has time_unix (as `track --save-frames` writes it)
    gives its rows those times; one without leaves the column empty."""
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(SAMPLES, rec, ignore=shutil.ignore_patterns("truth.csv"))
    names = sorted(p.name for p in rec.glob("*.png"))
    base = 1_790_000_000.25
    with open(rec / "times.csv", "w") as fh:
        fh.write("file,time_s,time_unix\n")
        for i, n in enumerate(names):
            fh.write(f"{n},{i / 30:.6f},{base + i / 30:.6f}\n")
    out = tmp_path / "rows.csv"
    assert run("batch", rec, "--rig", RIG, "--out", out).exit_code == 0
    got = rows(out)
    assert [float(g["time_unix"]) for g in got] == pytest.approx(
        [base + i / 30 for i in range(len(names))], abs=1e-6
    )
    assert run("batch", SAMPLES, "--rig", RIG, "--out", out).exit_code == 0
    assert {g["time_unix"] for g in rows(out)} == {""}


def test_fuse_writes_errors_and_summary(tmp_path):
    """`visvec fuse --truth --errors --summary`: the fused rows' errors and figures."""
    lamps = ROOT / "configs" / "lamps.toml"
    rec = tmp_path / "rec"
    # 3 s: the fusion first aligns the fixes' clock with the IMU's (about 1 s)
    assert run("simulate", "--rig", lamps, "--out", rec, "--frames", 90, "--imu").exit_code == 0
    fixes = tmp_path / "fixes.csv"
    assert run("batch", rec, "--rig", lamps, "--out", fixes).exit_code == 0
    out, err, summ = tmp_path / "fused.csv", tmp_path / "err.csv", tmp_path / "sum.json"
    r = run("fuse", "--imu", rec / "imu.csv", "--fixes", fixes, "--truth", rec / "imu_truth.csv",
            "--out", out, "--errors", err, "--summary", summ)  # fmt: skip
    assert r.exit_code == 0, r.output
    fused, errs = rows(out), rows(err)
    assert len(errs) == len(fused)
    ok = [e for e in errs if e["status"] == "ok"]
    rms_x = math.sqrt(sum(float(e["err_x_mm"]) ** 2 for e in ok) / len(ok))
    s = json.loads(summ.read_text())
    assert s["rows"] == len(fused) and s["truth"]["rms"]["x_mm"] == pytest.approx(rms_x, rel=1e-6)
    r = run("fuse", "--imu", rec / "imu.csv", "--fixes", fixes, "--errors", err)
    assert r.exit_code == 2 and "--errors needs --truth" in r.output
