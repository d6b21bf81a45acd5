"""`visvec batch` (visvec.cli.batch): rows from recordings, their truth, the notes it gives
on the rig and the camera."""

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.data import Frame
from visvec.rig import load_rig

from conftest import (
    CONFIGS,
    SAMPLES,
    assert_within_3_sigma,
    besides_the_zero_tilt_note,
    rig_variant,
    rows_of,
    run,
)

RIG = str(CONFIGS / "triangle.toml")


def test_batch_on_sample_frames_with_truth(tmp_path):
    out = tmp_path / "rows.csv"
    r = run("batch", SAMPLES, "--rig", RIG, "--out", out, "--truth", SAMPLES / "truth.csv")
    assert r.exit_code == 0, r.output
    rows = rows_of(out.read_text())
    assert len(rows) == len(list(SAMPLES.glob("*.png")))
    assert list(rows[0]) == [
        "frame",
        "time_s",
        "status",
        "yaw_deg",
        "pitch_deg",
        "roll_deg",
        "qw",
        "qx",
        "qy",
        "qz",
        "sigma_yaw_deg",
        "sigma_pitch_deg",
        "sigma_roll_deg",
        "rms_px",
        "n_points",
        "latency_ms",
        "warnings",
        "time_unix",  # absolute time, empty for a recording without one (issue 34)
    ]
    assert all(row["status"] == "ok" for row in rows)
    assert all(row["warnings"] == "" for row in rows)  # clean frames: nothing to warn of
    truth = {int(t["frame"]): t for t in csv.DictReader(open(SAMPLES / "truth.csv"))}
    err = []
    for row in rows:
        t = truth[int(row["frame"])]
        d = np.array([float(row[k]) - float(t[k]) for k in ("yaw_deg", "pitch_deg", "roll_deg")])
        d[0] = (d[0] + 180) % 360 - 180
        err.append(d)
        # each axis within 4 of its own sigma (12 rows: a Gaussian's 4 sigma, never hit)
        sig = np.array([float(row[f"sigma_{k}"]) for k in ("yaw_deg", "pitch_deg", "roll_deg")])
        assert np.all(np.abs(d) < 4 * sig), (row["frame"], d, sig)
        assert float(row["time_s"]) == pytest.approx(float(t["time_s"]))
    # and the RMS within the 640x480 targets (yaw 0.02 deg, tilts 0.01 deg: RESULTS.md)
    rms = np.sqrt(np.mean(np.square(err), axis=0))
    assert rms[0] <= 0.02 and rms[1] <= 0.01 and rms[2] <= 0.01, rms
    assert "yaw: rms" in r.output and "frames 12, ok 12" in r.output


def test_batch_says_once_when_a_triangle_rig_has_no_zero_tilt_calibration(tmp_path):
    """As `track` does: without a zero-tilt calibration the tilts carry the rig file's
    mounting error, which no sigma covers; said once on stderr, before the rows; not said
    with one, nor for a video that cannot be opened (that error comes first)."""
    r = run("batch", SAMPLES, "--rig", RIG, "--max-frames", 2)
    assert r.exit_code == 0, r.output
    assert r.stderr.count("no zero-tilt calibration given") == 1
    assert r.stdout.startswith("frame,time_s,status")  # the rows stay clean
    cal = tmp_path / "zero.toml"
    cal.write_text("[zero_tilt]\ncentroid_px = [319.5, 239.5]\n")
    r = run("batch", SAMPLES, "--rig", RIG, "--calibration", cal, "--max-frames", 2)
    assert r.exit_code == 0 and "zero-tilt" not in r.stderr, r.stderr
    r = run("batch", tmp_path / "missing.avi", "--rig", RIG)
    assert r.exit_code == 3 and "zero-tilt" not in r.stderr, r.stderr


def test_jsonl_format_has_the_csv_keys(tmp_path):
    r = run("batch", SAMPLES, "--rig", RIG, "--format", "jsonl", "--max-frames", "2")
    assert r.exit_code == 0
    # the rows on stdout (notes go to stderr)
    lines = [json.loads(x) for x in r.stdout.strip().splitlines()]
    assert len(lines) == 2 and lines[0]["status"] == "ok" and "sigma_roll_deg" in lines[0]


