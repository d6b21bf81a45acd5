"""`visvec track` (visvec.cli.track): live cameras that fail to open, stop, drop off and
come back; their clocks and settings."""

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.errors import SourceError
from visvec.rig import load_rig
from visvec.sources import VideoSource

from conftest import CONFIGS, SAMPLES, rows_of, run

RIG = str(CONFIGS / "triangle.toml")


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


def _stamped_times(monkeypatch, stamps_ms, reads):
    """The times VideoSource gives the frames of a _StampedCamera read at ``reads``
    (s, our clock), with the source and the warnings it logged."""
    import visvec.sources.video as video

    now = [0.0]
    monkeypatch.setattr(cv2, "VideoCapture", lambda spec: _StampedCamera(stamps_ms, reads, now))
    monkeypatch.setattr(video.time, "monotonic", lambda: now[0])
    said = _source_warnings(monkeypatch)
    src = VideoSource(0, max_frames=len(reads))
    return np.array([f.time_s for f in src]), src, said


# 3 s at 30 fps; read 2-20 ms after capture
_CAPTURE = np.arange(90) / 30.0
_READS = 100.0 + _CAPTURE + 0.002 + np.random.default_rng(5).uniform(0.0, 0.018, 90)
_STAMPS = 5000.0 + 1000.0 * _CAPTURE


@pytest.mark.parametrize(
    "case, stamps_ms, clock, said_word",
    [
        # the driver's capture times, kept by our clock
        ("good", _STAMPS, "source", None),
        # a backend without timestamps: the read times
        ("none", np.zeros(90), "read", None),
        # timestamps that stop increasing once in use: the read times from there on
        (
            "stuck",
            np.where(np.arange(90) < 75, _STAMPS, _STAMPS[74]),
            "read",
            "stopped making sense",
        ),
        # a clock that jumped 0.6 s within the trial: not the frames'
        ("jump", _STAMPS + 600.0 * (np.arange(90) >= 10), "read", "stopped making sense"),
        # a clock 20 % fast (FFmpeg's count of an MJPEG stream's frames at 25 fps, on a 30
        # fps camera): tried and refused, though within SOURCE_CLOCK_TOLERANCE_S of ours
        ("fast", 5000.0 + 1200.0 * _CAPTURE, "read", "% faster than this computer"),
    ],
)
def test_live_frame_times_come_from_the_driver_when_it_stamps_them(
    monkeypatch, case, stamps_ms, clock, said_word
):
    """A live source's timestamps are tried against the read times for
    SOURCE_CLOCK_TRIAL_S (the frames take their read times meanwhile) and used only if
    they kept our clock's rate; then while they stay increasing and in step."""
    import visvec.sources.video as video

    times, src, said = _stamped_times(monkeypatch, stamps_ms, _READS)
    read = _READS - _READS[0]
    trial = read < video.SOURCE_CLOCK_TRIAL_S
    assert src.clock == clock
    if clock == "source":
        np.testing.assert_allclose(times[trial], read[trial], atol=1e-9)
        # after the trial: the capture times (on our clock, from the first frame's read)
        # plus the fastest read of the trial (then moved towards a faster one at most
        # SOURCE_SLEW a second), not the jittered reads
        expect = _CAPTURE - (_READS[0] - 100.0) + (_READS - 100.0 - _CAPTURE)[trial].min()
        assert np.abs(times - expect)[~trial].max() < video.SOURCE_SLEW * 1.0
        assert np.abs(times - read)[~trial].max() > 0.01  # (which differ by up to 18 ms)
        assert np.all(np.diff(times) > 0)
    elif case == "stuck":  # the driver's times until they stuck, the reads after
        np.testing.assert_allclose(times[75:], read[75:], atol=1e-9)
        assert np.abs(times - read)[~trial][:75].max() > 0.01
    else:
        np.testing.assert_allclose(times, read, atol=1e-9)
    if said_word is None:
        assert not said
    else:
        assert len(said) == 1 and said_word in said[0], said


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


def test_a_cameras_own_clock_is_followed_through_a_drift(monkeypatch):
    """Half an hour at 30 fps from a camera whose clock runs 100 ppm slow, its frames
    read 2-20 ms after capture and its first one 80 ms late (a camera starting up): the
    frames' times (on our clock, from the first frame) stay those of their capture plus
    the fastest read's 2 ms, within 1 ms after the clock's trial (the first frame's lag
    does not carry over); they never go back, and the driver's timestamps stay in use.
    Anchored on the first frame, they were 78 ms late at first and drifted 0.18 s by the
    end."""
    import visvec.sources.video as video

    rng = np.random.default_rng(2)
    n = 30 * 60 * 30
    capture = np.arange(n) / 30.0  # our clock
    stamps_ms = 1000.0 * (50.0 + capture * (1.0 - 100e-6))
    reads = 200.0 + capture + 0.002 + rng.uniform(0.0, 0.018, n)
    reads[0] = 200.0 + 0.08
    # the frames after it wait until it was read (read back to back, 0.1 ms apart)
    reads = np.maximum(reads, 200.08 + 1e-4 * np.arange(n))
    now = [0.0]
    monkeypatch.setattr(cv2, "VideoCapture", lambda spec: _StampedCamera(stamps_ms, reads, now))
    monkeypatch.setattr(video.time, "monotonic", lambda: now[0])
    said = _source_warnings(monkeypatch)
    src = VideoSource(0, max_frames=n)
    times = np.array([f.time_s for f in src])
    assert src.clock == "source" and not said
    assert np.all(np.diff(times) > 0)
    # our time of each frame's capture plus the fastest read, from the first frame's read
    expect = capture + 0.002 - (reads[0] - 200.0)
    settled = capture > 90.0
    assert np.abs(times - expect)[settled].max() < 1e-3
