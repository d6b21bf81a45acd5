"""A long live run: `visvec track --imu --serve` left running as a lab leaves it, fed by
a network camera and a live IMU, its page open, watched from outside for what drifts.

The camera: an MJPEG stream served by this script on 127.0.0.1 (JPEG quality 95) of a
640x480 lamps ceiling (configs/lamps.toml) at 30 fps, the mock-up pushed around the
table on a lap of 66 s (PerimeterPath: 66 s holds whole periods of its pushes and its
sway, so the lap's frames, rendered once, loop without a seam). The IMU: 100 Hz planar
samples (gyro and accelerometers with the simulator's biases, noise and faults)
computed from the same path for every instant, sent over UDP in real time, stamped by
the IMU's own clock, which runs 50 ppm slow (`--imu-ppm`; a free-running crystal). The fused
rows come back over UDP (`--out udp://...`); the camera's own rows go to a file
(`--camera-out`); a client on the other core fetches what the live page fetches, as
often, and everything again once a minute (a page reloaded). The sensor is pinned to
core 0.

Watched per window (default 5 minutes): the fused rows' rate, their latency from a
sample's send to its row's arrival, the ok share, the position and heading errors
against the path; the sensor's resident memory, threads, open files and CPU share
(from /proc). Target: nothing grows or slows with the hours: memory after the first
window within 10 % of its level then, and each window's latency median and row rate
within 10 % of the first window's; no wrong ok row (10 mm or 0.5 deg off, or beyond 5
of its own sigma on an axis).

With `--busy N`, N busy processes share the sensor's core for the whole run (a starved
processor, as when the platform's computer runs other work): the wrong-row count is the
figure that matters there (a frame that waited before it was read must not become a fix
of the wrong moment), with the camera's rows warned `read_late` and the frames passed
over beside it.

    python benchmarks/live_soak.py [--minutes 60] [--window-min 5] [--busy N]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np

from visvec.rig import load_rig
from visvec.sim.lamps import ImuModel, LampScene, PerimeterPath, render_lamps

from _common import CONFIGS, UdpRows, free_udp_port, run_record, save_json

RIG = CONFIGS / "lamps.toml"
FPS, IMU_HZ, LAP_S = 30.0, 100.0, 66.0
PATH = PerimeterPath(lap_s=LAP_S)
WRONG_MM, WRONG_DEG = 10.0, 0.5
SIGMAS = ("sigma_x_mm", "sigma_y_mm", "sigma_heading_deg")


# a client that fetches what the page fetches, as often: the frame every 100 ms, the
# rows since the last it had every 250 ms, and everything again every RELOAD_S (a page
# reloaded, a second browser opened)
PAGE = """
import json, sys, time, urllib.request
url, reload_s = sys.argv[1], float(sys.argv[2])
seq, last_state, last_reload = 0, 0.0, time.monotonic()
while True:
    try:
        urllib.request.urlopen(url + "frame.jpg", timeout=5).read()
        now = time.monotonic()
        if now - last_reload > reload_s:
            seq, last_reload = 0, now
        if now - last_state > 0.25:
            with urllib.request.urlopen(url + f"api/state?since={seq}", timeout=5) as r:
                st = json.loads(r.read())
            seq, last_state = st["seq"], now
    except OSError:
        pass
    time.sleep(0.1)
