"""A live soak's fixes replayed through the fusion offline (`live_soak.py --keep DIR`).

The camera's rows the soak kept (poses, sigmas, and times as the sensor stamped them on
its own clock) are fed, each when the sensor had it, to the same fusion engine with an
IMU regenerated along the same path (the same model and clock rate, another noise
draw), tied to the host's clock as the sensor ties it. The fused rows are judged as
the soak judges them (against the path, each against its own sigma), beside the soak's
own rows. What the fusion makes of that run's fixes, repeatable and without the live
harness: a change to the fusion's timing model is checked on a real run's timing in
minutes rather than a new 20-minute run.

    python benchmarks/fusion_replay.py DIR [--minutes 20] [--seed 7]
"""

from __future__ import annotations

import argparse
import csv
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
from live_soak import IMU_HZ, IMU_PPM, PATH, imu_samples, over_sigma

from visvec.clocks import ClockTie
from visvec.fuse.live import parse_fix
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import Fusion
from visvec.sim.lamps import ImuModel

from _common import run_record, save_json

# rows beyond this many of their own sigma, this close together, are one event
CLUSTER_GAP_S = 0.5


def judge(t, pose, sigma, ok) -> dict:
    """The calibration test's figures and the rows beyond 5 sigma as events."""
    z = over_sigma(t, pose, sigma, ok)
    bad = np.flatnonzero(z > 5.0)
    events = []
    if len(bad):
        for run in np.split(bad, np.flatnonzero(np.diff(t[bad]) > CLUSTER_GAP_S) + 1):
            events.append({"from_s": round(float(t[run[0]]), 2),
                           "to_s": round(float(t[run[-1]]), 2), "rows": len(run),
                           "largest": round(float(z[run].max()), 2)})  # fmt: skip
    first = float(t[np.argmax(ok)]) if ok.any() else None
    # the position's error and sigma (each row's larger axis), over the ok rows
    e = np.hypot(*(pose[ok, :2] - PATH.at(t[ok])[:, :2]).T)
    sig_mm = sigma[ok, :2].max(axis=1)
    return {
        "rows": len(t),
        "ok_rows": int(ok.sum()),
        "first_ok_s": first,
        "beyond_3_sigma_share": round(float(np.mean(z[ok] > 3.0)), 5) if ok.any() else None,
        "beyond_5_sigma": len(bad),
        "position_rms_mm": round(float(np.sqrt(np.mean(e * e))), 4) if ok.any() else None,
        "position_sigma_median_mm": round(float(np.median(sig_mm)), 4) if ok.any() else None,
        "largest_error_over_sigma": round(float(z.max()), 2) if ok.any() else None,
        "beyond_4_sigma_first_10_s": int(np.sum((z > 4.0) & (t < (first or 0.0) + 10.0))),
        "events_beyond_5_sigma": events,
    }


def replay(keep: Path, minutes: float, seed: int) -> tuple[dict, dict]:
    """(the replay's judgement, the soak's own) over the first ``minutes``."""
    kept = np.load(keep / "fused.npz")
    sample, sent = kept["sample"], kept["sent"]
    # the IMU's host tie: a sample's send less its time on the IMU's own clock, at least
    host0 = float(np.min(sent - sample / IMU_HZ))
    log = (keep / "sensor.log").read_text()
    cam0 = float(re.search(r"first frame \(host monotonic clock ([0-9.]+) s\)", log).group(1))
    fixes = []
    with open(keep / "camera.csv") as fh:
        for row in csv.DictReader(fh):
            f = parse_fix(row, True)
            if f is not None:
                host = cam0 + float(row["time_s"])
                fixes.append((host, host + float(row["latency_ms"]) / 1000.0, f))
    rate = 1.0 - IMU_PPM * 1e-6
    eng, tie = Fusion(PlanarModel()), ClockTie()
    rng = np.random.default_rng(seed)
    j, j_end = int(sample[0]), int(sample[0]) + int(minutes * 60.0 * IMU_HZ)
    k = 0
    n = j_end - j
    t_out = np.empty(n)
    pose, sig = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    ok = np.zeros(n, bool)
    i = 0
    while j < j_end:
        for t, gz, ax, ay in imu_samples(j, int(IMU_HZ), rng, ImuModel()):
            if i >= n:
                break
            arrival = host0 + t + 1e-4
            t_imu = t * rate
            tie.add(arrival, t_imu)
            while k < len(fixes) and fixes[k][1] <= arrival:
                host, avail, f = fixes[k]
                k += 1
                eng.add_fix(replace(f, time_s=host - tie.offset, available_s=avail - tie.offset))
            fs = eng.step(t_imu, np.array([0.0, 0.0, math.radians(gz)]), np.array([ax, ay]))
            t_out[i] = t
            if fs.state is not None:  # an ok row (visvec.fuse.run.fused_rows)
                v, s = PlanarModel.values(fs.state)
                pose[i] = [v[0], v[1], math.degrees(v[2])]
                sig[i] = [s[0], s[1], math.degrees(s[2])]
                ok[i] = True
            i += 1
            j += 1
    mine = judge(t_out[:i], pose[:i], sig[:i], ok[:i])
    mine["aligned_ms"] = [round(1000.0 * v, 2) for v in (eng.aligned or (math.nan, math.nan))]
    m = sample < j_end
    theirs = judge(sample[m] / IMU_HZ, kept["pose"][m], kept["sigma"][m], kept["ok"][m])
    return mine, theirs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("keep", type=Path, help="a live soak's --keep folder")
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=7, help="the regenerated IMU's noise draw")
    args = ap.parse_args()
    mine, theirs = replay(args.keep, args.minutes, args.seed)
    res = {**run_record(), "kept": str(args.keep), "minutes": args.minutes, "seed": args.seed,
           "replay": mine, "soak": theirs}  # fmt: skip
    print(res)
    print(save_json("fusion_replay", res))


if __name__ == "__main__":
    main()
