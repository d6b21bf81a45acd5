"""Live fusion: UDP, standard input, a followed file, a serial device; signals end a run
with every row."""

import csv
import math

import numpy as np
import pytest
from click.testing import CliRunner
from fusion_cases import (
    _free_udp_port,
    _send_paced,
    planar_case,
    truth_table,
)

from visvec.cli.main import cli
from visvec.output import PLANAR_COLUMNS

from conftest import Stderr, data_rows, wait_until


@pytest.mark.slow  # 5 s of real time
def test_fuse_live_over_udp_in_real_time(tmp_path):
    """IMU samples sent at 100 Hz in real time and fixes as they become available, both
    over UDP on 127.0.0.1: the rows come out as the samples arrive, within 5 mm of the
    truth once fixes are in, and a malformed datagram is counted, not fatal."""
    import socket
    import subprocess
    import sys
    import time

    imu, truth, fixes = planar_case(tmp_path, duration=4.0, fix_hz=2.0)
    p_imu, p_fix = _free_udp_port(), _free_udp_port()
    out = tmp_path / "live.csv"
    n = 400
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "fuse", "--imu", f"udp://127.0.0.1:{p_imu}",
         "--fixes", f"udp://127.0.0.1:{p_fix}", "--out", str(out), "--max-samples", str(n)],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        seen = 0
        deadline = time.monotonic() + 30
        while seen < 2 and time.monotonic() < deadline:
            line = proc.stderr.readline()
            seen += "listening" in line
        assert seen == 2
        imu_lines = imu.read_text().splitlines()
        fix_lines = fixes.read_text().splitlines()
        fix_rows = [(float(r.split(",")[1]) + 0.6, r) for r in fix_lines[1:]]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(imu_lines[0].encode(), ("127.0.0.1", p_imu))
            s.sendto(fix_lines[0].encode(), ("127.0.0.1", p_fix))
            s.sendto(b"garbage,,", ("127.0.0.1", p_fix))
            _send_paced(s, imu_lines[1 : n + 1], p_imu, time.monotonic(), fix_rows, p_fix)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == n
    assert "1 malformed fix rows skipped" in err and "row latency median" in err
    assert "learned: fixes' time offset" in err
    tt = truth_table(truth)
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) > n / 2
    k = [int(float(r["time_s"]) * 100 + 0.5) for r in ok]
    e = [math.hypot(float(r["x_mm"]) - tt[i, 0], float(r["y_mm"]) - tt[i, 1])
         for r, i in zip(ok, k, strict=True)]  # fmt: skip
    assert np.sqrt(np.mean(np.square(e))) < 5.0


def test_fuse_live_from_stdin_matches_the_file_replay(tmp_path):
    """The IMU piped in on standard input (at 10x its real rate, from a driver, say) and
    a followed fixes file give the rows of the file replay: the live path holds each
    fix until the IMU's clock reaches its exposure plus latency_ms."""
    import subprocess
    import sys

    imu, _, fixes = planar_case(tmp_path, duration=6.0)
    ref = tmp_path / "ref.csv"
    live = tmp_path / "live.csv"
    r = CliRunner().invoke(cli, ["fuse", "--imu", str(imu), "--fixes", str(fixes),
                                 "--out", str(ref)])  # fmt: skip
    assert r.exit_code == 0, r.output
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "fuse", "--imu", "-", "--fixes", str(fixes), "--follow",
         "--out", str(live)], stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        # said once the fixes file's rows are in: the IMU then comes as from a device
        while "lines read, following" not in proc.stderr.readline():
            pass
        lines = imu.read_text().splitlines(keepends=True)
        for line in lines:
            proc.stdin.write(line)
            proc.stdin.flush()
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    with open(ref) as a, open(live) as b:
        ra, rb = list(csv.DictReader(a)), list(csv.DictReader(b))
    assert len(ra) == len(rb) > 500
    assert sum(x["status"] == "ok" for x in ra) > 400
    for x, y in zip(ra, rb, strict=True):
        assert x["status"] == y["status"]
        if x["status"] == "ok":
            assert abs(float(x["x_mm"]) - float(y["x_mm"])) < 1e-6


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_fuse_live_ends_on_a_signal_with_every_row_and_the_summary(tmp_path, sig):
    """A live run stopped by SIGTERM, SIGHUP or SIGINT: exit 0, the summary on stderr,
    every row written whole; a sample whose clock steps back is refused, not fused."""
    import signal
    import socket
    import subprocess
    import sys

    imu, _, fixes = planar_case(tmp_path, duration=3.0)
    p_imu, p_fix = _free_udp_port(), _free_udp_port()
    out = tmp_path / "live.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "fuse", "--imu", f"udp://127.0.0.1:{p_imu}",
         "--fixes", f"udp://127.0.0.1:{p_fix}", "--out", str(out)],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    err = Stderr(proc)
    try:
        err.wait_for("listening", times=2)
        lines = imu.read_text().splitlines()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(lines[0].encode(), ("127.0.0.1", p_imu))
            for line in [*lines[1:101], lines[50]]:  # the last one steps back in time
                s.sendto(line.encode(), ("127.0.0.1", p_imu))
        wait_until(lambda: data_rows(out) >= 101, "the 101 rows written")
        proc.send_signal(getattr(signal, sig))
        proc.wait(timeout=20)
    finally:
        proc.kill()
    err = err.rest()
    assert proc.returncode == 0, err
    assert "stopped early (Ctrl-C or a signal)" in err and "101 inertial samples" in err
    text = out.read_text()
    assert text.endswith("\n")
    rows = list(csv.DictReader(text.splitlines()))
    assert len(rows) == 101 and all(len(r) == len(PLANAR_COLUMNS) for r in rows)
    assert rows[-1]["warnings"] == "imu_time_back"


