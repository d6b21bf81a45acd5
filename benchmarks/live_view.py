"""The live view never slows the sensor: the same recording processed with and without a
page open, in alternating runs.

The recording (640x480 triangle frames from `visvec simulate`) is delivered as a camera
delivers it, at 30 frames a second (the live case: the row rate, and each row's latency,
the rows' latency_ms, from frame in hand to row out), and, as a stress case, as fast as
the sensor can read it (any time the page takes from the sensor then shows as a lower
row rate). Target: row rate and latency within 5 % of the runs without a page, in the
median over rounds of each round's ratio to its own run without a page (the machine's
own drift between rounds is as large as the target). The sensor's process (its loop and
the page's server threads) is pinned to core 0; the page's client runs on core 1: a
process fetching what the page fetches, as often (a lab's browser on another computer),
and the page itself in headless Chromium (a browser on the sensor's own computer, whose
rendering shares the machine's caches and memory with the sensor).

    python benchmarks/live_view.py [--frames 300] [--rounds 5]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from visvec.cli.frames import run_frames
from visvec.fuse.camera import paced
from visvec.output import AttitudeRow
from visvec.rig import load_rig
from visvec.sources import open_source
from visvec.view import start

from _common import CONFIGS, run_record, save_json

# none: no page; client: a process on core 1 fetching what the page fetches, as often
# (a browser on another computer); chromium: the page in headless Chromium on core 1
MODES = ("none", "client", "chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--window-size=1300,1000",
]  # fmt: skip


# a client that asks for what the page asks for, as often (a browser elsewhere)
POLLER = """
import sys, time, urllib.request
url = sys.argv[1]
n = 0
while True:
    for path in ["frame.jpg"] + (["api/state?since=0"] if n % 5 == 0 else []):
        try:
            urllib.request.urlopen(url + path, timeout=5).read()
        except OSError:
            pass
    n += 1
    time.sleep(0.1)
"""


def one_run(rig, rec: Path, mode: str, tmp: Path, pace: bool) -> dict:
    src = open_source(str(rec), fps=rig.fps)
    if pace:
        src = paced(src)
    server = start("127.0.0.1:0", rig, AttitudeRow, ["benchmark"])
    browser = None
    if mode == "chromium":
        chromium = shutil.which("chromium")
        browser = subprocess.Popen(
            ["taskset", "-c", "1", chromium, *CHROMIUM_ARGS, f"--user-data-dir={tmp / 'chromium'}",
             server.url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        time.sleep(3.0)  # the page loaded and polling before the sensor starts
    elif mode == "client":
        browser = subprocess.Popen(["taskset", "-c", "1", sys.executable, "-c", POLLER,
                                    server.url])  # fmt: skip
        time.sleep(1.0)
    t0 = time.perf_counter()
    rows = run_frames(rig, src, out=str(tmp / f"rows-{mode}-{t0}.csv"), fmt="csv",
                      method=None, overlay=None, max_frames=None, keep_rows=True,
                      watchers=[server.state])  # fmt: skip
    took = time.perf_counter() - t0
    served = server.state.seq
    if browser is not None:
        browser.terminate()
        browser.wait(timeout=10)
    server.stop()
    lat = [r.latency_ms for r in rows]
    return {
        "mode": mode,
        "paced": pace,
        "rows": len(rows),
        "rows_per_s": len(rows) / took,
        "latency_ms_median": statistics.median(lat),
        "latency_ms_p95": sorted(lat)[int(0.95 * len(lat))],
        "rows_seen_by_view": served,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    if not shutil.which("chromium"):
        sys.exit("needs Debian's chromium (apt-get install chromium)")
    os.sched_setaffinity(0, {0})
    rig = load_rig(CONFIGS / "triangle.toml")
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        rec = tmp / "rec"
        subprocess.run([sys.executable, "-m", "visvec", "simulate", "--rig",
                        str(CONFIGS / "triangle.toml"), "--out", str(rec), "--frames",
                        str(args.frames), "--motion", "swing"],
                       check=True, capture_output=True)  # fmt: skip
        runs = []
        for pace in (True, False):
            for k in range(args.rounds):
                for mode in MODES:
                    r = one_run(rig, rec, mode, tmp, pace)
                    r["round"] = k
                    runs.append(r)
                    print(f"{'30 fps' if pace else 'flat out'}, round {k + 1}, {mode}: "
                          f"{r['rows_per_s']:.1f} rows/s, latency median "
                          f"{r['latency_ms_median']:.3f} ms, p95 {r['latency_ms_p95']:.3f} ms",
                          flush=True)  # fmt: skip
    result = {**run_record(), "frames": args.frames, "rounds": args.rounds, "runs": runs}
    for pace in (True, False):
        case = "30fps" if pace else "flat_out"
        result[case] = {}
        for mode in MODES[1:]:
            rate, lat = [], []
            for k in range(args.rounds):
                base = next(r for r in runs if r["paced"] is pace and r["round"] == k
                            and r["mode"] == "none")  # fmt: skip
                this = next(r for r in runs if r["paced"] is pace and r["round"] == k
                            and r["mode"] == mode)  # fmt: skip
                rate.append(100 * (this["rows_per_s"] / base["rows_per_s"] - 1))
                lat.append(100 * (this["latency_ms_median"] / base["latency_ms_median"] - 1))
            r = {
                "rows_per_s_change_pct": statistics.median(rate),
                "latency_change_pct": statistics.median(lat),
            }
            r["met"] = abs(r["rows_per_s_change_pct"]) <= 5 and r["latency_change_pct"] <= 5
            result[case][mode] = r
            print(f"{case}, {mode}: rows/s {r['rows_per_s_change_pct']:+.1f} %, latency "
                  f"{r['latency_change_pct']:+.1f} % (median of the rounds' ratios); within "
                  f"5 %: {'met' if r['met'] else 'NOT met'}")  # fmt: skip
    save_json("live_view", result)


if __name__ == "__main__":
    main()
