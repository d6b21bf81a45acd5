"""The contract under hostile input (issue 29): no crash, no shifted row, no destroyed
file, no confident wrong answer."""

import csv
import os
import subprocess
import sys

from conftest import ROOT

SAMPLE = ROOT / "data" / "sample_frames"
RIG = ROOT / "configs" / "triangle.toml"


def _run(args, **kw):
    return subprocess.run([sys.executable, "-m", "visvec", *args], capture_output=True, **kw)


def test_file_names_that_are_not_utf8(tmp_path):
    """A recording folder, an image inside it, --overlay, --save-frames and simulate
    --out named with a byte that is not UTF-8: processed like any other, no crash."""
    bad = os.fsencode(tmp_path) + b"/rec\xff"
    os.mkdir(bad)
    names = sorted(p for p in os.listdir(SAMPLE) if p.endswith(".png"))[:3]
    for i, n in enumerate(names):
        data = (SAMPLE / n).read_bytes()
        with open(bad + (b"/frame_%d\xfe.png" % i), "wb") as fh:
            fh.write(data)
    out = tmp_path / "rows.csv"
    ov = os.fsencode(tmp_path) + b"/over\xff"
    r = _run(["batch", bad, "--rig", str(RIG), "--out", str(out), "--overlay", ov])
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out)))
    assert [x["status"] for x in rows] == ["ok"] * 3
    assert len(os.listdir(ov)) == 3
    sim = os.fsencode(tmp_path) + b"/sim\xff"
    r = _run(["simulate", "--rig", str(RIG), "--out", sim, "--frames", "2"])
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(sim)) == [b"frame_0000.png", b"frame_0001.png", b"truth.csv"]
    rec = os.fsencode(tmp_path) + b"/save\xff"
    r = _run(["track", "--rig", str(RIG), "--camera", sim, "--save-frames", rec, "--out",
              str(tmp_path / "t.csv")])  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert b"times.csv" in os.listdir(rec)


def test_a_video_whose_name_is_not_utf8_is_refused_clearly(tmp_path):
    bad = os.fsencode(tmp_path) + b"/clip\xff.avi"
    with open(bad, "wb") as fh:
        fh.write(b"RIFF")
    r = _run(["batch", bad, "--rig", str(RIG)])
    assert r.returncode == 3
    assert b"not UTF-8" in r.stderr and b"Traceback" not in r.stderr