"""
RELOAD_S = 60.0
# the IMU's clock runs this much slower than the host's (ppm): a free-running crystal
# (tens of ppm; 50 ppm is 0.18 s an hour)
IMU_PPM = 50.0


def _render(i: int) -> bytes:
    """Frame i of the lap as a JPEG (its own noise seed)."""
    rig = load_rig(RIG)
    scene = LampScene(exposure_ms=rig.exposure_ms or LampScene.exposure_ms)
    img = render_lamps(rig, PATH.at, i / FPS, scene, np.random.default_rng(1000 + i))
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def render_lap() -> list[bytes]:
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as ex:
        return list(ex.map(_render, range(int(LAP_S * FPS)), chunksize=20))


class Camera:
    """The MJPEG stream: frame i (of the lap, looped) sent at t0 + i / FPS."""

    def __init__(self, jpegs: list[bytes], t0: float, stop: threading.Event):
        outer = self
        self.sent = 0

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=f")
                self.end_headers()
                i = int(np.ceil((time.monotonic() - t0) * FPS))
                try:
                    while not stop.is_set():
                        wait = t0 + i / FPS - time.monotonic()
                        if wait > 0:
                            time.sleep(wait)
                        b = jpegs[i % len(jpegs)]
                        head = f"--f\r\nContent-Type: image/jpeg\r\nContent-Length: {len(b)}"
                        self.wfile.write(head.encode() + b"\r\n\r\n" + b + b"\r\n")
                        outer.sent += 1
                        i += 1
                except OSError:
                    return

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()


def imu_samples(j0: int, n: int, rng: np.random.Generator, model: ImuModel) -> np.ndarray:
    """Samples j0 .. j0 + n - 1 (time_s = j / IMU_HZ): time, gz (deg/s), ax, ay (m/s^2),
    as visvec.sim.lamps.simulate_imu makes them, for any stretch of the endless run."""
    t = (j0 + np.arange(n)) / IMU_HZ
    vel, acc = PATH.derivatives(t)
    psi = PATH.at(t)[:, 2]
    c, s = np.cos(psi), np.sin(psi)
    ax = (c * acc[:, 0] + s * acc[:, 1]) / 1000.0
    ay = (-s * acc[:, 0] + c * acc[:, 1]) / 1000.0
    gz = np.degrees(vel[:, 2]) + model.gyro_bias_dps + rng.standard_normal(n) * model.gyro_noise_dps
    ax = ax + model.accel_bias_mps2[0] + rng.standard_normal(n) * model.accel_noise_mps2
    ay = ay + model.accel_bias_mps2[1] + rng.standard_normal(n) * model.accel_noise_mps2
    faults = rng.random(n) < model.fault_fraction
    sign = rng.choice([-1.0, 1.0], size=n)
    gz[faults] = sign[faults] * 50.0 * model.fault_size
    ax[faults] = -sign[faults] * 0.5 * model.fault_size
    return np.column_stack([t, gz, ax, ay])


def proc_stats(pid: int) -> dict | None:
    """Resident memory (MB), threads, open files and CPU seconds of a process."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1024.0
    threads = int(re.search(r"Threads:\s+(\d+)", status).group(1))
    cpu = (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")
    return {"rss_mb": rss, "threads": threads, "fds": fds, "cpu_s": cpu}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--window-min", type=float, default=5.0)
    ap.add_argument(
        "--imu-ppm",
        type=float,
        default=IMU_PPM,
        help="how much slower the IMU's clock runs than the host's (ppm)",
    )
    ap.add_argument(
        "--busy",
        type=int,
        default=0,
        help="busy processes on the sensor's core beside it (a starved processor: the "
        "sensor gets 1/(N+1) of its core)",
    )
    ap.add_argument(
        "--keep",
        type=Path,
        help="keep the camera's rows, the fused rows and the sensor's log in this folder",
    )
    args = ap.parse_args()
    taskset = shutil.which("taskset")
    rate = 1.0 - args.imu_ppm * 1e-6
    t_render = time.perf_counter()
    jpegs = render_lap()
    print(f"rendered {len(jpegs)} frames in {time.perf_counter() - t_render:.0f} s", flush=True)
    stop = threading.Event()
    t0 = time.monotonic() + 1.0
    cam = Camera(jpegs, t0, stop)
    p_imu = free_udp_port()
    # per sample index: when sent, when its row came, its status and pose
    n_max = int((args.minutes * 60 + 120) * IMU_HZ)
    sent = np.full(n_max, np.nan)
    got = np.full(n_max, np.nan)
    pose = np.full((n_max, 3), np.nan)
    sigma = np.full((n_max, 3), np.nan)  # the rows' own 1-sigma
    ok = np.zeros(n_max, bool)

    def on_row(now: float, f: list[str]) -> None:
        col = rx.col
        # the row's time is its sample's, on the IMU's clock: its index here
        k = int(round(float(f[col["time_s"]]) / rate * IMU_HZ))
        if 0 <= k < n_max:
            got[k] = now
            ok[k] = f[col["status"]] == "ok"
            if ok[k]:
                pose[k] = [float(f[col[c]]) for c in ("x_mm", "y_mm", "heading_deg")]
                sigma[k] = [float(f[col[c]]) for c in SIGMAS]

    rx = UdpRows(on_row)
    p_out = rx.port
    with tempfile.TemporaryDirectory() as tmp:
        camera_rows = Path(tmp) / "camera.csv"
        cmd = [sys.executable, "-m", "visvec", "--status-every", "60", "track", "--rig",
               str(RIG), "--camera", cam.url, "--imu", f"udp://127.0.0.1:{p_imu}", "--out",
               f"udp://127.0.0.1:{p_out}", "--camera-out", str(camera_rows), "--serve",
               "127.0.0.1:0"]  # fmt: skip
        # a sensor that does not stop is sent SIGABRT at the end: Python's fault
        # handler then writes every thread's stack to the log
        env = dict(os.environ, PYTHONFAULTHANDLER="1")
        proc = subprocess.Popen(([taskset, "-c", "0"] if taskset else []) + cmd,
                                stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
        busy = [
            subprocess.Popen(
                ([taskset, "-c", "0"] if taskset else [])
                + [sys.executable, "-c", "while True: pass"]
            )  # fmt: skip
            for _ in range(args.busy)
        ]
        log: list[str] = []
        seen = threading.Event()
        page: list[str] = []

        def drain():
            for line in proc.stderr:
                log.append(line.rstrip())
                m = re.search(r"live view at (\S+)", line)
                if m:
                    page.append(m.group(1))
                if "listening" in line:
                    seen.set()

        threading.Thread(target=drain, daemon=True).start()
        if not seen.wait(60.0):
            proc.kill()
            sys.exit("the sensor did not start:\n" + "\n".join(log))
        poller = None
        if page:
            client = [sys.executable, "-c", PAGE, page[0], str(RELOAD_S)]
            poller = subprocess.Popen(([taskset, "-c", "1"] if taskset else []) + client)
        model = ImuModel()
        rng = np.random.default_rng(7)
        end = time.monotonic() + args.minutes * 60.0
        stats: list[dict] = []
        j = max(int(np.ceil((time.monotonic() - t0) * IMU_HZ)), 0)
        j_first = j
        next_stat = time.monotonic()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"time_s,gz_dps,ax_mps2,ay_mps2", ("127.0.0.1", p_imu))
            while time.monotonic() < end and proc.poll() is None:
                chunk = imu_samples(j, int(IMU_HZ), rng, model)
                for t, gz, ax, ay in chunk:
                    wait = t0 + t - time.monotonic()
                    t_imu = t * rate  # the time the IMU's own clock gives the sample
                    if wait > 0:
                        time.sleep(wait)
                    if j < n_max:
                        sent[j] = time.monotonic()
                    s.sendto(
                        f"{t_imu:.5f},{gz:.6f},{ax:.6f},{ay:.6f}".encode(), ("127.0.0.1", p_imu)
                    )
                    j += 1
                if time.monotonic() >= next_stat:
                    st = proc_stats(proc.pid)
                    if st is not None:
                        stats.append({"t_s": time.monotonic() - t0, **st})
                    next_stat += 10.0
        alive = proc.poll() is None
        # SIGTERM ends the run as Ctrl-C does (a shell starts a background job with
        # SIGINT ignored, and its children inherit that: this script under nohup ... &
        # could not stop the sensor with SIGINT); with --serve the page stays until a
        # second one
        for _ in range(2):
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
                break
            except subprocess.TimeoutExpired:
                pass
        else:
            proc.send_signal(signal.SIGABRT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for b in busy:
            b.kill()
            b.wait()
        time.sleep(0.5)
        stop.set()
        rx.close()
        if poller is not None:
            poller.terminate()
            poller.wait(timeout=10)
        cam.httpd.shutdown()
        camera_lines = sum(1 for _ in open(camera_rows)) - 1 if camera_rows.exists() else 0
        # ok camera rows whose frame had waited before it was read: no fixes
        read_late = 0
        if camera_rows.exists():
            with open(camera_rows) as fh:
                read_late = sum(1 for line in fh if "read_late" in line)
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            shutil.copy(camera_rows, args.keep / "camera.csv")
            (args.keep / "sensor.log").write_text("\n".join(log) + "\n")
            k = np.arange(j_first, j)
            np.savez(
                args.keep / "fused.npz",
                sample=k,
                t=k / IMU_HZ,
                sent=sent[k],
                got=got[k],
                pose=pose[k],
                sigma=sigma[k],
                ok=ok[k],
            )
    res = analyse(args, sent, got, pose, sigma, ok, j_first, j, stats)
    res.update(
        ran_to_the_end=alive,
        exit_code=proc.returncode,
        frames_served=cam.sent,
        camera_rows_written=camera_lines,
        camera_rows_read_late=read_late,
        camera_frames_passed_over=next(
            (
                int(m.group(1))
                for x in log
                if (m := re.search(r"(\d+) frames of the stream came", x))
            ),
            0,
        ),
        busy_processes=args.busy,
        sensor_log_tail=log[-6:],
        # what the threads were doing when a sensor that did not stop was aborted
        stopped_by_abort=proc.returncode == -signal.SIGABRT,
        stacks_at_abort=[x for x in log if x.startswith(("Thread", "Current thread", "  File"))],
        one_core=bool(taskset),
    )
    print(save_json("live_soak", res))
    for w in res["windows"]:
        print(w)
    print({k: v for k, v in res.items() if k not in ("windows", "memory")})


def over_sigma(t: np.ndarray, pose: np.ndarray, sigma: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Each row's largest error over its own sigma (x, y mm; heading deg) against the
    path at its time ``t``; 0 for rows not ok."""
    truth = PATH.at(t)
    e_deg = (pose[:, 2] - np.degrees(truth[:, 2]) + 180.0) % 360.0 - 180.0
    err = np.column_stack([pose[:, 0] - truth[:, 0], pose[:, 1] - truth[:, 1], e_deg])
    z = np.where(ok[:, None], np.abs(err) / np.where(ok[:, None], sigma, 1.0), 0.0)
    return z.max(axis=1)


def analyse(args, sent, got, pose, sigma, ok, j0, j1, stats) -> dict:
    """Per window: rows, latency, ok share, errors; the process's memory and CPU. Over the
    run: the ok rows off by WRONG_MM or WRONG_DEG, and those beyond 5 of their own sigma
    on an axis (x, y, heading: the calibration test of DEVELOPERS.md)."""
    idx = np.arange(j0, j1)
    t = idx / IMU_HZ
    truth = PATH.at(t)
    lat = (got[idx] - sent[idx]) * 1000.0
    okk = ok[idx]
    e_mm = np.hypot(pose[idx, 0] - truth[:, 0], pose[idx, 1] - truth[:, 1])
    e_deg = (pose[idx, 2] - np.degrees(truth[:, 2]) + 180.0) % 360.0 - 180.0
    win = args.window_min * 60.0
    st_t = np.array([s["t_s"] for s in stats])
    windows = []
    for a in np.arange(t[0], t[-1] - 0.5 * win, win):
        m = (t >= a) & (t < a + win)
        got_m = np.isfinite(lat[m])
        o = m & okk
        mem = [s for s, tt in zip(stats, st_t, strict=True) if a <= tt < a + win]
        cpu = None
        if len(mem) > 1:
            cpu = (mem[-1]["cpu_s"] - mem[0]["cpu_s"]) / (mem[-1]["t_s"] - mem[0]["t_s"])
        windows.append({
            "from_min": round(float(a) / 60.0, 1),
            "samples": int(m.sum()),
            "rows_per_s": round(float(got_m.sum()) / win, 2),
            "ok_share": round(float(o.sum()) / max(int(m.sum()), 1), 4),
            "latency_ms_median": round(float(np.nanmedian(lat[m])), 3),
            "latency_ms_p99": round(float(np.nanpercentile(lat[m], 99)), 3),
            "latency_ms_max": round(float(np.nanmax(lat[m])), 2),
            "position_rms_mm": round(float(np.sqrt(np.mean(e_mm[o] ** 2))), 3),
            "position_max_mm": round(float(np.max(e_mm[o])), 2),
            "heading_rms_deg": round(float(np.sqrt(np.mean(e_deg[o] ** 2))), 4),
            "rss_mb": round(float(np.mean([s["rss_mb"] for s in mem])), 1) if mem else None,
            "threads": max(s["threads"] for s in mem) if mem else None,
            "fds": max(s["fds"] for s in mem) if mem else None,
            "cpu_share": round(cpu, 3) if cpu is not None else None,
        })  # fmt: skip
    wrong = int(np.sum(okk & ((e_mm > WRONG_MM) | (np.abs(e_deg) > WRONG_DEG))))
    zmax = over_sigma(t, pose[idx], sigma[idx], okk)
    beyond3 = float(np.mean(zmax[okk] > 3.0)) if okk.any() else 0.0
    first, rest = windows[0], windows[1:] or windows
    rss = [w["rss_mb"] for w in windows if w["rss_mb"] is not None]
    growth = round(max(rss[1:] or rss) / rss[0] - 1.0, 4) if rss else None
    lat_worst = max(w["latency_ms_median"] for w in rest) / first["latency_ms_median"]
    rate_worst = min(w["rows_per_s"] for w in rest) / first["rows_per_s"]
    return {
        **run_record(),
        "minutes": args.minutes,
        "window_min": args.window_min,
        "imu_samples": int(j1 - j0),
        "rows_received": int(np.isfinite(lat).sum()),
        "ok_rows": int(okk.sum()),
        "wrong_ok_rows": wrong,
        "ok_rows_beyond_5_sigma": int(np.sum(zmax > 5.0)),
        "ok_rows_beyond_3_sigma_share": round(beyond3, 5),
        "largest_error_over_sigma": round(float(zmax.max()), 2) if okk.any() else None,
        "windows": windows,
        "memory": [{"t_min": round(s["t_s"] / 60.0, 2), "rss_mb": s["rss_mb"]} for s in stats],
        "rss_growth_after_first_window": growth,
        "latency_median_worst_to_first": round(lat_worst, 3),
        "row_rate_worst_to_first": round(rate_worst, 4),
    }  # fmt: skip


if __name__ == "__main__":
    main()
