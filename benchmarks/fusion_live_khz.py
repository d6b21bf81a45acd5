"""Live 3-D fusion of a 1 kHz IMU: `visvec fuse` reading the IMU and the fixes as UDP
streams in real time, its rows sent back over UDP, pinned to one core.

The stream is a real one made faster: BROAD trial 06 (Laidig et al. 2021, fast
rotation up to 925 deg/s, a 286 Hz gyro) resampled to 1 kHz (the gyro linearly, the
optical truth by slerp); fixes as in fusion_recordings.py (the truth at 2 Hz, 0.1 deg
noise, sent 0.6 s after their exposure: each one replays 600 stored samples). This
script sends both streams at their own pace from another core and receives the rows.

Latency: the sensor's own figure (from a sample's arrival to its row leaving, its
summary line: the target, 1 ms median) and, measured outside, from a sample's send to
its row's arrival (the loopback, the reader thread and the row's encoding included).

    python benchmarks/fusion_live_khz.py [--seconds 30]
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from fusion_recordings import write_inputs
from scipy.spatial.transform import Rotation, Slerp

from visvec.bench.recordings import load, shared_recordings

from _common import ROOT, UdpRows, free_udp_port, run_record, save_json

DATA = ROOT.parent / "shared" / "data"
HZ = 1000.0
TRIAL = "06_undisturbed_fast_rotation_A"
START_S = 20.0  # into the trial: past its rest, into the rotation


def stream(seconds: float, tmp: Path) -> tuple[list[tuple[float, str, bytes]], int]:
    """The datagrams to send, (time from the start, 'imu' or 'fix', line) in time
    order, the headers first; and the number of IMU samples."""
    found = [(d, p) for d, p in shared_recordings(DATA) if p.stem == TRIAL]
    if not found:
        sys.exit(f"{TRIAL}: not among the shared recordings under {DATA}")
    rec = load(*found[0])
    t = np.arange(0.0, seconds, 1.0 / HZ) + rec.t[0] + START_S
    gyro = np.stack([np.interp(t, rec.t, rec.gyro[:, k]) for k in range(3)], axis=1)
    ok = rec.truth_ok & np.isfinite(rec.R).all(axis=(1, 2))
    R = Slerp(rec.t[ok], Rotation.from_matrix(rec.R[ok]))(t).as_matrix()
    near = np.interp(t, rec.t, rec.truth_ok.astype(float)) > 0.999
    write_inputs(tmp, t - t[0], gyro, R, np.random.default_rng(0), near)
    out: list[tuple[float, str, bytes]] = []
    lines = (tmp / "imu.csv").read_text().splitlines()
    out.append((-1.0, "imu", lines[0].encode()))  # the headers first
    out += [(float(ln.split(",")[0]), "imu", ln.encode()) for ln in lines[1:]]
    rows = list(csv.reader((tmp / "fixes.csv").read_text().splitlines()))
    out.append((-1.0, "fix", ",".join(rows[0]).encode()))
    for r in rows[1:]:
        # available (sent) at its exposure plus its latency
        out.append((float(r[1]) + float(r[15]) / 1000.0, "fix", ",".join(r).encode()))
    out.sort(key=lambda x: (x[0], x[1] != "imu"))
    return out, len(lines) - 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        plan, n_imu = stream(args.seconds, Path(tmp))
    received: dict[int, float] = {}
    rx = UdpRows(lambda now, fields: received.__setitem__(int(fields[0]), now))
    p_imu, p_fix = free_udp_port(), free_udp_port()
    taskset = ["taskset", "-c", "0"] if shutil.which("taskset") else []
    cmd = [*taskset, sys.executable, "-m", "visvec", "fuse", "--imu",
           f"udp://127.0.0.1:{p_imu}", "--fixes", f"udp://127.0.0.1:{p_fix}", "--out",
           f"udp://127.0.0.1:{rx.port}", "--max-samples", str(n_imu)]  # fmt: skip
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    listening = 0
    while listening < 2:  # both readers bound
        line = proc.stderr.readline()
        if not line:
            sys.exit("the sensor stopped before it started")
        listening += "listening" in line
    time.sleep(0.5)
    if hasattr(os, "sched_setaffinity") and (os.cpu_count() or 1) > 1:
        os.sched_setaffinity(0, {1})  # the sender off the sensor's core
    sent: list[float] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        ports = {"imu": p_imu, "fix": p_fix}
        t0 = time.monotonic()
        for at, kind, data in plan:
            while (wait := t0 + at - time.monotonic()) > 0:
                if wait > 0.0003:
                    time.sleep(wait - 0.0002)
            if kind == "imu" and not data.startswith(b"time_s"):
                sent.append(time.monotonic())
            s.sendto(data, ("127.0.0.1", ports[kind]))
        late = time.monotonic() - t0 - plan[-1][0]
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:  # a sample lost on the way: the run ends by Ctrl-C
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    time.sleep(0.3)
    rx.close()
    if not received:
        sys.exit(f"no rows came back; the sensor said:\n{err}")
    lat = np.array([(received[k] - sent[k]) * 1000.0 for k in range(len(sent)) if k in received])
    own = re.search(r"row latency median ([0-9.]+) ms", err)
    result = {
        **run_record(),
        "trial": TRIAL,
        "imu_hz": HZ,
        "seconds": args.seconds,
        "imu_samples_sent": len(sent),
        "rows_received": len(received),
        "sender_behind_s": late,
        "one_core": bool(taskset),
        "sensor_latency_median_ms": float(own.group(1)) if own else None,
        "latency_ms_send_to_row": {
            "median": float(np.median(lat)),
            "p90": float(np.percentile(lat, 90)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
        },
        "sensor_summary": [
            ln for ln in err.strip().splitlines() if "inertial samples" in ln or "learned:" in ln
        ],  # fmt: skip
    }
    save_json("fusion_live_khz", result)
    print(result)


if __name__ == "__main__":
    main()
