"""The command line: exit codes, messages, row streaming, bad input."""

import csv
import io
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.frames import run_frames
from visvec.cli.main import cli
from visvec.data import Frame
from visvec.errors import NoOkRows, SourceError
from visvec.rig import load_rig
from visvec.sources import VideoSource

from conftest import CONFIGS, ROOT, rig_variant

RIG = str(CONFIGS / "triangle.toml")
SAMPLES = ROOT / "data" / "sample_frames"


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def assert_within_3_sigma(rows, truth):
    """Every row's yaw, pitch and roll within 3 of its sigma of the truth file's."""
    for x, t in zip(rows, truth, strict=True):
        for k in ("yaw", "pitch", "roll"):
            err = (float(x[f"{k}_deg"]) - float(t[f"{k}_deg"]) + 180.0) % 360.0 - 180.0
            assert abs(err) < 3.0 * float(x[f"sigma_{k}_deg"]), (x["frame"], k)


def besides_the_zero_tilt_note(stderr: str) -> str:
    """stderr without the note a run on an uncalibrated triangle rig starts with, and
    without the summary line every run of frames ends with (checked there: it says
    every frame was ok)."""
    note = "visvec: note: no zero-tilt calibration given"
    lines = [x for x in stderr.splitlines(keepends=True) if not x.startswith(note)]
    summary = re.compile(r"visvec: (\d+) frames, (\d+) ok \(")
    kept = []
    for x in lines:
        m = summary.match(x)
        if m:
            assert m.group(1) == m.group(2), x  # a summary of a run with refusals
            continue
        kept.append(x)
    return "".join(kept)


def rows_of(text):
    return list(csv.DictReader(io.StringIO(text)))


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


def test_bad_rig_exit_2_before_any_frame(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(RIG).read_text().replace("fy = 600.0", ""))
    out = tmp_path / "rows.csv"
    r = run("batch", SAMPLES, "--rig", bad, "--out", out)
    assert r.exit_code == 2
    assert "bad.toml" in r.output and "[camera] fy" in r.output and "missing" in r.output
    assert not out.exists()


@pytest.mark.parametrize("what", ["missing_folder", "empty_folder", "missing_video"])
def test_unopenable_sources_exit_3(tmp_path, what):
    path = {
        "missing_folder": tmp_path / "nope",
        "empty_folder": tmp_path,
        "missing_video": tmp_path / "rec.avi",
    }[what]
    r = run("batch", path, "--rig", RIG)
    assert r.exit_code == 3
    assert str(path) in r.output


def test_camera_that_cannot_be_opened_exit_3():
    r = run("track", "--rig", RIG, "--camera", "97")
    assert r.exit_code == 3
    assert "97" in r.output and "cannot open" in r.output


def test_a_camera_that_cannot_be_opened_gives_one_line_not_opencvs_warnings():
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "visvec", "track", "--rig", str(RIG), "--camera", "97"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert p.returncode == 3
    assert p.stderr.strip().splitlines() == [
        "visvec: error: camera 97: cannot open it (not connected, in use by another "
        "program, or no permission?); --camera also takes a video file or URL"
    ]


