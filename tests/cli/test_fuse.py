"""`visvec fuse` from the command line: planar and 3-D files."""

import csv
import re

import numpy as np
import pytest
from click.testing import CliRunner
from fusion_cases import (
    planar_case,
    write,
)

from visvec.cli.main import cli
from visvec.output import PLANAR_COLUMNS
from visvec.rotations import logmap


def test_fuse_cli(tmp_path):
    imu, truth, fixes = planar_case(tmp_path, duration=12.0)
    out = tmp_path / "fused.csv"
    r = CliRunner().invoke(cli, ["fuse", "--imu", str(imu), "--fixes", str(fixes), "--out",
                                 str(out), "--truth", str(truth), "--rest-s", "2"])  # fmt: skip
    assert r.exit_code == 0, r.output
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(PLANAR_COLUMNS) and len(rows) == 1201
    assert rows[0]["status"] == "no_target" and "no_fix_yet" in rows[0]["warnings"]
    assert rows[-1]["status"] == "ok" and float(rows[-1]["sigma_x_mm"]) > 0
    assert "biases from" in r.output and "mean NIS" in r.output and "x: rms" in r.output
    # what the filter learned, the fixes' time offset first (these are on time: near 0)
    m = re.search(r"learned: fixes' time offset ([-+][\d.]+) \+- ([\d.]+) ms", r.output)
    assert m and abs(float(m[1])) < 3 * float(m[2]) + 1.0, r.output
    bad = write(tmp_path, "bad.csv", "time_s,gz_dps,ax_mps2,ay_mps2\n0,0,0,0\n-1,0,0,0\n")
    r = CliRunner().invoke(cli, ["fuse", "--imu", str(bad), "--fixes", str(fixes)])
    assert r.exit_code == 2 and "line 3" in r.output
    r = CliRunner().invoke(cli, ["fuse", "--imu", str(imu), "--fixes", str(fixes), "--rest-s", "9"])
    assert r.exit_code == 2 and "--rest-s 9: the first 9 s do not look like rest" in r.output


@pytest.mark.slow  # 7 s: the default run stays under 5 minutes
def test_fuse_3d_through_the_cli(tmp_path):
    """`visvec fuse` on a triangle sweep's 3-D gyro and the camera's rows as fixes (from
    `visvec batch`): attitude rows at the IMU's rate, within 0.05 deg of the truth and
    within 5 sigma on every ok row."""
    from visvec.rotations import quat_to_matrix

    from conftest import ROOT

    rig = ROOT / "configs" / "triangle.toml"
    rec = tmp_path / "rec"
    sim = ["simulate", "--rig", str(rig), "--out", str(rec), "--frames", "40", "--motion",
           "sweep", "--yaw-rate-dps", "20", "--imu"]  # fmt: skip
    r = CliRunner().invoke(cli, sim)
    assert r.exit_code == 0, r.output
    fixes, out = tmp_path / "fixes.csv", tmp_path / "fused.csv"
    r = CliRunner().invoke(cli, ["batch", str(rec), "--rig", str(rig), "--out", str(fixes)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["fuse", "--imu", str(rec / "imu.csv"), "--fixes", str(fixes),
                                 "--out", str(out)])  # fmt: skip
    assert r.exit_code == 0, r.output
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    with open(rec / "imu_truth.csv") as fh:
        truth = [quat_to_matrix(np.array([float(t[k]) for k in ("qw", "qx", "qy", "qz")]))
                 for t in csv.DictReader(fh)]  # fmt: skip
    assert len(rows) == len(truth) and "yaw_deg" in rows[0]
    ok = [x for x in rows if x["status"] == "ok"]
    assert len(ok) > 0.8 * len(rows)
    err = []
    for x in ok:
        q = np.array([float(x[k]) for k in ("qw", "qx", "qy", "qz")])
        e = np.degrees(np.linalg.norm(logmap(truth[int(x["frame"])].T @ quat_to_matrix(q))))
        err.append(e)
        sig = max(float(x[f"sigma_{k}"]) for k in ("yaw_deg", "pitch_deg", "roll_deg"))
        assert e < 5 * np.sqrt(3) * sig + 1e-4, (x["frame"], e, sig)
    assert np.sqrt(np.mean(np.square(err))) < 0.05


def test_the_planar_learned_line_says_when_the_offset_is_not_learned_yet():
    """The closing line of a planar run: the fixes' time offset with its sigma once the
    fixes have told it; while its sigma is still near the prior's (one fix, or fixes
    with no motion between them) it says so instead of printing the prior."""
    from types import SimpleNamespace

    from visvec.cli.fuse import planar_learned_line
    from visvec.fuse.planar import PlanarModel

    prior = PlanarModel().time_offset_sigma
    x = np.zeros(9)
    x[8] = 0.03
    P = np.diag([1.0] * 8 + [(0.9 * prior) ** 2])
    line = planar_learned_line(SimpleNamespace(x=x, P=P), prior)
    assert "time offset not yet" in line and f"prior +- {1000 * prior:.0f} ms" in line
    assert "gyro bias" in line
    P[8, 8] = 0.002**2
    line = planar_learned_line(SimpleNamespace(x=x, P=P), prior)
    assert "time offset +30.0 +- 2.0 ms" in line
