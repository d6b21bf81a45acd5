"""The contract under hostile input (issue 29): no crash, no shifted row, no destroyed
file, no confident wrong answer."""

import csv
import os
import subprocess
import sys

import pytest

from conftest import ROOT, data_rows, wait_until

SAMPLE = ROOT / "data" / "sample_frames"
RIG = ROOT / "configs" / "triangle.toml"


def _slow_recording(tmp_path, step_s: float):
    """The sample frames as a recording taken every ``step_s`` seconds (to be played
    with --realtime)."""
    import shutil

    slow = tmp_path / "slow"
    shutil.copytree(SAMPLE, slow)
    names = sorted(p.name for p in slow.glob("*.png"))
    (slow / "truth.csv").unlink()
    (slow / "times.csv").write_text(
        "file,time_s\n" + "".join(f"{n},{i * step_s:.3f}\n" for i, n in enumerate(names))
    )
    return slow


def _run(args, **kw):
    return subprocess.run([sys.executable, "-m", "visvec", *args], capture_output=True, **kw)


@pytest.mark.slow  # 6 s: the default run stays under 5 minutes
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


@pytest.mark.slow
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
        (["calibrate", "camera", str(SAMPLE), "--pattern", "9y6", "--square-mm", "25"],
         b"--pattern '9y6': expected inner corners as COLSxROWS"),
        (["rate", "--budget", "--ifov-deg", "nan"], b"--ifov-deg"),
        (["track", "--rig", str(RIG), "--camera", str(SAMPLE), "--serve", "70000"],
         b"--serve '70000': the port must be 0-65535"),
        (["fuse", "--imu", "a.csv", "--fixes", "b.csv", "--gyro-noise-dps", "nan"],
         b"--gyro-noise-dps"),
    ]:  # fmt: skip
        r = _run(args)
        assert r.returncode == 2, (args, r.stderr)
        assert what in r.stderr and b"Traceback" not in r.stderr, (args, r.stderr)


@pytest.mark.slow  # 10 s on a slow host
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


