"""A live stream read in a thread of its own (visvec.sources.reader): frames stamped
when they arrive, the newest handed out, and a frame that waited in a queue (the reader
itself held up) said to be late, as is the one read when the hold-up ended."""

from __future__ import annotations

import time

import numpy as np

from visvec.sources.reader import PERIOD_FRAMES, LiveReader

PERIOD = 0.02  # a 50 fps stream


class Stream:
    """Frames that arrive every PERIOD from the first read; a read returns the next
    frame at once if it has arrived, else when it does. Frame ``hold`` is read
    ``hold_s`` after it arrived (the reader's thread not scheduled), so the frames that
    arrive meanwhile wait in the queue."""

    def __init__(self, n: int, hold: int, hold_s: float):
        self.n, self.hold, self.hold_s = n, hold, hold_s
        self.k, self.t0 = 0, None

    def read(self):
        if self.k >= self.n:
            return False, None
        if self.t0 is None:
            self.t0 = time.monotonic()
        due = self.t0 + self.k * PERIOD + (self.hold_s if self.k == self.hold else 0.0)
        time.sleep(max(due - time.monotonic(), 0.0))
        self.k += 1
        return True, np.full((2, 2), self.k - 1, np.uint8)

    def get(self, prop):
        return 0.0

    def release(self):
        pass


def test_queued_frames_are_late_and_the_newest_is_handed_out():
    hold = PERIOD_FRAMES + 10
    reader = LiveReader(Stream(60, hold=hold, hold_s=0.15))
    taken = []
    while True:
        a = reader.take(timeout_s=2.0)
        if not a.ok:
            break
        taken.append(a)
        time.sleep(0.001)
    reader.release()
    n = [a.n for a in taken]
    assert n == sorted(set(n)) and n[-1] == 59  # in order, each once, to the last
    assert [int(a.image[0, 0]) for a in taken] == n  # the frames' own numbers
    late = {a.n for a in taken if a.late.is_set()}
    # the first frames, before the stream's period is known, are taken as queued
    first = set(range(PERIOD_FRAMES + 1))
    assert first & set(n) <= late
    # the frame held up and those that queued behind it (7 frames arrived in 0.15 s)
    queued = set(range(hold, hold + 8)) & set(n)
    assert queued and queued <= late
    # and no other, but for the next, which came 10 ms after the queue was read: less
    # than half the period (lowered by the burst) after it, so taken as queued too
    assert late - first - queued <= {hold + 8}
    # the times are the arrivals: PERIOD apart where the reader kept up
    t = {a.n: a.t for a in taken}
    steady = [t[k + 1] - t[k] for k in range(PERIOD_FRAMES, hold - 1) if k in t and k + 1 in t]
    assert steady and abs(np.median(steady) - PERIOD) < 0.004


def test_frames_not_taken_are_dropped_and_counted():
    reader = LiveReader(Stream(30, hold=-1, hold_s=0.0))
    first = reader.take()
    time.sleep(10 * PERIOD)  # a slow consumer: ten frames come meanwhile
    second = reader.take()
    reader.release()
    assert first.ok and second.ok
    # the newest frame, not the next one
    assert 9 <= second.n - first.n <= 11 and reader.dropped == second.n - first.n - 1
