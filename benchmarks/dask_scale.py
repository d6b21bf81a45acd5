"""Scale on Dask (issue 33): a 40-run Monte Carlo study (`visvec montecarlo`'s runs on
configs/markers.toml) on one worker and on a local Dask cluster of two (this machine's
cores), the speed-up, and the scheduler's own cost per task.

Each configuration runs the same 40 runs through visvec.distribute.TaskPool, as the
command does; the results of the two must be identical (checked). The per-task
overhead: 400 tasks that do nothing through the same two-worker cluster, wall time
over their count (what a study pays per task beyond its work).

    python benchmarks/dask_scale.py [--runs 40] [--frames 350] [--poses 500]

(`visvec montecarlo`'s own run size; the workers import visvec before the clock starts,
as the serial process already has.)
"""

from __future__ import annotations

import argparse
import json
import time

from visvec.bench.markers import RunSpec, run_one
from visvec.distribute import TaskPool
from visvec.rig import load_rig

from _common import CONFIGS, run_record, save_json

TARGET_SPEEDUP = 1.8
NOOP_TASKS = 400


def noop(x):
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--frames", type=int, default=350)
    ap.add_argument("--poses", type=int, default=500)
    args = ap.parse_args()
    rig = load_rig(CONFIGS / "markers.toml")
    specs = [RunSpec(rig, 0.12, 0.05, 1000 + k, args.frames, args.poses, True)
             for k in range(args.runs)]  # fmt: skip
    walls, results = {}, {}
    for workers in (1, 2):
        with TaskPool(workers=workers) as pool:
            # every worker imports visvec once, as this process already has
            pool.warm("visvec.bench.markers")
            t0 = time.perf_counter()
            results[workers] = pool.map(run_one, specs)
            walls[workers] = time.perf_counter() - t0
            where = pool.where
        print(f"{workers} worker(s) ({where}): {walls[workers]:.1f} s", flush=True)
    identical = json.dumps(results[1]) == json.dumps(results[2])
    with TaskPool(workers=2) as pool:
        pool.map(noop, range(20))  # warm
        t0 = time.perf_counter()
        pool.map(noop, range(NOOP_TASKS))
        overhead_ms = (time.perf_counter() - t0) / NOOP_TASKS * 1000.0
    speedup = walls[1] / walls[2]
    out = {
        **run_record(),
        "runs": args.runs,
        "frames": args.frames,
        "poses": args.poses,
        "seconds_per_run_one_worker": walls[1] / args.runs,
        "wall_s": {str(k): v for k, v in walls.items()},
        "speedup": speedup,
        "target_speedup": TARGET_SPEEDUP,
        "identical_results": identical,
        "overhead_ms_per_task": overhead_ms,
    }
    save_json("dask_scale", out)
    print(f"speed-up {speedup:.2f}x (target >= {TARGET_SPEEDUP}); results identical: "
          f"{identical}; scheduler overhead {overhead_ms:.2f} ms per task")  # fmt: skip


if __name__ == "__main__":
    main()