def test_a_reader_that_closes_the_pipe_ends_the_run_quietly(tmp_path):
    """`visvec batch ... | head -2`: the run ends with status 0 and no error message, and
    a calibration whose report is cut short has still written its file."""
    import subprocess
    import sys

    rig320 = str(CONFIGS / "triangle-320.toml")
    frames = tmp_path / "level"
    r = run("simulate", "--rig", rig320, "--out", frames, "--frames", 40, "--motion", "level")
    assert r.exit_code == 0
    vis = [sys.executable, "-m", "visvec"]
    p = subprocess.Popen(
        [*vis, "batch", str(frames), "--rig", rig320],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert p.stdout.readline().startswith("frame,time_s,status")
    p.stdout.close()  # the reader is gone before the rows come
    assert p.wait(timeout=120) == 0
    assert besides_the_zero_tilt_note(p.stderr.read()) == ""
    cal = tmp_path / "cal.toml"
    cmd = [*vis, "calibrate", "zero-tilt", str(frames), "--rig", rig320, "--out", str(cal)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    p.stdout.close()
    assert p.wait(timeout=120) == 0
    assert p.stderr.read() == ""
    assert "sigma_scale" in cal.read_text()


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


def test_ctrl_c_ends_cleanly_with_every_row_written(tmp_path):
    rig = load_rig(RIG)
    img = cv2.imread(str(sorted(SAMPLES.glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)

    def frames():
        for i in range(3):
            yield Frame(i, i / 30, img, f"f{i}")
        raise KeyboardInterrupt

    out = tmp_path / "rows.csv"
    rows = run_frames(
        rig,
        frames(),
        out=str(out),
        fmt="csv",
        method="full",
        overlay=None,
        max_frames=None,
        keep_rows=True,
    )
    assert len(rows) == 3
    assert len(rows_of(out.read_text())) == 3


def test_status_lines_for_an_operator(tmp_path, capsys):
    """With the rows going to a file, `track` at a terminal prints a status line every
    few seconds and one at the end: frames, ok share, rate, the last ok attitude."""
    rig = load_rig(RIG)
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(SAMPLES.glob("*.png"))[:3]]
    frames = [Frame(i, i / 30, im, f"f{i}") for i, im in enumerate(imgs)]
    frames.append(Frame(3, 0.1, None, "f3", error="empty frame"))
    out = tmp_path / "rows.csv"
    run_frames(
        rig,
        frames,
        out=str(out),
        fmt="csv",
        method=None,
        overlay=None,
        max_frames=None,
        progress=1e-9,  # a status line after every frame (stderr is not a terminal here)
    )
    lines = [x for x in capsys.readouterr().err.splitlines() if "frames/s" in x]
    assert len(lines) == 5  # one per frame at a 0 s interval, and the last
    assert lines[-1].startswith("visvec: 4 frames, 3 ok (75.0 %),")
    last = rows_of(out.read_text())[2]
    assert f"last ok (frame 2): yaw {float(last['yaw_deg']):+.4f}, pitch" in lines[-1]
    # and why the others were not ok
    assert lines[-1].endswith("; not ok: read_error 1") and "not ok" not in lines[0]


def test_a_long_run_does_not_hold_its_rows_in_memory(tmp_path):
    """`track` can run for hours: the loop's memory must not grow with the frame count."""
    import tracemalloc

    rig = load_rig(RIG)

    def peak(n):
        frames = (Frame(i, i / 30, None, f"f{i}", error="empty frame") for i in range(n))
        tracemalloc.start()
        with pytest.raises(NoOkRows):  # every frame here is a read_error: exit 4
            run_frames(
                rig,
                frames,
                out=str(tmp_path / "r.csv"),
                fmt="csv",
                method=None,
                overlay=None,
                max_frames=None,
            )
        size = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return size

    assert peak(4000) - peak(400) < 100_000  # bytes; a kept row is about 1 kB


def test_track_can_keep_the_frames_for_a_replay(tmp_path):
    """--save-frames keeps every frame losslessly with its time: `batch` on the folder
    gives the same rows."""
    saved = tmp_path / "rec"
    r = run(
        "track",
        "--rig",
        RIG,
        "--camera",
        SAMPLES,
        "--save-frames",
        saved,
        "--out",
        tmp_path / "live.csv",
    )
    assert r.exit_code == 0, r.output
    r2 = run("batch", saved, "--rig", RIG, "--out", tmp_path / "replay.csv")
    assert r2.exit_code == 0, r2.output
    live = rows_of((tmp_path / "live.csv").read_text())
    replay = rows_of((tmp_path / "replay.csv").read_text())
    assert len(live) == len(list(SAMPLES.glob("*.png"))) == len(replay)
    for a, b in zip(live, replay, strict=True):
        a.pop("latency_ms"), b.pop("latency_ms")
        assert a == b
    # the run said it had no zero-tilt calibration; with one, it does not
    assert "no zero-tilt calibration given" in r.stderr
    cal = tmp_path / "zero.toml"
    cal.write_text("[zero_tilt]\ncentroid_px = [319.5, 239.5]\n")
    r4 = run("track", "--rig", RIG, "--calibration", cal, "--camera", SAMPLES, "--out", "-")
    assert r4.exit_code == 0 and "zero-tilt" not in r4.stderr
    assert r4.stdout.startswith("frame,time_s,status")  # '-': standard output
    # a second recording into the same folder is refused before the camera is opened,
    # and the first is left whole
    times = (saved / "times.csv").read_text()
    r3 = run("track", "--rig", RIG, "--camera", 7, "--save-frames", saved, "--max-frames", 2)
    assert r3.exit_code == 2 and "already holds a recording" in r3.output, r3.output
    assert (saved / "times.csv").read_text() == times


def test_camera_that_stops_delivering_is_retried_then_raises(monkeypatch):
    class DeadCap:
        def read(self):
            return False, None

        def isOpened(self):
            return True

        def get(self, prop):
            return 0.0

        def release(self):
            pass

    monkeypatch.setattr(cv2, "VideoCapture", lambda spec: DeadCap())
    src = VideoSource(0, retry_s=0.2)
    with pytest.raises(SourceError, match="stopped delivering"):
        next(iter(src))


def _source_warnings(monkeypatch) -> list[str]:
    """The video source's logged warnings, whatever handlers an earlier test left on the
    ``visvec`` logger (the CLI routes it to stderr and stops its propagation)."""
    import visvec.sources.video as video

    said = []
    monkeypatch.setattr(video._log, "warning", lambda msg, *args: said.append(msg % args))
    return said


def test_camera_that_drops_off_is_opened_again_and_the_run_goes_on(monkeypatch):
    """A USB webcam that drops off the bus and comes back (a loose cable) delivers again
    only to a new capture: while retrying, the source closes and opens it again (every
    REOPEN_EVERY_S), asks it for the rig's mode again, and the frames go on with their
    indices; one that never comes back still ends the run after retry_s (exit 3)."""
    import visvec.sources.video as video

    img = np.full((240, 320), 90, np.uint8)
    caps = []

    class FlakyCam:
        """The first capture delivers two frames, then nothing; later ones deliver."""

        def __init__(self, spec):
            self.n, self.props, self.dead = 0, {}, not caps
            caps.append(self)

        def isOpened(self):
            return True

        def set(self, prop, value):
            self.props[prop] = value
            return True

        def get(self, prop):
            return 0.0

        def read(self):
            self.n += 1
            if self.dead and self.n > 2:
                return False, None
            return True, img

        def release(self):
            self.released = True

    monkeypatch.setattr(cv2, "VideoCapture", FlakyCam)
    monkeypatch.setattr(video, "REOPEN_EVERY_S", 0.1)
    said = _source_warnings(monkeypatch)
    src = VideoSource(0, retry_s=2.0, max_frames=5, size=(320, 240))
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert all(f.image is not None for f in frames)
    assert src.reopened == 1 and len(caps) == 2 and caps[0].released
    assert caps[1].props[cv2.CAP_PROP_FRAME_WIDTH] == 320  # the rig's mode asked again
    assert sum("opening it again" in m for m in said) == 1, said

    class GoneForGood(FlakyCam):
        """The first capture delivers two frames; later ones none."""

        def read(self):
            self.n += 1
            return (True, img) if self is caps[0] and self.n <= 2 else (False, None)

    caps.clear()
    monkeypatch.setattr(cv2, "VideoCapture", GoneForGood)
    src = VideoSource(0, retry_s=0.35, size=(320, 240))
    with pytest.raises(SourceError, match=r"opened again [23] times"):
        list(src)


class _StampedCamera:
    """A camera whose driver stamps each frame (CAP_PROP_POS_MSEC) with ``stamps_ms``,
    while frames are read at ``reads_s`` on our clock."""

    def __init__(self, stamps_ms, reads_s, clock):
        self.stamps, self.reads, self.clock, self.k = stamps_ms, reads_s, clock, -1

    def isOpened(self):
        return True

    def set(self, prop, value):
        return True

    def get(self, prop):
        return float(self.stamps[self.k]) if prop == cv2.CAP_PROP_POS_MSEC else 0.0

    def read(self):
        self.k += 1
        self.clock[0] = self.reads[self.k]
        return True, np.zeros((4, 4), np.uint8)

    def release(self):
        pass


@pytest.mark.parametrize(
    "stamps_ms, expect_s, clock",
    [
        # the driver's capture times: regular, though the reads jitter by a frame
        ([5000.0, 5033.3, 5066.7, 5100.0], [0.0, 0.0333, 0.0667, 0.1], "source"),
        # a backend without timestamps: the read times
        ([0.0, 0.0, 0.0, 0.0], [0.0, 0.05, 0.07, 0.13], "read"),
        # timestamps that stop increasing: the read times from there on
        ([5000.0, 5033.3, 5033.3, 5100.0], [0.0, 0.0333, 0.07, 0.13], "read"),
        # a clock that has run 0.6 s slower than ours by the fourth frame: not the frames'
        ([5000.0, 5033.3, 5066.7, 5100.0], [0.0, 0.0333, 0.0667, 0.7], "read"),
    ],
)
def test_live_frame_times_come_from_the_driver_when_it_stamps_them(
    monkeypatch, stamps_ms, expect_s, clock
):
    reads = [100.0, 100.05, 100.07, 100.13 if expect_s[3] < 0.5 else 100.7]
    now = [0.0]
    monkeypatch.setattr(cv2, "VideoCapture", lambda spec: _StampedCamera(stamps_ms, reads, now))
    import visvec.sources.video as video

    monkeypatch.setattr(video.time, "monotonic", lambda: now[0])
    said = _source_warnings(monkeypatch)
    src = VideoSource(0, max_frames=4)
    times = [f.time_s for f in src]
    np.testing.assert_allclose(times, expect_s, atol=1e-9)
    assert src.clock == clock
    # a switch away from timestamps that were in use is reported; none were: no message
    reported = any("stopped making sense" in m for m in said)
    assert reported == (clock == "read" and stamps_ms[0] > 0)


class _FakeCamera:
    """A cv2.VideoCapture stand-in for a camera whose modes are ``modes`` (w, h)."""

    def __init__(self, modes, frame):
        self.modes, self.frame, self.props = modes, frame, {}
        self.size = modes[0]

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.props[prop] = value
        want = (
            int(self.props.get(cv2.CAP_PROP_FRAME_WIDTH, self.size[0])),
            int(self.props.get(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])),
        )
        if want in self.modes:
            self.size = want
        return True

    def get(self, prop):
        return 0.0

    def read(self):
        return True, cv2.resize(self.frame, self.size)

    def release(self):
        pass


def test_track_asks_the_camera_for_the_rigs_frame_size_and_rate(monkeypatch):
    """A webcam starts in its own mode (640x480 here): track asks it for the rig's
    320x240 and fps, and refuses a camera without that mode before any row, naming
    both sizes, instead of a read_error row for every frame."""
    img = cv2.imread(str(sorted(SAMPLES.glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    rig320 = str(CONFIGS / "triangle-320.toml")
    cams = []

    def capture(modes):
        def make(spec):
            cams.append(_FakeCamera(modes, img))
            return cams[-1]

        return make

    monkeypatch.setattr(cv2, "VideoCapture", capture([(640, 480), (320, 240)]))
    r = run("track", "--rig", rig320, "--camera", "0", "--max-frames", "3")
    assert r.exit_code == 0, r.output
    assert cams[-1].props[cv2.CAP_PROP_FRAME_WIDTH] == 320
    assert cams[-1].props[cv2.CAP_PROP_FRAME_HEIGHT] == 240
    assert cams[-1].props[cv2.CAP_PROP_FPS] == load_rig(rig320).fps
    assert cams[-1].props[cv2.CAP_PROP_BUFFERSIZE] == 1  # the newest frame, not a queued one
    assert [x["status"] for x in rows_of(r.stdout)] == ["ok"] * 3
    monkeypatch.setattr(cv2, "VideoCapture", capture([(640, 480)]))
    r = CliRunner().invoke(cli, ["track", "--rig", rig320, "--camera", "0"])
    assert r.exit_code == 3
    assert "camera 0: delivers 640x480 frames, not the rig's 320x240" in r.output
    assert rows_of(r.stdout) == []  # refused before any row


def test_overlay_and_paper_method(tmp_path):
    ov = tmp_path / "ov"
    r = run(
        "batch", SAMPLES, "--rig", RIG, "--method", "paper", "--overlay", ov, "--max-frames", "2"
    )
    assert r.exit_code == 0
    assert len(list(ov.glob("*.png"))) == 2
    assert all(x["status"] == "ok" for x in rows_of(r.stdout))


def test_simulate_writes_frames_and_truth(tmp_path):
    r = run(
        "simulate",
        "--rig",
        CONFIGS / "triangle-320.toml",
        "--out",
        tmp_path / "s",
        "--frames",
        "3",
        "--seed",
        "4",
    )
    assert r.exit_code == 0
    truth = list(csv.DictReader(open(tmp_path / "s" / "truth.csv")))
    assert [t["file"] for t in truth] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    img = cv2.imread(str(tmp_path / "s" / "frame_0000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320) and img.dtype == np.uint8


def test_simulate_a_rolling_shutter_sweep_that_batch_corrects(tmp_path):
    """`simulate --readout-ms` renders a sweep with each frame's rates; `batch` with the
    rig's readout_ms corrects every frame after the first, which says it is uncorrected
    and whose sigma covers the turn."""
    rig = tmp_path / "rig.toml"
    text = (CONFIGS / "triangle.toml").read_text()
    rig.write_text(
        text.replace("readout_ms = 0.0", "readout_ms = 25.0").replace(
            "max_rate_dps = 10.0", "max_rate_dps = 20.0"
        )
    )
    sim = ["simulate", "--rig", RIG, "--frames", "10", "--seed", "5", "--motion", "sweep"]
    fast = ["--yaw-rate-dps", "20", "--max-tilt-deg", "3"]
    assert run(*sim, "--out", tmp_path / "g", *fast).exit_code == 0
    r = run(*sim, "--out", tmp_path / "s", *fast, "--readout-ms", "25")
    assert r.exit_code == 0, r.output
    a = cv2.imread(str(tmp_path / "g" / "frame_0004.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(tmp_path / "s" / "frame_0004.png"), cv2.IMREAD_GRAYSCALE)
    assert np.count_nonzero(a != b) > 500  # rows exposed at their own attitudes
    truth = list(csv.DictReader(open(tmp_path / "s" / "truth.csv")))
    yaw = np.unwrap(np.radians([float(t["yaw_deg"]) for t in truth]))
    np.testing.assert_allclose(np.degrees(np.diff(yaw)) * 30.0, 20.0, rtol=1e-6)
    r = run("batch", tmp_path / "s", "--rig", rig)
    rows = rows_of(r.stdout)
    assert r.exit_code == 0 and [x["status"] for x in rows] == ["ok"] * 10
    uncorrected = [i for i, x in enumerate(rows) if "rolling_shutter_uncorrected" in x["warnings"]]
    assert uncorrected == [0]
    assert_within_3_sigma(rows, truth)
    bad = run(*sim, "--out", tmp_path / "x", "--readout-ms", "40")
    assert bad.exit_code == 2 and "--readout-ms" in bad.output
    bad = run("simulate", "--rig", RIG, "--out", tmp_path / "x", "--yaw-rate-dps", "5")
    assert bad.exit_code == 2 and "--motion sweep" in bad.output


def test_motion_blur_of_a_long_exposure_neither_loses_nor_biases_the_triangle(tmp_path):
    """`simulate --exposure-ms 33` blurs a 40 deg/s sweep by its motion (each row
    collects light over 33 ms, centred on its time); tracked, every frame is ok and
    within 3 sigma: a blur symmetric about the exposure's middle moves no edge."""
    rig = str(CONFIGS / "triangle-320.toml")
    sim = ["simulate", "--rig", rig, "--frames", "10", "--seed", "8", "--motion", "sweep"]
    fast = ["--yaw-rate-dps", "40"]
    assert run(*sim, "--out", tmp_path / "sharp", *fast).exit_code == 0
    r = run(*sim, "--out", tmp_path / "blur", *fast, "--exposure-ms", "33")
    assert r.exit_code == 0, r.output
    a = cv2.imread(str(tmp_path / "sharp" / "frame_0005.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(str(tmp_path / "blur" / "frame_0005.png"), cv2.IMREAD_GRAYSCALE)
    assert np.count_nonzero(np.abs(a.astype(int) - b) > 3) > 100  # edges smeared
    r = run("batch", tmp_path / "blur", "--rig", rig)
    rows = rows_of(r.stdout)
    truth = list(csv.DictReader(open(tmp_path / "blur" / "truth.csv")))
    assert [x["status"] for x in rows] == ["ok"] * 10
    assert_within_3_sigma(rows, truth)
    bad = run(*sim, "--out", tmp_path / "x", "--exposure-ms", "50")
    assert bad.exit_code == 2 and "--exposure-ms" in bad.output


def test_body_rates_of_a_turn_about_the_lab_vertical():
    from visvec.rotations import euler_to_matrix
    from visvec.sim.simulate import body_rates

    w = np.radians(15.0)
    R = np.array([euler_to_matrix(0.4 + w * k / 30.0, 0.05, -0.03) for k in range(5)])
    for k, om in enumerate(body_rates(R, 1.0 / 30.0)):
        np.testing.assert_allclose(om, R[k].T @ [0.0, 0.0, w], atol=1e-12)


def test_unexpected_error_is_one_line_exit_1(monkeypatch):
    import visvec.cli.batch as b

    def boom(*a, **k):
        raise RuntimeError("kaboom")

    monkeypatch.setattr(b, "run_frames", boom)
    r = CliRunner().invoke(cli, ["batch", str(SAMPLES), "--rig", RIG])
    assert r.exit_code == 1
    assert "kaboom" in r.output and "Traceback" not in r.output


def test_truth_file_with_bad_row(tmp_path):
    t = tmp_path / "t.csv"
    t.write_text("frame,yaw_deg,pitch_deg,roll_deg\n0,1,2,3\n1,x,2,3\n")
    r = run("batch", SAMPLES, "--rig", RIG, "--truth", t)
    assert r.exit_code == 2 and "line 3" in r.output


def test_public_api_docstring_example_runs():
    import os

    from visvec.api import FolderSource, TrianglePipeline, load_rig

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        rig = load_rig("configs/triangle.toml")
        rows = list(TrianglePipeline(rig).run(FolderSource("data/sample_frames")))
    finally:
        os.chdir(cwd)
    assert len(rows) == 12 and all(r.ok for r in rows)


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


def test_track_reads_a_stream_url(tmp_path):
    import functools
    import http.server
    import threading

    video = tmp_path / "rec.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480), False)
    for f in sorted(SAMPLES.glob("*.png"))[:3]:
        w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    w.release()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/rec.avi"
        r = run("track", "--rig", RIG, "--camera", url, "--retry-s", "0.5")
    finally:
        httpd.shutdown()
    if r.exit_code == 3 and "cannot open" in r.output:
        pytest.skip("this OpenCV build cannot read HTTP streams")
    assert r.exit_code == 0, r.output
    rows = rows_of(r.stdout)
    assert len(rows) == 3 and all(x["status"] == "ok" for x in rows)


def test_overlay_text_sits_on_a_dark_box_without_black_outlines():
    """The overlay's header is white text on a darkened box. A thick black outline under
    the text was misaligned with it under OpenCV 5 (wider glyph spacing) and made the
    numbers unreadable; nothing may be darker than the darkened background."""
    from visvec.data import Status
    from visvec.output import AttitudeRow
    from visvec.overlay import _text

    grey = np.full((120, 400, 3), 150, np.uint8)
    row = AttitudeRow(
        frame=7,
        time_s=0.2,
        status=Status.OK,
        euler_deg=np.array([-42.11, -2.434, -0.775]),
        sigma_deg=np.array([0.014, 0.001, 0.001]),
        rms_px=0.02,
        n_points=3,
        latency_ms=1.0,
        warnings=("near_fov_edge",),
    )
    out = _text(grey.copy(), row)
    assert out.min() >= 150 // 3  # no black outline pixels
    assert out.max() >= 250  # the white text is there
    assert (out[5:60, 5:200] < 150).mean() > 0.5  # on a darkened box
    assert np.array_equal(out[100:, :], grey[100:, :])  # below the box: untouched


def test_overlay_draws_where_the_lens_models_field_ends(rig640):
    """A rig whose lens model folds over 345 px out (short of the 400 px corners): the
    overlay draws that edge, beyond which nothing is measured; a rig whose model holds
    to the corners draws none."""
    from dataclasses import replace

    from visvec.data import Status
    from visvec.output import AttitudeRow
    from visvec.overlay import draw_overlay

    frame = np.full((480, 640), 100, np.uint8)
    row = AttitudeRow(frame=0, time_s=0.0, status=Status.NO_TARGET, rms_px=np.nan,
                      n_points=0, latency_ms=1.0, warnings=("no_triangle",))  # fmt: skip
    dist = np.array([-0.32, 0.12, 0.0, 0.0, -0.02])
    folding = replace(rig640, camera=replace(rig640.camera, fx=340.0, fy=340.0, dist=dist))
    r = folding.camera.field_radius_px
    u, v = int(round(319.5 + 0.8 * r)), int(round(239.5 + 0.6 * r))  # towards a corner
    assert np.any(draw_overlay(frame, None, row, folding)[v - 1 : v + 2, u - 1 : u + 2] != 100)
    plain = draw_overlay(frame, None, row, rig640)
    assert np.all(plain[200:, :] == 100)  # below the header: the frame alone


@pytest.mark.parametrize("fmt", ["csv", "jsonl"])
def test_rows_stream_to_udp_one_datagram_each(fmt):
    """--out udp://HOST:PORT: every row is one datagram (a CSV header first), in order,
    for a flight computer or ground station listening on a socket."""
    import socket

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(5.0)
    url = f"udp://127.0.0.1:{rx.getsockname()[1]}"
    try:
        r = run("batch", SAMPLES, "--rig", RIG, "--out", url, "--format", fmt, "--max-frames", "3")
        assert r.exit_code == 0, r.output
        got = [rx.recv(65536).decode() for _ in range(4 if fmt == "csv" else 3)]
    finally:
        rx.close()
    assert all(g.endswith("\n") and g.count("\n") == 1 for g in got)
    rows = rows_of("".join(got)) if fmt == "csv" else [json.loads(g) for g in got]
    assert [int(x["frame"]) for x in rows] == [0, 1, 2]
    assert all(x["status"] == "ok" for x in rows)
    assert r.stdout == ""  # nothing on stdout when the rows go to the socket


@pytest.mark.parametrize(
    "url, words",
    [
        ("udp://127.0.0.1", "expected udp://HOST:PORT"),
        ("udp://no-such-host.invalid:5005", "cannot resolve"),
    ],
)
def test_bad_udp_address_is_refused_before_any_row(url, words):
    r = run("batch", SAMPLES, "--rig", RIG, "--out", url)
    assert r.exit_code == 2 and words in r.output


def test_status_lines_when_stderr_is_not_a_terminal(tmp_path):
    """Long work says it is alive: status lines every --status-every seconds (none with
    0), and every batch ends with its one-line summary."""
    runner = CliRunner()
    r = runner.invoke(cli, ["--status-every", "0.001", "batch", str(SAMPLES), "--rig", str(RIG),
                            "--out", str(tmp_path / "a.csv")])  # fmt: skip
    assert r.exit_code == 0, r.output
    lines = [x for x in r.stderr.splitlines() if x.startswith("visvec: batch: ")]
    assert lines and all(" of 12 frames (" in x and "ok " in x for x in lines)
    assert r.stderr.splitlines()[-1].startswith("visvec: 12 frames, 12 ok (100.0 %)")
    r = runner.invoke(cli, ["--status-every", "0", "batch", str(SAMPLES), "--rig", str(RIG),
                            "--out", str(tmp_path / "b.csv")])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert not [x for x in r.stderr.splitlines() if x.startswith("visvec: batch: ")]
    assert "visvec: 12 frames, 12 ok" in r.stderr


def test_progress_bar_at_a_terminal(tmp_path):
    """At a terminal, a bar (with the frame count and the ok share) instead of lines."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import sys
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "batch", str(SAMPLES), "--rig", str(RIG), "--out",
         str(tmp_path / "rows.csv")],
        stderr=slave, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(slave)
    out = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    proc.wait(timeout=60)
    os.close(master)
    text = out.decode(errors="replace")
    assert proc.returncode == 0, text
    assert "visvec batch:" in text and "/12 [" in text  # tqdm's bar: done/total
    assert "visvec: 12 frames, 12 ok (100.0 %)" in text  # and the summary stays


def test_misspelt_required_key_is_named(tmp_path):
    text = Path(RIG).read_text()
    assert "\nfx = " in text
    (tmp_path / "fxx.toml").write_text(text.replace("\nfx = ", "\nfxx = ", 1))
    r = run("batch", SAMPLES, "--rig", tmp_path / "fxx.toml")
    assert r.exit_code == 2 and "fx: missing (required); the file has 'fxx'" in r.stderr
    # a key of its own (fy) is not offered for a missing fx
    (tmp_path / "nofx.toml").write_text(
        "\n".join(x for x in text.splitlines() if not x.startswith("fx = "))
    )
    r = run("batch", SAMPLES, "--rig", tmp_path / "nofx.toml")
    assert r.exit_code == 2 and r.stderr.rstrip().endswith("fx: missing (required)")


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


def test_help_groups_the_options_of_each_kind():
    """`simulate --help`: the options for one target kind under that kind's heading,
    after the options for all; every option described; no range shown as None."""
    text = run("simulate", "--help").output
    heads = [line for line in text.splitlines() if line.endswith("options:") or line == "Options:"]
    assert heads == ["Options:", "Triangle options:", "Markers options:", "Starfield options:",
                     "Lamps options:"]  # fmt: skip
    tri = text.split("Triangle options:")[1].split("Markers options:")[0]
    assert "--blur" in tri and "--readout-ms" in tri and "--spurious" not in tri
    assert "--spurious" in text.split("Lamps options:")[1]
    assert "None]" not in text
    rate = run("rate", "--help").output
    assert "[required unless --budget]" in " ".join(rate.split())
    assert "--budget options:" in rate
