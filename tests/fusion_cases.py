"""Fusion test cases shared by tests/fuse and tests/cli: simulated IMU and fixes files,
and helpers for the live tests."""

import csv
import math

import numpy as np

from visvec.fuse.inputs import Fix, read_fixes, read_imu
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import fuse
from visvec.output import PLANAR_COLUMNS
from visvec.rotations import expmap, logmap
from visvec.sim.lamps import PerimeterPath, simulate_imu

PATH = PerimeterPath(rest_s=3.0)


def planar_case(tmp_path, duration=40.0, latency_ms=600.0, fix_hz=1.7, seed=0, sigma=0.1):
    """IMU, truth and fixes files along the perimeter path."""
    imu, truth = simulate_imu(PATH, duration, tmp_path, seed=seed)
    rng = np.random.default_rng(seed)
    fixes = tmp_path / "fixes.csv"
    with open(fixes, "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(PLANAR_COLUMNS)
        for i, t in enumerate(np.arange(0.2, duration, 1.0 / fix_hz)):
            x, y, h = PATH.at(t)
            wr.writerow(
                [
                    i,
                    f"{t:.4f}",
                    "ok",
                    x + rng.normal(0, sigma),
                    y + rng.normal(0, sigma),
                    math.degrees(h) + rng.normal(0, 0.005),
                    sigma,
                    sigma,
                    0.005,
                    0.05,
                    20,
                    latency_ms,
                    "",
                    "",
                ]
            )  # fmt: skip (warnings, time_unix)
    return imu, truth, fixes


def truth_table(path):
    with open(path) as fh:
        return np.array([[float(r["x_mm"]), float(r["y_mm"]), float(r["heading_deg"])]
                         for r in csv.DictReader(fh)])  # fmt: skip


def run(imu_path, fixes_path, model=None, limits=None):
    fx = read_fixes(fixes_path)
    imu = read_imu(imu_path, planar=fx.planar)
    return list(fuse(imu, fx.fixes, model or PlanarModel(), limits=limits))


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def _sim3d(n=6000, dt=0.01, seed=4, amp=1.0, delay=0.0, rest_s=0.0, speed=1.0, drift=0.0):
    """A 3-D gyro (body rate w_b with a misalignment, bias and noise; the reading at t
    is the rate at t - delay - drift t: a clock off by ``drift`` s/s) and the true
    attitudes; still for rest_s seconds."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    on = (t >= rest_s).astype(float)[:, None]
    u = speed * t
    w_b = on * amp * np.column_stack([0.8 * np.sin(0.7 * u), 0.6 * np.sin(1.1 * u + 1),
                                      0.9 * np.cos(0.5 * u)])  # fmt: skip
    R = [np.eye(3)]
    for i in range(1, n):
        R.append(R[-1] @ expmap(0.5 * (w_b[i] + w_b[i - 1]) * dt))
    Rm = expmap(np.radians([2.0, -1.5, 1.8]))
    w_late = np.column_stack([np.interp(t - delay - drift * t, t, w_b[:, k]) for k in range(3)])
    gyro = w_late @ Rm + np.radians([0.4, -0.3, 0.2]) + rng.normal(0, np.radians(0.05), (n, 3))
    return t, R, gyro, rng


def _run_engine(eng, t, gyro, fixes):
    """Every sample through a fusion engine, each fix given to it once available."""
    fx = sorted(fixes, key=lambda f: f.available_s)
    out, j = [], 0
    for k in range(len(t)):
        while j < len(fx) and fx[j].available_s <= t[k]:
            eng.add_fix(fx[j])
            j += 1
        out.append(eng.step(t[k], gyro[k], None))
    return out


def _fixes(t, R, rng, every=50, sigma_deg=0.1, latency=0.6):
    s = np.radians(sigma_deg)
    return [Fix(t[i], t[i] + latency, R[i] @ expmap(s * rng.standard_normal(3)),
                np.eye(3) * s**2, i) for i in range(0, len(t), every)]  # fmt: skip


def _err(out, R, start=0):
    return np.array([np.degrees(np.linalg.norm(logmap(R[x.index].T @ x.state.R)))
                     for x in out[start:] if x.state is not None])  # fmt: skip


def _send_paced(sock, lines, port, t0, fix_rows=(), fix_port=None):
    """Send CSV ``lines`` (time_s first) as datagrams at ``t0`` plus their time, and
    before each the (available time, line) ``fix_rows`` whose time has come."""
    import time

    fix_rows = list(fix_rows)
    for line in lines:
        ts = float(line.split(",")[0])
        while fix_rows and fix_rows[0][0] <= ts:
            sock.sendto(fix_rows.pop(0)[1].encode(), ("127.0.0.1", fix_port))
        wait = t0 + ts - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        sock.sendto(line.encode(), ("127.0.0.1", port))


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