def _serial_fuse(tmp_path, *extra):
    """`fuse` reading IMU rows from a pseudo-terminal (standing in for /dev/ttyUSB0):
    (process, IMU file, pty master fd, slave fd, rows file)."""
    import os
    import subprocess
    import sys

    pytest.importorskip("serial")
    imu, _, fixes = planar_case(tmp_path, duration=2.0)
    master, slave = os.openpty()
    out = tmp_path / "serial.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "fuse", "--imu",
         f"serial://{os.ttyname(slave)}?baud=115200", "--fixes", str(fixes), "--follow",
         "--out", str(out), *extra], stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    return proc, imu, master, slave, out


def test_fuse_live_from_a_serial_device(tmp_path):
    """IMU rows on a serial line (a pseudo-terminal standing in for /dev/ttyUSB0),
    read through pyserial: fused as they come."""
    import os

    proc, imu, master, slave, out = _serial_fuse(tmp_path, "--max-samples", "150")
    err = Stderr(proc)
    try:
        err.wait_for("open at 115200 baud")
        for line in imu.read_text().splitlines()[:160]:
            os.write(master, (line + "\n").encode())
        proc.wait(timeout=20)
    finally:
        proc.kill()
        os.close(master)
        os.close(slave)
    err = err.rest()
    assert proc.returncode == 0, err
    with open(out) as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 150 and sum(r["status"] == "ok" for r in rows) > 50


def test_a_serial_device_that_disappears_is_retried(tmp_path):
    """The serial line goes away mid-run: said on stderr and retried every second, the
    run goes on (and ends on a signal with its rows)."""
    import os
    import signal

    proc, imu, master, slave, out = _serial_fuse(tmp_path)
    err = Stderr(proc)
    try:
        err.wait_for("open at 115200 baud")
        for line in imu.read_text().splitlines()[:40]:  # the header and 39 samples
            os.write(master, (line + "\n").encode())
        wait_until(lambda: data_rows(out) >= 39, "the 39 rows written")
        os.close(master)
        os.close(slave)
        err.wait_for("retrying every 1 s", times=2)  # lost, then not there: tried again
        assert proc.poll() is None  # still running, retrying
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    finally:
        proc.kill()
    err = err.rest()
    assert proc.returncode == 0, err
    assert "lost (" in err
    assert len(list(csv.DictReader(open(out)))) == 39


def test_the_rows_latency_tally_is_bounded_and_reads_the_median():
    """A live run's latencies are tallied in a fixed histogram, not kept row by row (a
    run of hours): its median within half a bin (0.3 %) of the rows' own, from any
    spread of values; values below and above its range counted at its bounds."""
    from visvec.fuse.live import LATENCY_HI_MS, LATENCY_LO_MS, LatencyTally

    rng = np.random.default_rng(3)
    for scale, spread in ((0.6, 0.3), (12.0, 1.5), (0.004, 0.1)):
        tally = LatencyTally()
        size = tally.counts.nbytes
        ms = scale * np.exp(spread * rng.standard_normal(20_001))
        for v in ms:
            tally.add(float(v))
        assert len(tally) == len(ms) and tally.counts.nbytes == size
        exact = np.sort(ms)[len(ms) // 2]  # the median the summary line gave before
        assert tally.median() == pytest.approx(exact, rel=0.003)
    low, high = LatencyTally(), LatencyTally()
    for v in (0.0, -1.0, 1e-9):
        low.add(v)
    high.add(1e9)
    assert low.median() == LATENCY_LO_MS and high.median() == LATENCY_HI_MS
    assert math.isnan(LatencyTally().median())


def test_the_imu_clock_is_tied_to_the_hosts_through_an_hour_of_drift():
    """An hour of 100 Hz samples from an IMU whose clock runs 50 ppm slow or fast (a
    free-running crystal) or steps back (the IMU restarted), arriving 0.2-3 ms after
    their time: the tie (host minus IMU time, by which the camera's fixes are put on the
    IMU's clock) stays within 1 ms of the fastest arrival's, where the least over the
    whole run fell 0.18 s behind the slow clock."""
    from visvec.clocks import CLOCK_WINDOW_S, ClockTie

    rng = np.random.default_rng(5)
    host = np.arange(0.0, 3600.0, 0.01)
    delay = 0.0002 + rng.exponential(0.001, len(host))
    for ppm in (50.0, -50.0):
        imu_t = 100.0 + host * (1.0 - ppm * 1e-6)
        tie, least = ClockTie(), math.inf
        for h, t, d in zip(host, imu_t, delay, strict=True):
            tie.add(h + d, t)
            least = min(least, h + d - t)
        truth = host[-1] - imu_t[-1] + 0.0002  # the fastest possible arrival's
        assert abs(tie.offset - truth) < 1e-3 + abs(ppm) * 1e-6 * CLOCK_WINDOW_S
        if ppm > 0:
            assert truth - least > 0.17  # the least over the run: 0.18 s behind
    # the IMU restarts its clock: the new tie after one window
    tie = ClockTie()
    for h in np.arange(0.0, 30.0, 0.01):
        tie.add(h + 0.001, h if h < 15.0 else h - 15.0)
    assert tie.offset == pytest.approx(15.001)