@pytest.mark.slow  # 7-8 s: the default run stays under 5 minutes
def test_outputs_never_destroy_inputs_or_each_other(tmp_path):
    """--out over the rig, into the recording, over a calibration's rig file, a URL
    scheme visvec does not speak, or a file another run is writing: refused (exit 2)
    before any work, the input untouched."""
    import shutil

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
    slow = _slow_recording(tmp_path, 1.0)
    out = tmp_path / "rows.csv"
    first = subprocess.Popen(
        [sys.executable, "-m", "visvec", "track", "--rig", str(rig), "--camera", str(slow),
         "--realtime", "--out", str(out)], stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        wait_until(lambda: data_rows(out) >= 1, "the first run's first row")
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


def _rig_with(tmp_path, old: str, new: str, name="rig.toml"):
    text = RIG.read_text()
    assert old in text
    p = tmp_path / name
    p.write_text(text.replace(old, new))
    return p


@pytest.mark.slow
def test_a_rig_that_cannot_work_is_refused_naming_the_key(tmp_path):
    """An equilateral triangle (three attitudes 120 deg apart fit it), absurd camera
    values, a file that is not text or is nested without end, /dev/zero: refused by
    `check` before any work, naming the file and the key; no traceback, no unbounded
    read."""
    verts = (
        "vertices_mm = [[372.5, 0.0, 2150.0], [-186.3, 190.5, 2150.0], [-186.3, -190.5, 2150.0]]"
    )
    eq = "vertices_mm = [[300.0, 0.0, 2150.0], [-150.0, 259.8, 2150.0], [-150.0, -259.8, 2150.0]]"
    cases = [
        (_rig_with(tmp_path, verts, eq, "eq.toml"), b"vertices_mm: the angles are"),
        (_rig_with(tmp_path, "width = 640", "width = 100000000", "w.toml"), b"width"),
        (_rig_with(tmp_path, "cx = ", "cx = 1e6 #", "cx.toml"), b"cx"),
    ]
    text = RIG.read_text()
    if "dist = " in text:
        import re

        bad = re.sub(r"dist = \[[^\]]*\]", "dist = [1e6, 0.0, 0.0, 0.0, 0.0]", text)
    else:
        bad = text.replace("[camera]\n", "[camera]\ndist = [1e6, 0.0, 0.0, 0.0, 0.0]\n", 1)
    (tmp_path / "dist.toml").write_text(bad)
    cases.append((tmp_path / "dist.toml", b"dist"))
    (tmp_path / "bytes.toml").write_bytes(RIG.read_bytes() + b"\n# \xff\xfe\n")
    cases.append((tmp_path / "bytes.toml", b"not a UTF-8 text file"))
    (tmp_path / "deep.toml").write_text("x = " + "[" * 100000 + "]" * 100000 + "\n")
    cases.append((tmp_path / "deep.toml", b"nested too deeply"))
    cases.append(("/dev/zero", b"not a rig file"))
    for rig, msg in cases:
        r = _run(["check", "--rig", str(rig), "--frames", "1"], timeout=60)
        assert r.returncode == 2, (rig, r.stderr)
        assert msg in r.stderr and b"Traceback" not in r.stderr, (rig, r.stderr)
        assert str(rig).encode() in r.stderr


def test_a_lamp_map_that_is_no_map_is_not_echoed(tmp_path):
    lamps = ROOT / "configs" / "lamps.toml"
    secret = tmp_path / "secret.txt"
    secret.write_text("password=hunter2\nmore\n")
    text = lamps.read_text()
    import re

    rig = tmp_path / "lamps.toml"
    rig.write_text(re.sub(r'map = "[^"]*"', f'map = "{secret}"', text))
    r = _run(["check", "--rig", str(rig)])
    assert r.returncode == 2 and b"not a lamp map" in r.stderr
    assert b"hunter2" not in r.stderr
    rig.write_text(re.sub(r'map = "[^"]*"', 'map = "/dev/zero"', text))
    r = _run(["check", "--rig", str(rig)], timeout=60)
    assert r.returncode == 2 and b"not a file" in r.stderr


def _sample_video(path, damage=None, cut=None):
    """The 12 sample frames as an MJPG AVI at 10 fps; ``damage``: a frame whose JPEG
    data is zeroed; ``cut``: keep this share of the file."""
    import cv2

    from visvec.imageio import read_image

    names = sorted(p for p in SAMPLE.glob("*.png"))
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    for n in names:
        w.write(cv2.cvtColor(read_image(n, cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))
    w.release()
    data = bytearray(path.read_bytes())
    if damage is not None:
        soi = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]
        data[soi[damage] : soi[damage] + 400] = bytes(400)
    if cut is not None:
        data = data[: int(len(data) * cut)]
    path.write_bytes(bytes(data))
    return len(names)


def test_a_damaged_video_keeps_every_row_in_its_place(tmp_path):
    """A frame that cannot be decoded is a read_error row under its own index and time;
    the frames after it keep theirs (their values match their own truth)."""
    vid = tmp_path / "damaged.avi"
    n = _sample_video(vid, damage=5)
    out = tmp_path / "rows.csv"
    r = _run(["batch", str(vid), "--rig", str(RIG), "--out", str(out)])
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out)))
    truth = {int(t["frame"]): t for t in csv.DictReader(open(SAMPLE / "truth.csv"))}
    assert [int(x["frame"]) for x in rows] == list(range(n))
    assert rows[5]["status"] == "read_error" and b"frame 5" in r.stderr
    for x in rows:
        k = int(x["frame"])
        assert abs(float(x["time_s"]) - k / 10.0) < 1e-6
        if k != 5:
            assert x["status"] == "ok"
            d = (float(x["yaw_deg"]) - float(truth[k]["yaw_deg"]) + 180) % 360 - 180
            assert abs(d) < 0.5, (k, d)
    assert b"mjpeg @" not in r.stderr  # FFmpeg's message names no frame: ours does


def test_a_video_cut_short_says_so_and_an_empty_one_is_refused(tmp_path):
    vid = tmp_path / "cut.avi"
    n = _sample_video(vid, cut=0.5)
    r = _run(["batch", str(vid), "--rig", str(RIG), "--out", str(tmp_path / "rows.csv")])
    rows = list(csv.DictReader(open(tmp_path / "rows.csv")))
    # the frames the container lists but the file no longer holds are read_error rows,
    # each named; none of the frames the cut touched is an ok row
    assert r.returncode == 0, r.stderr
    assert [int(x["frame"]) for x in rows] == list(range(n))
    assert rows[-1]["status"] == "read_error" and f"frame {n - 1}".encode() in r.stderr
    first_bad = next(i for i, x in enumerate(rows) if x["status"] != "ok")
    assert 0 < first_bad < n and all(x["status"] != "ok" for x in rows[first_bad:])
    import cv2

    empty = tmp_path / "empty.avi"
    w = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    w.release()
    r = _run(["batch", str(empty), "--rig", str(RIG)])
    assert r.returncode == 3 and b"Traceback" not in r.stderr, r.stderr