def test_bad_frames_are_read_error_rows_and_the_run_goes_on(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    names = sorted(p.name for p in SAMPLES.glob("*.png"))[:3]
    for n in names:
        shutil.copy(SAMPLES / n, folder / n)
    (folder / names[1]).write_bytes(b"not a png")  # unreadable
    (folder / "frame_9.png").write_bytes(b"")  # empty
    cv2.imwrite(str(folder / "frame_99.png"), np.zeros((100, 100), np.uint8))  # wrong size
    r = run("batch", folder, "--rig", RIG)
    assert r.exit_code == 0
    rows = rows_of(r.stdout)
    assert [x["status"] for x in rows] == ["ok", "read_error", "ok", "read_error", "read_error"]
    assert rows[1]["yaw_deg"] == ""
    assert "cannot decode" in r.stderr and "expected 640x480" in r.stderr
    # the run ends saying how many were refused, why, and what to check
    assert "visvec: 3 of 5 frames not ok (read_error 3); read_error: frames unreadable" in r.stderr


def test_the_run_names_its_refusals_only_when_they_are_many():
    """The closing note on refused frames: by reason, most frequent first, with the
    hints of the codes named; none when under 10 % of the frames (or under 3) are."""
    from visvec.pipeline import TrianglePipeline

    rig = load_rig(RIG)
    good = cv2.imread(str(sorted(SAMPLES.glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    black = np.zeros_like(good)
    pipe = TrianglePipeline(rig)
    for i in range(20):
        pipe.process(Frame(i, i / 30.0, good if i != 5 else None))
    assert pipe.refused == {"read_error": 1} and pipe.notes() == []
    # the lights go out: the triangle tracked vanishes (obstructed), then is not found
    for i in range(20, 26):
        pipe.process(Frame(i, i / 30.0, black))
    [note] = pipe.notes()
    assert note.startswith("visvec: 7 of 26 frames not ok (low_brightness;no_triangle 5, ")
    assert "read_error 1, low_brightness;obstructed 1); low_brightness: frames darker" in note
    assert "no_triangle: no bright region" in note and "read_error: frames unreadable" in note


def test_natural_sort_and_sidecar_times(tmp_path):
    names = sorted(p.name for p in SAMPLES.glob("*.png"))[:3]
    for i, n in zip((10, 2, 1), names, strict=True):
        shutil.copy(SAMPLES / n, tmp_path / f"img{i}.png")
    (tmp_path / "times.csv").write_text("file,time_s\nimg1.png,5.0\nimg2.png,5.5\nimg10.png,7.25\n")
    rows = rows_of(run("batch", tmp_path, "--rig", RIG).stdout)
    assert [float(x["time_s"]) for x in rows] == [5.0, 5.5, 7.25]


def test_overlay_and_paper_method(tmp_path):
    ov = tmp_path / "ov"
    r = run(
        "batch", SAMPLES, "--rig", RIG, "--method", "paper", "--overlay", ov, "--max-frames", "2"
    )
    assert r.exit_code == 0
    assert len(list(ov.glob("*.png"))) == 2
    assert all(x["status"] == "ok" for x in rows_of(r.stdout))


def test_truth_file_with_bad_row(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("frame,yaw_deg,pitch_deg,roll_deg\n0,1,2,3\n1,x,2,3\n")
    r = run("batch", SAMPLES, "--rig", RIG, "--truth", t)
    assert r.exit_code == 2 and "line 3" in r.output


def test_batch_says_when_the_target_is_not_where_the_rig_file_puts_it(tmp_path):
    """A ceiling 6 mm higher than the rig file says: every row is still ok (the height is
    estimated), and the run ends with a note of the height over the frames."""
    frames = tmp_path / "frames"
    sim = ["simulate", "--rig", RIG, "--frames", 14, "--seed", 3, "--motion", "sweep"]
    assert run(*sim, "--out", frames, "--target-height-mm", 6).exit_code == 0
    r = run("batch", frames, "--rig", RIG, "--out", tmp_path / "rows.csv")
    assert r.exit_code == 0, r.output
    assert all(row["status"] == "ok" for row in rows_of((tmp_path / "rows.csv").read_text()))
    note = [line for line in r.output.splitlines() if "mm higher than the rig file" in line]
    assert len(note) == 1, r.output
    height = float(note[0].split("looks ")[1].split(" +-")[0])
    assert abs(height - 6.0) < 0.5, note
    # the rig's own lab: no note
    assert run(*sim, "--out", tmp_path / "exact").exit_code == 0
    r = run("batch", tmp_path / "exact", "--rig", RIG, "--out", tmp_path / "rows2.csv")
    assert r.exit_code == 0 and "than the rig file" not in r.output


@pytest.mark.slow  # 7 s on a slow host
def test_batch_says_when_the_camera_aspect_is_off(tmp_path):
    """A rig file whose fy is 0.5 % too large for its camera (603 for 600): no attitude
    fits the triangle as seen, every frame is refused, and the run ends saying so and,
    from the triangle's shape over a 40 deg turn, that the aspect fy / fx is about 1,
    not the rig file's 1.005. The rig's own camera: every frame ok, nothing to say."""
    sim = ["simulate", "--rig", RIG, "--frames", 60, "--seed", 3, "--motion", "sweep"]
    assert run(*sim, "--yaw-rate-dps", 20, "--out", tmp_path / "frames").exit_code == 0
    rig = rig_variant(RIG, "fy", "600.0", "603.0", tmp_path / "rig.toml")
    r = run("batch", tmp_path / "frames", "--rig", rig, "--out", tmp_path / "rows.csv")
    # not one ok row: exit 4, so that a script can tell (issue 34)
    assert r.exit_code == 4 and "none of the 60 frames gave an ok row" in r.stderr
    rows = rows_of((tmp_path / "rows.csv").read_text())
    assert {x["status"] for x in rows} == {"rejected"}
    assert "visvec: 60 of 60 frames not ok (inconsistent_geometry 60); " in r.stderr
    note = [line for line in r.stderr.splitlines() if "aspect fy / fx is" in line]
    assert len(note) == 1 and "calibrate camera" in note[0], r.stderr
    est, sigma = note[0].split("aspect fy / fx is ")[1].split(",")[0].split(" +- ")
    assert float(sigma) < 0.001 and abs(float(est) - 1.0) < 3 * float(sigma), note
    assert "not the rig file's 1.0050" in note[0]
    r = run("batch", tmp_path / "frames", "--rig", RIG, "--out", tmp_path / "exact.csv")
    assert r.exit_code == 0 and besides_the_zero_tilt_note(r.stderr) == ""
    assert {x["status"] for x in rows_of((tmp_path / "exact.csv").read_text())} == {"ok"}


@pytest.mark.slow  # 8 s on a slow host
def test_batch_says_when_the_camera_principal_point_is_off(tmp_path):
    """A rig file whose cx is 10 px right of the camera's: two frames in three refused,
    and over a swing out and back (where the principal point's keystone is told from a
    shear) the run ends naming the principal point that fits, within 3 sigma of the
    camera's."""
    sim = ["simulate", "--rig", RIG, "--frames", 60, "--seed", 1, "--motion", "swing"]
    assert run(*sim, "--yaw-rate-dps", 10, "--out", tmp_path / "frames").exit_code == 0
    rig = rig_variant(RIG, "cx", "319.5", "329.5", tmp_path / "rig.toml")
    r = run("batch", tmp_path / "frames", "--rig", rig, "--out", tmp_path / "rows.csv")
    assert r.exit_code == 0 and "frames not ok (inconsistent_geometry" in r.stderr
    note = [line for line in r.stderr.splitlines() if "principal point is about" in line]
    assert len(note) == 1 and "calibrate camera" in note[0], r.stderr
    cx, sigma = note[0].split("principal point is about cx ")[1].split(",")[0].split(" +- ")
    assert abs(float(cx) - 319.5) < 3.0 * float(sigma) and float(sigma) < 3.0, note
    assert "rolling shutter" not in r.stderr


@pytest.mark.slow
def test_batch_says_when_the_frames_show_a_rolling_shutter_the_rig_does_not(tmp_path):
    """A rolling-shutter webcam (25 ms) swinging out and back at up to 20 deg/s under a
    rig file that says global shutter: the first frames are sheared (refused, or ok and
    biased), those after the frames' own readout estimate passes 5 sigma are taken out
    with it, say so, and are right within their sigma; the run ends saying why and what
    to do. The same swing seen by a global shutter has nothing to say, nor has a slow
    turn in a lab whose target hangs 15 mm from where the rig file puts it (before
    `calibrate zero-tilt`: its residuals, fixed in the triangle's frame, looked like a
    -16 ms shutter)."""
    sim = ["simulate", "--rig", RIG, "--frames", 30, "--seed", 4, "--motion", "swing"]
    fast = ["--yaw-rate-dps", 20]
    assert run(*sim, *fast, "--out", tmp_path / "rs", "--readout-ms", 25).exit_code == 0
    assert run(*sim, *fast, "--out", tmp_path / "gs").exit_code == 0
    r = run("batch", tmp_path / "rs", "--rig", RIG, "--out", tmp_path / "rs.csv")
    assert r.exit_code == 0
    note = [line for line in r.output.splitlines() if "rolling shutter" in line]
    assert len(note) == 1 and "calibrate readout" in note[0], r.output
    readout = float(note[0].split("reading out in about ")[1].split(" +-")[0])
    assert 15 <= readout <= 35, note  # first order: a rough figure
    rows = rows_of((tmp_path / "rs.csv").read_text())
    estimated = [i for i, x in enumerate(rows) if "rolling_shutter_estimated" in x["warnings"]]
    ok = [i for i, x in enumerate(rows) if x["status"] == "ok"]
    # from the first estimated row on, every ok row is taken out with the estimate
    assert estimated and estimated == [i for i in ok if i >= estimated[0]], rows
    assert estimated[0] <= 20 and len(estimated) >= 10, estimated
    assert f"{len(estimated)} ok rows were taken out with this running estimate" in note[0]
    truth = list(csv.DictReader(open(tmp_path / "rs" / "truth.csv")))
    assert_within_3_sigma([rows[i] for i in estimated], [truth[i] for i in estimated])
    # the swing: out at up to 20 deg/s and back to where it started
    yaw = np.degrees(np.unwrap(np.radians([float(t["yaw_deg"]) for t in truth])))
    rate = np.diff(yaw) * 30.0
    assert 19.0 < rate.max() <= 20.0 and -20.0 <= rate.min() < -19.0
    assert abs(yaw[-1] - yaw[0]) < 1e-6
    r = run("batch", tmp_path / "gs", "--rig", RIG, "--out", tmp_path / "gs.csv")
    assert r.exit_code == 0 and "rolling shutter" not in r.output
    rows = rows_of((tmp_path / "gs.csv").read_text())
    assert all(row["status"] == "ok" and row["warnings"] == "" for row in rows)
    off = ["simulate", "--rig", RIG, "--frames", 60, "--seed", 7, "--motion", "sweep"]
    slow = ["--yaw-rate-dps", 5, "--target-offset-mm", 15, 0]
    assert run(*off, *slow, "--out", tmp_path / "off").exit_code == 0
    r = run("batch", tmp_path / "off", "--rig", RIG, "--out", tmp_path / "off.csv")
    assert r.exit_code == 0 and "rolling shutter" not in r.output
    assert "rolling_shutter" not in (tmp_path / "off.csv").read_text()


def test_batch_on_a_video_file_uses_its_clock(tmp_path):
    video = tmp_path / "rec.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480), False)
    assert w.isOpened()
    for f in sorted(SAMPLES.glob("*.png"))[:3]:
        w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    w.release()
    r = run("batch", video, "--rig", RIG)
    assert r.exit_code == 0
    rows = rows_of(r.stdout)
    assert [float(x["time_s"]) for x in rows] == pytest.approx([0.0, 0.1, 0.2])
    assert all(x["status"] == "ok" for x in rows)


def test_batch_takes_a_quoted_glob(tmp_path):
    """`batch 'frames/frame_000[0-3].png'` (a pattern the shell did not expand): those
    images, in natural order, with the folder's times."""
    out = tmp_path / "rows.csv"
    r = run("batch", f"{SAMPLES}/frame_000[0-3].png", "--rig", RIG, "--out", out)
    assert r.exit_code == 0, r.stderr
    rows = rows_of(out.read_text())
    assert [x["status"] for x in rows] == ["ok"] * 4
    full = rows_of(run("batch", SAMPLES, "--rig", RIG).stdout)
    assert [x["yaw_deg"] for x in rows] == [x["yaw_deg"] for x in full[:4]]
    r = run("batch", f"{SAMPLES}/nothing_*.png", "--rig", RIG)
    assert r.exit_code == 3 and "no image matches the pattern" in r.stderr


@pytest.mark.slow  # 4-7 s: the default run stays under 5 minutes
def test_many_recordings_one_output_each_wherever_they_run(tmp_path):
    """`batch REC... --out-dir DIR`: one output per recording, named after it, the same
    rows whether the recordings run in this process or on a local Dask cluster of two
    workers (latency_ms, the time each frame took, aside), a line per recording; one
    recording's options are refused before any work."""
    pytest.importorskip("distributed")
    recs = []
    for k in range(3):
        rec = tmp_path / f"rec{k}"
        r = CliRunner().invoke(cli, ["simulate", "--rig", RIG, "--out", str(rec), "--frames",
                                     "6", "--seed", str(k)])  # fmt: skip
        assert r.exit_code == 0, r.output
        recs.append(str(rec))
    outs = {}
    for workers in ("1", "2"):
        out = tmp_path / f"out{workers}"
        r = CliRunner().invoke(cli, ["batch", *recs, "--rig", RIG, "--out-dir", str(out),
                                     "--workers", workers])  # fmt: skip
        assert r.exit_code == 0, r.output
        for k in range(3):
            assert f"rec{k}: 6 ok of 6 rows -> {out / f'rec{k}.csv'}" in r.output
        outs[workers] = {
            k: [{c: v for c, v in row.items() if c != "latency_ms"}
                for row in csv.DictReader(open(out / f"rec{k}.csv"))]
            for k in range(3)
        }  # fmt: skip
    assert outs["1"] == outs["2"]
    assert outs["1"][0] != outs["1"][1]  # each recording its own rows
    r = CliRunner().invoke(cli, ["batch", *recs, "--rig", RIG, "--out-dir", str(tmp_path / "x"),
                                 "--truth", str(tmp_path / "rec0" / "truth.csv")])  # fmt: skip
    assert r.exit_code == 2 and "--truth: one recording's options" in r.output
    assert not (tmp_path / "x").exists()
    r = CliRunner().invoke(cli, ["batch", *recs, "--rig", RIG])
    assert r.exit_code == 2 and "several recordings need --out-dir" in r.output


def test_batch_of_an_mp4v_video_with_the_pixel_fit_says_it_measures_with_the_lines(tmp_path):
    """The shipped recording as an mp4v video: a pixel-fit rig says before the first row
    that the pixel fit is set aside on these frames (FMP4 predicts frames from earlier
    ones) and writes the same rows as the lines' rig; both say that no sigma_scale
    measured the codec's errors, and their ok rows carry inter_frame_codec; as
    Motion-JPEG, none of it."""
    files = sorted(SAMPLES.glob("*.png"))
    videos = {}
    for fourcc, name in (("mp4v", "rec.mp4"), ("MJPG", "rec.avi")):
        w = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*fourcc), 10.0,
                            (640, 480), False)  # fmt: skip
        for f in files:
            w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
        w.release()
        videos[fourcc] = tmp_path / name
    rig = CONFIGS / "triangle.toml"
    pixels = rig_variant(rig, "refine", '"lines"', '"pixels"', tmp_path / "pixels.toml")
    out = {}
    for key, video, r in (("lines", videos["mp4v"], rig), ("pixels", videos["mp4v"], pixels),
                          ("mjpeg", videos["MJPG"], pixels)):  # fmt: skip
        res = run("batch", video, "--rig", r, "--out", tmp_path / f"{key}.csv")
        assert res.exit_code == 0, res.output
        rows = rows_of((tmp_path / f"{key}.csv").read_text())
        assert len(rows) == len(files) and sum(x["status"] == "ok" for x in rows) >= 10
        out[key] = (res.stderr, [{k: x[k] for k in x if k != "latency_ms"} for x in rows])
    start = "the frames come through FMP4, a codec that predicts frames from earlier ones"
    assert out["pixels"][0].count(start) == 1 and "set aside" in out["pixels"][0]
    assert out["pixels"][1] == out["lines"][1]
    # the lines' rig is told the rows' sigma does not cover the codec's errors, and
    # each ok row says so; Motion-JPEG's frames are neither
    assert out["lines"][0].count(start) == 1 and "set aside" not in out["lines"][0]
    assert "calibrate zero-tilt` on level frames taken through this same" in out["lines"][0]
    ok = [x for x in out["lines"][1] if x["status"] == "ok"]
    assert all("inter_frame_codec" in x["warnings"].split(";") for x in ok)
    assert "FMP4" not in out["mjpeg"][0] and "set aside" not in out["mjpeg"][0]
    assert not any("inter_frame_codec" in x["warnings"] for x in out["mjpeg"][1])


@pytest.mark.slow  # 8-10 s: a local cluster started and interrupted
def test_ctrl_c_on_many_recordings_names_each_incomplete_output(tmp_path):
    """Ctrl-C, as a terminal sends it (to every process of the group), on `batch REC...
    --out-dir DIR` with two workers: exit 130, no worker's traceback, a line for each
    output that is not finished (was: exit 0, a 37-71-line traceback, nothing said)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    frames = sorted(Path(SAMPLES).glob("*.png"))
    recs = []
    for k in range(4):
        rec = tmp_path / f"rec{k}"
        rec.mkdir()
        for i in range(480):
            (rec / f"frame_{i:04d}.png").symlink_to(frames[i % len(frames)])
        recs.append(str(rec))
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "visvec", "batch", *recs, "--rig", str(RIG),
                          "--out-dir", str(out), "--workers", "2"],
                         stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if any(f.stat().st_size > 2000 for f in out.glob("*.csv")):
                break
            time.sleep(0.05)
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    named = [line for line in err.splitlines() if line.startswith("visvec: interrupted: ")]
    assert named and all(("incomplete" in x or "not written" in x) for x in named), err
    assert len(named) == len({x.split(": ")[2] for x in named})  # one line each
