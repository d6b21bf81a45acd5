"""Cameras, video files and stream URLs through cv2.VideoCapture."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import cv2

from visvec.clocks import ClockTie
from visvec.data import Frame
from visvec.errors import SourceError
from visvec.rig import CameraControls
from visvec.sources.avi import read_avi_index
from visvec.sources.controls import apply_controls, describe_controls
from visvec.sources.folder import to_gray
from visvec.sources.reader import Arrival, LiveReader

_log = logging.getLogger(__name__)

# a live source's timestamps are used while their elapsed time stays within this of
# ours (s): a clock that is not running at real time (or jumped) is not the frames'
SOURCE_CLOCK_TOLERANCE_S = 0.5
# ... and only once they have kept time with ours for this long (s), to within
# SOURCE_RATE_TOLERANCE: until then a frame's time is when it was read. An MJPEG
# stream's timestamps are FFmpeg's count of its frames at 25 fps, 20 % fast on a 30 fps
# camera: taken at their word they put frames up to SOURCE_CLOCK_TOLERANCE_S off before
# the tolerance caught them
SOURCE_CLOCK_TRIAL_S = 2.0
# two crystals differ by tens of ppm; a clock 0.5 % off ours is not a crystal's
SOURCE_RATE_TOLERANCE = 5e-3
# the source's clock is tied to ours by its fastest-read frame of the last
# visvec.clocks.CLOCK_WINDOW_S, the tie moved towards it by at most this much a second
# (1000 ppm: 0.03 ms a frame at 30 fps, so the frames' times never go back): a camera's
# crystal that runs tens of ppm off the computer's is followed through hours
SOURCE_SLEW = 1e-3
# a live source that stops delivering is closed and opened again this often while it is
# retried (s): a USB camera that dropped off the bus and came back (a loose cable, a
# brown-out) or a stream whose connection broke delivers again only to a new capture
REOPEN_EVERY_S = 1.0
# a network stream (http://, rtsp://) that sends nothing for this long is taken to have
# stalled and is opened again (s): FFmpeg's own wait is about 30 s
STREAM_STALL_S = 1.5
# between attempts to open a stream that refused or failed (s)
STREAM_RETRY_PAUSE_S = 0.2


MAX_UNREADABLE_IN_A_ROW = 25  # then a file is taken to be cut short there


def codec_of(cap: cv2.VideoCapture) -> str:
    """The FOURCC of the codec a capture decodes (stripped), or "" where it does not
    say (0, -1, or not four printable characters); whether it predicts frames from
    earlier ones: :func:`visvec.data.inter_frame`."""
    v = int(cap.get(cv2.CAP_PROP_FOURCC) or 0)
    if v <= 0:
        return ""
    s = "".join(chr((v >> (8 * k)) & 0xFF) for k in range(4))
    return s.strip() if s.isprintable() else ""


def _rate_off(trial: list[tuple[float, float]]) -> float:
    """How much faster than ours a source's clock ran over a trial (0.01: 1 %), from
    (read time, read time - source time) pairs: the least of the second over the
    trial's first third against its last third (the frames read soonest after their
    timestamps, whose lags are the transport's alone), divided by the time between."""
    t0, t1 = trial[0][0], trial[-1][0]
    third = (t1 - t0) / 3.0
    a = min((p for p in trial if p[0] <= t0 + third), key=lambda p: p[1])
    b = min((p for p in trial if p[0] >= t1 - third), key=lambda p: p[1])
    return (a[1] - b[1]) / max(b[0] - a[0], 1e-9)