def test_a_fifo_given_as_a_video_is_refused_at_once(tmp_path):
    fifo = tmp_path / "pipe.avi"
    os.mkfifo(fifo)
    r = _run(["batch", str(fifo), "--rig", str(RIG)], timeout=30)
    assert r.returncode == 3 and b"not a regular file" in r.stderr


@pytest.mark.slow
def test_a_calibration_that_should_be_refused(tmp_path):
    """Zero-tilt frames that are not level are refused, nothing written; a
    calibration made with one camera is refused on another (size or intrinsics),
    naming both."""
    tilted = tmp_path / "tilted"
    r = _run(["simulate", "--rig", str(RIG), "--out", str(tilted), "--frames", "12",
              "--max-tilt-deg", "5"])  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = tmp_path / "zero.toml"
    r = _run(["calibrate", "zero-tilt", str(tilted), "--rig", str(RIG), "--out", str(out)])
    assert r.returncode == 1 and b"do not fit a level platform" in r.stderr, r.stderr
    assert not out.exists()
    level = tmp_path / "level"
    r = _run(["simulate", "--rig", str(RIG), "--out", str(level), "--frames", "12",
              "--motion", "level"])  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = _run(["calibrate", "zero-tilt", str(level), "--rig", str(RIG), "--out", str(out)])
    assert r.returncode == 0, r.stderr
    assert "[made_for]" in out.read_text()
    r = _run(["check", "--rig", str(RIG), "--calibration", str(out), "--frames", "1"])
    assert r.returncode == 0, r.stderr
    other = _rig_with(tmp_path, "fx = 600.0", "fx = 640.0", "other.toml")
    r = _run(["check", "--rig", str(other), "--calibration", str(out), "--frames", "1"])
    assert r.returncode == 2 and b"fx = 600" in r.stderr and b"calibrate again" in r.stderr
    big = _rig_with(tmp_path, "width = 640", "width = 800", "big.toml")
    r = _run(["check", "--rig", str(big), "--calibration", str(out), "--frames", "1"])
    assert r.returncode == 2 and b"640x480" in r.stderr, r.stderr


def test_a_full_disk_leaves_whole_rows_and_names_the_file(tmp_path):
    """Writes that fail part-way (a file size limit standing in for a full disk): the
    file is cut back to its last whole row and the error names it (exit 1)."""
    import resource
    import signal

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1500, 1500))

    out = tmp_path / "rows.csv"
    r = subprocess.run(
        [sys.executable, "-m", "visvec", "batch", str(SAMPLE), "--rig", str(RIG), "--out",
         str(out)], capture_output=True, preexec_fn=limit,
    )  # fmt: skip
    assert r.returncode == 1, r.stderr
    assert str(out).encode() in r.stderr and b"complete rows" in r.stderr
    assert b"unexpected" not in r.stderr
    text = out.read_text()
    assert text.endswith("\n") and 0 < len(text) <= 1500
    lines = text.splitlines()
    assert len({line.count(",") for line in lines}) == 1  # no cut row
    r = _run(["batch", str(SAMPLE), "--rig", str(RIG), "--out", "/dev/full"])
    assert r.returncode == 1 and b"/dev/full" in r.stderr and b"unexpected" not in r.stderr


