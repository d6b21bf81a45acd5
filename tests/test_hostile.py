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


def test_numbers_that_are_not_numbers_are_refused(tmp_path):
    """NaN and infinity in options, times and truth files: refused naming the option
    or the line (exit 2), never accepted."""
    for args, what in [
        (["simulate", "--rig", str(RIG), "--out", str(tmp_path / "s"), "--exposure", "nan"],
         b"--exposure"),
        (["simulate", "--rig", str(RIG), "--out", str(tmp_path / "s"), "--max-tilt-deg",
          "inf"], b"--max-tilt-deg"),
        (["simulate", "--rig", str(RIG), "--out", str(tmp_path / "s"), "--target-offset-mm",
          "nan", "0"], b"--target-offset-mm"),
        (["montecarlo", "--rig", str(ROOT / "configs" / "markers.toml"), "--out",
          str(tmp_path / "m"), "--centroid-noise", "nan"], b"--centroid-noise"),
        (["calibrate", "camera", str(SAMPLE), "--pattern", "9x6", "--square-mm", "inf"],
         b"--square-mm"),
        (["calibrate", "camera", str(SAMPLE), "--pattern", "2x2", "--square-mm", "25"],
         b"3x3"),
        (["rate", "--budget", "--ifov-deg", "nan"], b"--ifov-deg"),
        (["fuse", "--imu", "a.csv", "--fixes", "b.csv", "--gyro-noise-dps", "nan"],
         b"--gyro-noise-dps"),
    ]:  # fmt: skip
        r = _run(args)
        assert r.returncode == 2, (args, r.stderr)
        assert what in r.stderr and b"Traceback" not in r.stderr, (args, r.stderr)


def test_bad_times_and_truth_files_name_the_line(tmp_path):
    import shutil

    rec = tmp_path / "rec"
    rec.mkdir()
    names = sorted(p.name for p in SAMPLE.glob("*.png"))[:3]
    for n in names:
        shutil.copy(SAMPLE / n, rec / n)
    for bad, msg in [("nan", b"finite"), ("inf", b"finite"), ("0.0", b"does not increase")]:
        (rec / "times.csv").write_text(f"file,time_s\n{names[0]},0.0\n{names[1]},{bad}\n")
        r = _run(["batch", str(rec), "--rig", str(RIG)])
        assert r.returncode == 2 and b"line 3" in r.stderr and msg in r.stderr, r.stderr
    (rec / "times.csv").unlink()
    truth = tmp_path / "truth.csv"
    truth.write_text("frame,yaw_deg,pitch_deg,roll_deg\n0,1,nan,0\n")
    r = _run(["batch", str(rec), "--rig", str(RIG), "--truth", str(truth)])
    assert r.returncode == 2 and b"line 2" in r.stderr and b"finite" in r.stderr
    truth.write_text("frame,yaw_deg,pitch_deg,roll_deg\n")
    r = _run(["batch", str(rec), "--rig", str(RIG), "--truth", str(truth)])
    assert r.returncode == 2 and b"no rows" in r.stderr
    truth.write_bytes(b"frame,yaw_deg,pitch_deg,roll_deg\n0,\xff\xfe,0,0\n")
    r = _run(["batch", str(rec), "--rig", str(RIG), "--truth", str(truth)])
    assert r.returncode == 2 and b"UTF-8" in r.stderr


def test_jsonl_rows_are_json(tmp_path):
    """A value that is not finite is written as null, never as a bare NaN."""
    import io
    import json

    from visvec.sinks.writers import JsonlSink

    buf = io.StringIO()
    JsonlSink(buf, ["a", "b"]).write({"a": float("nan"), "b": float("inf")})
    assert json.loads(buf.getvalue()) == {"a": None, "b": None}


def test_outputs_never_destroy_inputs_or_each_other(tmp_path):
    """--out over the rig, into the recording, over a calibration's rig file, a URL
    scheme visvec does not speak, or a file another run is writing: refused (exit 2)
    before any work, the input untouched."""
    import shutil
    import time

    rig = tmp_path / "rig.toml"
    shutil.copy(RIG, rig)
    before = rig.read_bytes()
    rec = tmp_path / "rec"
    shutil.copytree(SAMPLE, rec)
    cases = [
        (["batch", str(rec), "--rig", str(rig), "--out", str(rig)], b"input of the run"),
        (["batch", str(rec), "--rig", str(rig), "--out", str(rec / "rows.csv")],
         b"inside the input folder"),
        (["batch", str(rec), "--rig", str(rig), "--overlay", str(rec / "ov")],
         b"inside the input folder"),
        (["batch", str(rec), "--rig", str(rig), "--out", "tcp://127.0.0.1:9"],
         b"udp://HOST:PORT"),
        (["calibrate", "zero-tilt", str(rec), "--rig", str(rig), "--out", str(rig)],
         b"input of the run"),
    ]  # fmt: skip
    for args, msg in cases:
        r = _run(args)
        assert r.returncode == 2 and msg in r.stderr, (args, r.stderr)
    assert rig.read_bytes() == before
    assert sorted(p.name for p in rec.iterdir()) == sorted(p.name for p in SAMPLE.iterdir())
    assert not (tmp_path / "tcp:").exists()
    # a second writer of the same file is refused while the first runs (a recording
    # played at one frame a second)
    slow = tmp_path / "slow"
    shutil.copytree(SAMPLE, slow)
    names = sorted(p.name for p in slow.glob("*.png"))
    (slow / "truth.csv").unlink()
    (slow / "times.csv").write_text(
        "file,time_s\n" + "".join(f"{n},{i}.0\n" for i, n in enumerate(names))
    )
    out = tmp_path / "rows.csv"
    first = subprocess.Popen(
        [sys.executable, "-m", "visvec", "track", "--rig", str(rig), "--camera", str(slow),
         "--realtime", "--out", str(out)], stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (not out.exists() or out.read_text().count("\n") < 2):
            time.sleep(0.05)
        r = _run(["batch", str(rec), "--rig", str(rig), "--out", str(out)])
        assert r.returncode == 2 and b"another run is writing" in r.stderr, r.stderr
        first.terminate()
        first.wait(timeout=30)
    finally:
        first.kill()
    assert first.returncode == 0
    text = out.read_text()
    rows = list(csv.DictReader(text.splitlines()))
    assert text.endswith("\n") and len(rows) >= 1 and all(r["status"] == "ok" for r in rows)