class VideoSource:
    """Frames from a camera index, a video file or a stream URL.

    Parameters
    ----------
    spec : int or str
        Camera index, file path or URL.
    fps : float
        Frame rate used for times when the source gives none.
    retry_s : float
        A live camera that stops delivering frames is retried for this long before
        :class:`SourceError` is raised, and closed and opened again every
        REOPEN_EVERY_S meanwhile. Files simply end.
    max_frames : int, optional
    size : (width, height), optional
        A camera (index) is asked for this frame size and ``fps`` (the rig's); if its
        first frame comes at another size, :class:`SourceError` (every frame would be
        unusable). Files and URLs deliver what they hold.

    Raises
    ------
    SourceError
        If the source cannot be opened.
    """

    def __init__(
        self,
        spec: int | str,
        fps: float = 30.0,
        retry_s: float = 5.0,
        max_frames: int | None = None,
        size: tuple[int, int] | None = None,
        controls: CameraControls | None = None,
    ):
        self.spec = spec
        # a camera's exposure, gain and focus, set at every open; what it runs with and
        # what it refused, said once (track prints them, the live view shows them)
        self.controls = controls if isinstance(spec, int) else None
        self.settings: list[str] = []
        self.settings_warnings: list[str] = []
        self.live = isinstance(spec, int) or "://" in str(spec)
        # a network stream: opened and read with timeouts, and waited for up to retry_s
        self.stream = isinstance(spec, str) and "://" in spec
        self.size = size if isinstance(spec, int) else None
        self._mode = (self.size, fps)  # what a camera is asked for, again on a reopen
        self.retry_s = retry_s
        self.cap = self._open_stream() if self.stream else self._open()
        # the codec the frames come through (Frame.codec)
        self.codec = codec_of(self.cap) if self.cap.isOpened() else ""
        if not self.cap.isOpened():
            if isinstance(spec, int):
                raise SourceError(
                    f"camera {spec}: cannot open it (not connected, in use by another "
                    f"program, or no permission?)"
                )
            if self.stream:
                raise SourceError(
                    f"{spec}: the stream did not answer within {retry_s:g} s: is "
                    "the camera on, the address and port right, and the stream's path?"
                )
            raise SourceError(f"{spec}: cannot open the video or stream")
        src_fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.fps = src_fps if src_fps and src_fps > 0 and not isinstance(spec, int) else fps
        # a Motion-JPEG AVI file: read by its own index (visvec.sources.avi), so that
        # a damaged stretch does not shift the frames after it onto others' numbers
        self._avi = (read_avi_index(spec) if not self.live and str(spec).lower().endswith(".avi")
                     else None)  # fmt: skip
        if self._avi is not None:
            self.fps = self._avi.fps
        self.max_frames = max_frames
        self._t0: float | None = None
        # a live source's own frame timestamps (CAP_PROP_POS_MSEC: V4L2's buffer time,
        # a stream's presentation time) as (first, last) in s, while they stay usable
        self._src: tuple[float, float] | None = None
        self._src_t0 = 0.0  # our time of the source's first timestamp (since a reopen)
        # the source's clock against ours since its first timestamp, and the tie used
        self._tie = ClockTie()
        self._src_off = 0.0
        self._src_read = 0.0  # our time of the last frame read by its timestamp
        # (read time, read time - source time) of the frames of the source clock's
        # trial (SOURCE_CLOCK_TRIAL_S); None once it is over
        self._trial: list[tuple[float, float]] | None = None
        self._read_time = True  # the last frame's time is when it was read
        self._next_n = 0  # the number its reader gives the next frame
        self.dropped = 0  # live frames read and not taken: the pipeline fell behind
        self.clock = "source" if self.live else "file"
        self.reopened = 0  # how often a live source was closed and opened again
        self._last_frame_at: float | None = None  # time.monotonic() of the last frame read

    def _open_stream(self) -> cv2.VideoCapture:
        """A network stream, tried until it opens or ``retry_s`` has passed: each
        attempt waits for the server at most what is left of it."""
        end = time.monotonic() + self.retry_s
        while True:
            cap = self._open(max(end - time.monotonic(), 0.1))
            if cap.isOpened() or time.monotonic() >= end:
                return cap
            cap.release()
            time.sleep(min(STREAM_RETRY_PAUSE_S, max(end - time.monotonic(), 0.0)))

    def _open(self, timeout_s: float | None = None) -> cv2.VideoCapture:
        """A capture of the source, a camera asked for the rig's frame size and rate; a
        network stream with FFmpeg's timeouts: ``timeout_s`` to open, STREAM_STALL_S
        to read a frame."""
        if self.stream:
            if timeout_s is None:
                timeout_s = max(self.retry_s, 0.1)
            cap = cv2.VideoCapture(
                self.spec,
                cv2.CAP_FFMPEG,
                [
                    cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                    int(timeout_s * 1000),
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                    int(STREAM_STALL_S * 1000),
                ],
            )
            # a live stream is read in a thread of its own (visvec.sources.reader); a
            # recording served over the network (it has a length) frame by frame
            live = cap.isOpened() and not cap.get(cv2.CAP_PROP_FRAME_COUNT) > 0
            return LiveReader(cap, "visvec-stream") if live else cap
        cap = cv2.VideoCapture(self.spec)
        size, fps = self._mode
        if size is not None and cap.isOpened():
            # V4L2, DirectShow and AVFoundation switch to the nearest mode they have
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(size[0]))
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(size[1]))
            cap.set(cv2.CAP_PROP_FPS, float(fps))
            # one buffered frame: read() returns the newest one, not one that waited in
            # the driver's queue while the last was processed (the latency column counts
            # from the frame in hand, so a queue would hide its age)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1.0)
        if isinstance(self.spec, int) and cap.isOpened():
            name = f"camera {self.spec}"
            refused = apply_controls(cap, self.controls, name) if self.controls else []
            if not self.settings:
                line, warnings = describe_controls(cap, name)
                self.settings = [line]
                self.settings_warnings = refused + warnings
        return cap

    def __iter__(self) -> Iterator[Frame]:
        if self._avi is not None:
            yield from self._iter_avi()
            return
        i = 0
        failed = 0  # frames of a file that could not be decoded, in a row
        try:
            while self.max_frames is None or i < self.max_frames:
                a = self._read()
                ok, img = a.ok, a.image
                if not ok and not self.live:
                    count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
                    if count <= 0 or i >= count:
                        if i == 0:
                            raise SourceError(f"{self.spec}: no frame of the video can be read")
                        return  # the file has ended
                    # a frame the container has but the decoder cannot read: a row of its
                    # own, and the next frames keep their own index and time
                    failed += 1
                    if failed > MAX_UNREADABLE_IN_A_ROW:
                        _log.warning(
                            "%s: frames %d to %d of %d cannot be read (the file is damaged or "
                            "cut short); the run ends there",
                            self.spec, i - failed + 1, count - 1, count,
                        )  # fmt: skip
                        return
                    yield Frame(i, i / self.fps, None, f"{self.spec}#{i}",
                                error=f"frame {i} of the video cannot be decoded")  # fmt: skip
                    i += 1
                    self.cap.set(cv2.CAP_PROP_POS_FRAMES, float(i))
                    continue
                if not ok:
                    count = self.cap.get(cv2.CAP_PROP_FRAME_COUNT)
                    if count and count > 0 and i >= count:
                        return  # a stream of known length has ended
                    a = self._retry()
                    img = a.image
                failed = 0
                # a live frame's time is when its reader read it (time.monotonic()),
                # not when it was taken here
                now = a.t
                self._last_frame_at = now
                if self._t0 is None:
                    self._t0 = now
                    # the computer's clock at the first frame: a live frame's absolute
                    # time is this plus its time from the first
                    self._unix0 = time.time() - (time.monotonic() - now)
                unix = None
                late = None
                if self.live:
                    # frames its reader read and this loop did not take (it fell behind):
                    # no rows, as a camera's driver drops them, but their numbers
                    passed = max(a.n - self._next_n, 0)
                    i += passed
                    self.dropped += passed
                    self._next_n = a.n + 1
                    t = self._live_time(now - self._t0, a.ms)
                    unix = self._unix0 + t
                    # a time that is when the frame was read, and the frame had waited
                    late = a.late if self._read_time else None
                else:
                    ms = a.ms  # (read with the frame by _read)
                    t = ms / 1000.0 if ms and ms > 0 else i / self.fps
                    # the container's own frame number: frames the decoder skipped
                    # silently are rows of their own, not shifted onto the next one's
                    k = int(round(t * self.fps)) if ms and ms > 0 else i
                    while i < k and (self.max_frames is None or i < self.max_frames):
                        yield Frame(i, i / self.fps, None, f"{self.spec}#{i}",
                                    error=f"frame {i} of the video was skipped by the "
                                    "decoder")  # fmt: skip
                        i += 1
                if img is None or img.size == 0:
                    yield Frame(i, t, None, f"{self.spec}#{i}", error="empty frame",
                                time_unix=unix)  # fmt: skip
                else:
                    if self.size is not None:
                        self._check_size(img)
                    yield Frame(i, t, to_gray(img), f"{self.spec}#{i}", time_unix=unix,
                                codec=self.codec, read_late=late)  # fmt: skip
                i += 1
        finally:
            self.cap.release()

    def _iter_avi(self) -> Iterator[Frame]:
        """A Motion-JPEG AVI's frames by its index: frame i at i / fps; one that cannot
        be decoded a read error of its own; without an index, the frames after a chunk
        that broke off are not placed, and the run ends there, said."""
        avi = self._avi
        self.cap.release()
        n = len(avi) if self.max_frames is None else min(len(avi), self.max_frames)
        if n == 0:
            raise SourceError(f"{self.spec}: no frame of the video can be read")
        failed = 0
        with open(avi.path, "rb") as fh:
            for i in range(n):
                img = avi.image(i, fh)
                if img is None:
                    failed += 1
                    if i == n - 1 and failed == n:
                        raise SourceError(f"{self.spec}: no frame of the video can be read")
                    yield Frame(i, i / avi.fps, None, f"{self.spec}#{i}",
                                error=f"frame {i} of the video cannot be decoded")  # fmt: skip
                    continue
                if self.size is not None:
                    self._check_size(img)
                yield Frame(i, i / avi.fps, to_gray(img), f"{self.spec}#{i}",
                            codec=self.codec)  # fmt: skip
        if avi.cut:
            # cut short: the frames the header counts beyond the data, each a row
            for i in range(n, avi.total if self.max_frames is None else
                           min(avi.total, self.max_frames)):  # fmt: skip
                yield Frame(
                    i,
                    i / avi.fps,
                    None,
                    f"{self.spec}#{i}",
                    error=f"frame {i} of the video is not in the file (cut short)",
                )
        elif avi.lost_from is not None and (self.max_frames is None or avi.lost_from < n):
            _log.warning(
                "%s: the file has no index and its data break off after frame %d: the "
                "frames after it (%d by its header) cannot be placed; the run ends there",
                self.spec, avi.lost_from - 1, avi.total,
            )  # fmt: skip
        elif len(avi) < avi.total and self.max_frames is None and avi.lost_from is None:
            _log.warning("%s: %d of the %d frames its header counts are in the file (cut "
                         "short?)", self.spec, len(avi), avi.total)  # fmt: skip

    def _read(self) -> Arrival:
        """The next frame: a live source's newest from its reader (stamped when it was
        read there), a file's read now."""
        if isinstance(self.cap, LiveReader):
            return self.cap.take()
        ok, img = self.cap.read()
        t = time.monotonic()
        return Arrival(ok, img, t, self.cap.get(cv2.CAP_PROP_POS_MSEC) if ok else 0.0)

    def _live_time(self, t_read: float, ms: float) -> float:
        """A live frame's time (s from the first frame): the source's own timestamp
        ``ms`` (the driver's capture time, not when the frame was read, which lags by
        up to a frame) once it has kept time with our clock for SOURCE_CLOCK_TRIAL_S
        (to SOURCE_RATE_TOLERANCE) and while it stays positive, increasing and within
        SOURCE_CLOCK_TOLERANCE_S of ours; the read time ``t_read`` during the trial and,
        from the first frame whose timestamp fails (a backend without timestamps gives
        0), for the rest of the run. ``self._read_time`` says which it was.

        The source's elapsed time is put on our clock by a tie (visvec.clocks.ClockTie:
        the frame of the last 10 s read soonest after its timestamp), set at the trial's
        end and then moved towards the tie by at most SOURCE_SLEW a second: a camera
        whose crystal runs 50 ppm off ours put its frames 0.18 s off an hour into a run,
        then (at 0.5 s, after 3 hours) was dropped for the read times."""
        self._read_time = True
        if self.clock != "source":
            return t_read
        ts = ms / 1000.0 if ms and ms > 0 else None
        if self._src is None and ms == 0.0:
            ts = 0.0  # a first timestamp may be 0 (a stream's clock starts there)
        if ts is not None and self._src is None:
            # the first frame, or the first after a reopen (a stream's clock restarts):
            # a new trial
            self._src = (ts, ts)
            self._src_t0 = t_read
            self._tie = ClockTie()
            self._tie.add(t_read, t_read)
            self._trial = [(t_read, 0.0)]
            return t_read
        if ts is not None and ts > self._src[1]:
            base = self._src_t0 + ts - self._src[0]
            self._tie.add(t_read, base)
            self._src = (self._src[0], ts)
            if self._trial is not None and abs(base - t_read) < SOURCE_CLOCK_TOLERANCE_S:
                self._trial.append((t_read, t_read - base))
                if t_read - self._src_t0 < SOURCE_CLOCK_TRIAL_S:
                    return t_read
                fast = _rate_off(self._trial)
                self._trial = None
                if abs(fast) <= SOURCE_RATE_TOLERANCE:
                    self._src_off, self._src_read = self._tie.offset, t_read
                    self._read_time = False
                    return base + self._src_off
                _log.warning(
                    "%s: the source's frame timestamps do not keep time (%.1f %% %s "
                    "than this computer's clock); frames are timed when they are read",
                    self.spec, 100 * abs(fast), "faster" if fast > 0 else "slower",
                )  # fmt: skip
                self.clock = "read"
                return t_read
            if self._trial is None:
                slew = SOURCE_SLEW * max(t_read - self._src_read, 0.0)
                self._src_off += min(max(self._tie.offset - self._src_off, -slew), slew)
                self._src_read = t_read
                t = base + self._src_off
                if abs(t - t_read) < SOURCE_CLOCK_TOLERANCE_S:
                    self._read_time = False
                    return t
        if self._src is not None and self._src[1] > 0:  # (not: never any but 0)
            _log.warning(
                "%s: the source's frame timestamps stopped making sense at %.3f s; times "
                "are now those at which frames are read",
                self.spec,
                t_read,
            )
        self.clock = "read"
        return t_read

    def _check_size(self, img) -> None:
        """The first good frame of a camera asked for ``size``: refuse another size."""
        w, h = self.size
        if img.shape[:2] != (h, w):
            raise SourceError(
                f"camera {self.spec}: delivers {img.shape[1]}x{img.shape[0]} frames, not the "
                f"rig's {w}x{h} (it has no such mode); calibrate the camera at "
                f"{img.shape[1]}x{img.shape[0]} (visvec calibrate camera) and use that "
                f"[camera] section"
            )
        self.size = None  # checked once

    def _retry(self) -> Arrival:
        """The next frame of a live source that failed to deliver one: read again, and
        every REOPEN_EVERY_S close and open it again, until ``retry_s`` has passed."""
        start = time.monotonic()
        # a stream's read has already waited STREAM_STALL_S: opened again at once
        reopen_at = start if self.stream else start + REOPEN_EVERY_S
        n = 0
        while time.monotonic() < start + self.retry_s:
            time.sleep(0.05)
            if time.monotonic() >= reopen_at:
                reopen_at = time.monotonic() + REOPEN_EVERY_S
                self.cap.release()
                left = start + self.retry_s - time.monotonic()
                self.cap = self._open(max(left, 0.1) if self.stream else None)
                self.reopened += 1
                self._src = None  # a new capture's timestamps start again
                self._next_n = 0
                n += 1
                if n == 1:  # once per outage: the final error, if any, says how often
                    since = start if self._last_frame_at is None else self._last_frame_at
                    _log.warning(
                        "%s: no frame for %.1f s; opening it again",
                        self.spec,
                        time.monotonic() - since,
                    )
                # a new capture may come in another mode (checked on its first frame)
                self.size = self._mode[0]
            if self.cap.isOpened():
                a = self._read()
                if a.ok:
                    self.codec = codec_of(self.cap)
                    return a
        what = "stream" if self.stream else "camera"
        raise SourceError(
            f"{self.spec}: the {what} stopped delivering frames (retried for {self.retry_s:g} s, "
            f"opened again {n} times)"
        )