def test_ctrl_c_on_simulate_says_the_folder_is_incomplete(tmp_path):
    import signal

    out = tmp_path / "sim"
    p = subprocess.Popen(
        [sys.executable, "-m", "visvec", "simulate", "--rig", str(RIG), "--out", str(out),
         "--frames", "2000"], stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        wait_until(lambda: len(list(out.glob("*.png"))) >= 2, "two frames written", timeout=60)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        p.kill()
    assert p.returncode == 130 and b"incomplete" in err, err
    # what it says to do works: the folder deleted, the same command makes it whole
    assert f"delete {out} and run the same command again".encode() in err, err
    import shutil

    shutil.rmtree(out)
    r = _run(["simulate", "--rig", str(RIG), "--out", str(out), "--frames", "3"])
    assert r.returncode == 0 and len(list(out.glob("frame_*.png"))) == 3, r.stderr


def test_small_ones(tmp_path):
    """simulate into a folder with an older simulation, a truncated JPEG, fixes on
    another clock than the IMU's: each refused or named, never silent."""
    import shutil

    sim = tmp_path / "sim"
    assert _run(["simulate", "--rig", str(RIG), "--out", str(sim), "--frames", "2"]).returncode == 0
    r = _run(["simulate", "--rig", str(RIG), "--out", str(sim), "--frames", "1"])
    assert r.returncode == 2 and b"already holds a recording" in r.stderr
    rec = tmp_path / "jpg"
    rec.mkdir()
    import cv2

    from visvec.imageio import read_image

    img = read_image(SAMPLE / "frame_0000.png")
    ok, buf = cv2.imencode(".jpg", img)
    (rec / "a.jpg").write_bytes(buf.tobytes())
    (rec / "b.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    out = tmp_path / "rows.csv"
    r = _run(["batch", str(rec), "--rig", str(RIG), "--out", str(out)])
    rows = list(csv.DictReader(open(out)))
    assert [x["status"] for x in rows] == ["ok", "read_error"]
    assert b"b.jpg: a JPEG cut short" in r.stderr and b"Premature" not in r.stderr
    imu = tmp_path / "imu.csv"
    imu.write_text("time_s,gx_dps,gy_dps,gz_dps\n" + "".join(
        f"{1.7e9 + k * 0.01:.2f},0,0,0\n" for k in range(50)))  # fmt: skip
    fixes = tmp_path / "fixes.csv"
    shutil.copy(SAMPLE / "truth.csv", tmp_path / "t.csv")
    fixes.write_text(
        "frame,time_s,status,yaw_deg,pitch_deg,roll_deg,qw,qx,qy,qz,sigma_yaw_deg,"
        "sigma_pitch_deg,sigma_roll_deg,rms_px,n_points,latency_ms,warnings\n"
        "0,0.1,ok,0,0,0,1,0,0,0,0.1,0.1,0.1,,,0,\n"
    )
    r = _run(["fuse", "--imu", str(imu), "--fixes", str(fixes)])
    assert r.returncode == 2 and b"one clock" in r.stderr, r.stderr


def test_calibrate_system_counts_a_duplicated_frame_once(tmp_path):
    import shutil

    rec = tmp_path / "m"
    markers = ROOT / "configs" / "markers.toml"
    r = _run(["simulate", "--rig", str(markers), "--out", str(rec), "--frames", "6"])
    assert r.returncode == 0, r.stderr
    shutil.copy(rec / "frame_0002.png", rec / "frame_0006.png")
    r = _run(["calibrate", "system", str(rec), "--rig", str(markers), "--out",
              str(tmp_path / "cal.toml"), "--max-iterations", "2"], timeout=120)  # fmt: skip
    assert b"frame 6: skipped (the same image as frame 2)" in r.stderr, r.stderr


@pytest.mark.slow  # 6 s: the default run stays under 5 minutes
def test_track_ends_on_every_signal_with_its_rows_counted(tmp_path):
    """SIGINT, SIGTERM, SIGHUP mid-run: exit 0, 'interrupted after N frames', and the
    output holds exactly N whole rows."""
    import re
    import signal

    slow = _slow_recording(tmp_path, 0.3)
    for sig in ("SIGINT", "SIGTERM", "SIGHUP"):
        out = tmp_path / f"{sig}.csv"
        p = subprocess.Popen(
            [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera", str(slow),
             "--realtime", "--out", str(out)], stderr=subprocess.PIPE,
        )  # fmt: skip
        try:
            wait_until(lambda out=out: data_rows(out) >= 2, "two rows written")
            p.send_signal(getattr(signal, sig))
            _, err = p.communicate(timeout=30)
        finally:
            p.kill()
        assert p.returncode == 0, (sig, err)
        m = re.search(rb"interrupted after (\d+) frames; all rows written", err)
        assert m, (sig, err)
        text = out.read_text()
        rows = list(csv.DictReader(text.splitlines()))
        assert text.endswith("\n") and len(rows) == int(m.group(1)) and 2 <= len(rows) < 12


def test_an_output_folder_that_cannot_be_made_is_refused(tmp_path):
    blocker = tmp_path / "taken"
    blocker.write_text("a file, not a folder")
    for opt in ("--overlay", "--save-frames"):
        r = _run(["track", "--rig", str(RIG), "--camera", str(SAMPLE), opt, str(blocker),
                  "--out", str(tmp_path / "rows.csv")])  # fmt: skip
        assert r.returncode == 2 and opt.encode() in r.stderr and b"unexpected" not in r.stderr


def test_one_run_s_outputs_never_share_a_path(tmp_path):
    """Two outputs of one run at one path (--out and --errors, --out and --summary,
    track --imu's --out and --camera-out, an output inside a folder output): refused
    (exit 2) before any work, naming both options; nothing written."""
    from conftest import run

    out = tmp_path / "x.csv"
    batch = ["batch", SAMPLE, "--rig", RIG, "--truth", SAMPLE / "truth.csv"]
    cases = [
        ([*batch, "--out", out, "--errors", out], "--errors", "--out"),
        ([*batch, "--out", out, "--summary", out], "--summary", "--out"),
        ([*batch, "--overlay", tmp_path / "o", "--out", tmp_path / "o" / "r.csv"], "--overlay",
         "--out"),
        (["track", "--rig", RIG, "--camera", SAMPLE, "--imu", "udp://127.0.0.1:9", "--out", out,
          "--camera-out", out], "--camera-out", "--out"),
        (["fuse", "--imu", out, "--fixes", out, "--out", tmp_path / "f.csv", "--errors",
          tmp_path / "f.csv", "--truth", out], "--out", "--errors"),
    ]  # fmt: skip
    out.write_text("time_s,status\n")
    for args, option, other in cases:
        r = run(*args)
        assert r.exit_code == 2, (args, r.output)
        assert f"Invalid value for {option}" in r.output and f"also where {other} goes" in r.output
    assert out.read_text() == "time_s,status\n"
    assert not (tmp_path / "o").exists() and not (tmp_path / "f.csv").exists()


def test_calibrating_from_frames_that_cannot_be_read_is_an_unreadable_source(tmp_path):
    """calibrate zero-tilt on a folder of files that are no images: exit 3 (an
    unreadable source, as the reference says), naming the folder, nothing written; a
    folder where some frames are read and none is level is a failed calibration (not
    3)."""
    from conftest import run

    bad = tmp_path / "bad"
    bad.mkdir()
    for i in range(3):
        (bad / f"f{i}.png").write_text("not an image")
    out = tmp_path / "zero.toml"
    r = run("calibrate", "zero-tilt", bad, "--rig", RIG, "--out", out)
    assert r.exit_code == 3 and f"{bad}: none of the 3 frames could be read" in r.output
    assert not out.exists()
    r = run("calibrate", "zero-tilt", SAMPLE, "--rig", RIG, "--out", out)
    assert r.exit_code != 3


def test_fps_is_the_frame_interval_the_run_expects(tmp_path):
    """`rate FOLDER --fps 10` on frames without their times, with a rig that names no fps
    (30 by default): the star field expects 0.1 s between frames (was 1/30 s: every frame
    a frame_jump, exit 4) and the rates are right; --fps must be a finite rate in
    (0, 10000] (1e308 gave every time_s 0.0); a folder's own times (its truth.csv) are
    used before --fps, and the run says so."""
    import shutil

    from conftest import run

    star = ROOT / "configs" / "starfield.toml"
    text = star.read_text()
    assert "fps = 10.0" in text and "exposure_ms = 50.0" in text
    rig = tmp_path / "nofps.toml"
    rig.write_text(
        text.replace("fps = 10.0\n", "").replace("exposure_ms = 50.0", "exposure_ms = 20.0")
    )
    sim = tmp_path / "sim"
    assert run("simulate", "--rig", star, "--out", sim, "--frames", "6", "--case", "1",
               "--fps", "10").exit_code == 0  # fmt: skip
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in sim.glob("frame_*.png"):
        shutil.copy(f, bare)
    out = tmp_path / "rates.csv"
    r = run("rate", bare, "--rig", rig, "--fps", "10", "--truth", sim / "truth.csv", "--out", out)
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(out.open()))
    assert [x["status"] for x in rows[1:]] == ["ok"] * 5
    assert abs(float(rows[-1]["time_s"]) - 0.5) < 1e-9
    assert abs(float(rows[-1]["wx_dps"]) - 1.0) < 0.02  # case 1: 1 deg/s about x
    for bad in ("1e308", "0", "-5", "nan", "inf"):
        r = run("rate", bare, "--rig", rig, "--fps", bad)
        assert r.exit_code == 2 and "--fps" in r.output, (bad, r.output)
    r = run("batch", sim, "--rig", rig, "--fps", "1", "--out", tmp_path / "b.csv")
    assert "has its own frame times (truth.csv): they are used, not --fps 1" in r.output


def _damaged(path, fourcc: str, how: str) -> int:
    """The 12 sample frames written with ``fourcc`` (10 fps) to ``path`` (its suffix the
    container), then damaged: "zeroed" (5,000 bytes in the middle zeroed), "truncated"
    (the last 30 % cut), "no index" (an AVI's idx1 made unreadable), or "no index,
    zeroed" (both)."""
    import cv2

    from visvec.imageio import read_image

    names = sorted(SAMPLE.glob("*.png"))
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (640, 480))
    for n in names:
        w.write(cv2.cvtColor(read_image(n, cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))
    w.release()
    data = bytearray(path.read_bytes())
    if "no index" in how:
        # the container's index: an AVI's idx1, an MP4's moov (its sample table), an
        # MKV's Cues element (ID 1C 53 BB 6B)
        tag = {".avi": b"idx1", ".mp4": b"moov", ".mkv": b"\x1c\x53\xbb\x6b"}[path.suffix]
        k = data.rfind(tag)
        assert k > 0
        data[k : k + 4] = b"xxxx"
    if "zeroed" in how:
        mid = len(data) // 2
        data[mid : mid + 5000] = bytes(5000)
    if how == "truncated":
        data = data[: int(len(data) * 0.7)]
    path.write_bytes(bytes(data))
    return len(names)


def _rows_in_place(tmp_path, video) -> tuple[list[dict], str]:
    """The rows of a damaged video; every ok row's yaw that of its own frame's truth."""
    from conftest import run

    out = tmp_path / f"{video.name}.csv"
    r = run("batch", video, "--rig", RIG, "--out", out)
    rows = list(csv.DictReader(open(out))) if out.exists() else []
    truth = {int(t["frame"]): t for t in csv.DictReader(open(SAMPLE / "truth.csv"))}
    for x in rows:
        k = int(x["frame"])
        assert abs(float(x["time_s"]) - k / 10.0) < 1e-6, x
        if x["status"] == "ok":
            d = (float(x["yaw_deg"]) - float(truth[k]["yaw_deg"]) + 180) % 360 - 180
            assert abs(d) < 0.5, (video.name, k, d)  # an ok row is its own frame's
    assert [int(x["frame"]) for x in rows] == list(range(len(rows)))
    return rows, r.output


def test_a_damaged_motion_jpeg_avi_keeps_its_rows_in_place(tmp_path):
    """Issue 59's case: 5,000 bytes zeroed in the middle of an MJPG AVI lost a chunk, and
    every later row carried the frame before's index and time (rows 6-10 held frames
    7-11's attitudes, ok). Read by its index, the frame that cannot be decoded is its
    own read_error row and every other row is its own frame's."""
    video = tmp_path / "zeroed.avi"
    n = _damaged(video, "MJPG", "zeroed")
    rows, _ = _rows_in_place(tmp_path, video)
    assert len(rows) == n
    assert sum(x["status"] == "read_error" for x in rows) >= 1
    assert sum(x["status"] == "ok" for x in rows) >= n - 2


@pytest.mark.slow  # 6 s in all: the default run keeps the AVI case above
@pytest.mark.parametrize(
    "fourcc, suffix, how",
    [("MJPG", "avi", "truncated"), ("MJPG", "avi", "no index"),
     ("MJPG", "avi", "no index, zeroed"), ("mp4v", "mp4", "zeroed"),
     ("mp4v", "mp4", "truncated"), ("mp4v", "mp4", "no index"), ("MJPG", "mkv", "zeroed"),
     ("MJPG", "mkv", "truncated"), ("MJPG", "mkv", "no index")],
)  # fmt: skip
def test_damaged_containers_never_put_a_row_on_another_frame(tmp_path, fourcc, suffix, how):
    """Damaged MJPG AVI, mp4v MP4 and MKV files (truncated, a zeroed span, the index
    gone): whatever can be read is read (an MP4 without its sample table cannot be: a
    source that cannot be opened), and no ok row claims another frame's index or time;
    an AVI without its index whose data break off ends there, said."""
    video = tmp_path / f"v.{suffix}"
    _damaged(video, fourcc, how)
    rows, out = _rows_in_place(tmp_path, video)
    if how == "no index" and suffix == "avi":
        assert len(rows) == 12 and all(x["status"] == "ok" for x in rows)
    if how == "no index" and suffix == "mp4":
        assert rows == [] and "cannot open the video" in out
    if how == "no index, zeroed":
        assert "cannot be placed" in out
