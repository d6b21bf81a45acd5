"""Live fusion in one process: `visvec track --imu` on a lamps recording played as a
camera at its own pace (640x480, 30 fps, the lamp pipeline on every frame) while this
script sends the matching IMU samples (100 Hz, planar) over UDP on 127.0.0.1 in real
time and receives the fused rows over UDP (`--out udp://...`).

Row latency is measured end to end, outside the sensor: from the moment a sample is
sent to the moment its fused row is received (so it includes the loopback, the
reader thread, the queue and the row's encoding); the sensor's own figure (from the
sample's arrival) is in its summary line. The sensor runs pinned to one core
(`taskset -c 0`) with the camera's processing on the same core. Accuracy: the fused
rows against the simulation's truth at every IMU sample.

    python benchmarks/fusion_live.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import csv
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import CONFIGS, UdpRows, free_udp_port, run_record, save_json


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    rig = CONFIGS / "lamps.toml"
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "rec"
        n_frames = int(args.seconds * 30)
        subprocess.run([sys.executable, "-m", "visvec", "simulate", "--rig", str(rig), "--out",
                        str(rec), "--frames", str(n_frames), "--motion", "perimeter", "--imu"],
                       check=True, capture_output=True)  # fmt: skip
        p_imu = free_udp_port()
        received: dict[int, tuple[float, list[str]]] = {}
        rx = UdpRows(lambda now, fields: received.__setitem__(int(fields[0]), (now, fields)))
        p_out = rx.port
        taskset = ["taskset", "-c", "0"] if shutil.which("taskset") else []
        cmd = [*taskset, sys.executable, "-m", "visvec", "track", "--rig", str(rig), "--camera",
               str(rec), "--realtime", "--imu", f"udp://127.0.0.1:{p_imu}", "--out",
               f"udp://127.0.0.1:{p_out}"]  # fmt: skip
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
        got: set[str] = set()
        while len(got) < 2:
            line = proc.stderr.readline()
            if not line:
                sys.exit("the sensor stopped before it started")
            got |= {w for w in ("listening", "first frame") if w in line}
        lines = (rec / "imu.csv").read_text().splitlines()
        sent: dict[int, float] = {}
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            t0 = time.monotonic()
            s.sendto(lines[0].encode(), ("127.0.0.1", p_imu))
            for k, line in enumerate(lines[1:]):
                wait = t0 + float(line.split(",")[0]) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                sent[k] = time.monotonic()
                s.sendto(line.encode(), ("127.0.0.1", p_imu))
        _, err = proc.communicate(timeout=60)
        time.sleep(0.3)
        rx.close()
        truth = np.array([[float(r["x_mm"]), float(r["y_mm"])]
                          for r in csv.DictReader(open(rec / "imu_truth.csv"))])  # fmt: skip
    lat = np.array([(received[k][0] - sent[k]) * 1000.0 for k in sent if k in received])
    col = rx.col
    ok = [f for _, f in received.values() if f[col["status"]] == "ok"]
    # the filter's own rows (the accuracy target) and the provisional ones before the
    # clocks are aligned (warned aligning_clocks: judged by their sigma)
    own = [f for f in ok if "aligning_clocks" not in f[col["warnings"]]]
    prov = [f for f in ok if "aligning_clocks" in f[col["warnings"]]]
    e = np.array([np.hypot(float(f[col["x_mm"]]) - truth[int(f[0]), 0],
                           float(f[col["y_mm"]]) - truth[int(f[0]), 1]) for f in own])  # fmt: skip
    zp = np.array([max(abs(float(f[col[f"{a}_mm"]]) - truth[int(f[0]), k])
                       / float(f[col[f"sigma_{a}_mm"]]) for k, a in enumerate("xy"))
                   for f in prov]) if prov else np.zeros(0)  # fmt: skip
    result = {
        **run_record(),
        "seconds": args.seconds,
        "frames": n_frames,
        "imu_samples": len(sent),
        "rows_received": len(received),
        "ok_rows": len(ok),
        "one_core": bool(taskset),
        "latency_ms": {
            "median": float(np.median(lat)),
            "p90": float(np.percentile(lat, 90)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
        },
        "position_rms_mm": float(np.sqrt(np.mean(e**2))),
        "position_max_mm": float(e.max()),
        "provisional_rows": len(prov),
        "provisional_largest_error_over_sigma": float(zp.max()) if len(zp) else None,
        # the sensor's closing lines: its summary (with its own latency figure) and
        # what the filter learned
        "sensor_summary": [
            ln for ln in err.strip().splitlines() if "inertial samples" in ln or "learned:" in ln
        ],  # fmt: skip
    }
    save_json("fusion_live", result)
    print(result)


if __name__ == "__main__":
    main()
