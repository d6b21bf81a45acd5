"""The planar fusion's start and sigma on synthetic lamps streams whose frames are
stated late (visvec.bench.planar): offsets of 7, 50, 150 and 300 ms, with no timing
jitter and with 1 ms, each on five stretches of the lap (other turns and pushes), 10 s
each, through `fuse` with the defaults.

Per run: when the first ok row came (from the first fix: provisional rows, warned
aligning_clocks, until the clocks are aligned) and when the filter itself took over, the
share of ok rows
beyond 3 of their own sigma on some axis, the rows beyond 5, the largest error over
sigma, and how far the alignment was off. The calibration test (DEVELOPERS.md): at most
twice a Gaussian's share beyond 3 and none beyond 5.

Then a lateness that lasts (a camera or its network held up): streams 8 ms late with
0.3 ms of jitter whose frames, from 8 s on, come 2, 3, 5 or 8 ms later still for 0.3 s
or 1 s, on the same five stretches, 14 s each; the same figures, and the share beyond 3
away from the hold-up (before it and from a second after it).

    python benchmarks/fusion_timing.py
"""

from __future__ import annotations

import numpy as np

from visvec.bench.planar import (
    GAUSS3,
    Along,
    errors_over_sigma,
    held_up,
    imu_along,
    late_fixes,
)
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import Fusion, fuse

from _common import run_record, save_json

OFFSETS_S = (0.007, 0.05, 0.15, 0.3)
JITTERS_S = (0.0, 0.001)
STRETCHES_S = (0.0, 11.0, 23.0, 37.0, 51.0)
SECONDS = 10.0
HOLD_EXTRA_S = (0.002, 0.003, 0.005, 0.008)
HOLD_FOR_S = (0.3, 1.0)
HOLD_AT_S = 8.0
HOLD_SECONDS = 14.0


def one(offset: float, jitter: float, t0: float) -> dict:
    path = Along(t0)
    eng = Fusion(PlanarModel())
    imu = imu_along(SECONDS, seed=int(t0), path=path)
    fixes = late_fixes(SECONDS, lambda t, r: offset + jitter * r.standard_normal(),
                       seed=int(t0) + 1, path=path)  # fmt: skip
    out = list(fuse(imu, fixes, PlanarModel(), engine=eng))
    t, z = errors_over_sigma(out, path)
    aligned = eng.aligned[0] if eng.aligned is not None else float("nan")
    # the filter itself from here (the rows before it: provisional, aligning_clocks)
    own = next((fs.time_s for fs in out if fs.state is not None
                and "aligning_clocks" not in fs.warnings), None)  # fmt: skip
    return {
        "offset_ms": offset * 1000.0,
        "jitter_ms": jitter * 1000.0,
        "stretch_s": t0,
        "first_ok_s": round(float(t[0]), 2) if len(t) else None,
        "aligned_s": round(float(own), 2) if own is not None else None,
        "beyond_3_share": round(float(np.mean(z > 3.0)), 4) if len(z) else None,
        "beyond_5": int(np.sum(z > 5.0)),
        "largest": round(float(z.max()), 2) if len(z) else None,
        "alignment_off_ms": round(1000.0 * (aligned - offset), 1),
    }


def one_held_up(extra: float, hold: float, t0: float) -> dict:
    path = Along(t0)
    imu = imu_along(HOLD_SECONDS, seed=int(t0) + 7, path=path)
    late = held_up(extra, HOLD_AT_S, hold)
    fixes = late_fixes(HOLD_SECONDS, late, seed=int(t0) + 8, path=path)
    t, z = errors_over_sigma(fuse(imu, fixes, PlanarModel()), path)
    away = (t < HOLD_AT_S) | (t > HOLD_AT_S + hold + 1.0)
    return {
        "extra_ms": extra * 1000.0,
        "for_s": hold,
        "stretch_s": t0,
        "beyond_3_share": round(float(np.mean(z > 3.0)), 4),
        "beyond_3_share_away": round(float(np.mean(z[away] > 3.0)), 4),
        "beyond_5": int(np.sum(z > 5.0)),
        "largest": round(float(z.max()), 2),
    }


def main() -> None:
    runs = [one(d, j, t0) for d in OFFSETS_S for j in JITTERS_S for t0 in STRETCHES_S]
    held = [one_held_up(e, h, t0) for e in HOLD_EXTRA_S for h in HOLD_FOR_S for t0 in STRETCHES_S]
    firsts = [r["first_ok_s"] for r in runs if r["first_ok_s"] is not None]
    shares = [r["beyond_3_share"] for r in runs if r["beyond_3_share"] is not None]
    res = {
        **run_record(),
        "runs": len(runs),
        "started": len(firsts),
        "first_ok_s_median": round(float(np.median(firsts)), 2),
        "first_ok_s_max": max(firsts),
        "aligned_s_median": round(
            float(np.median([r["aligned_s"] for r in runs if r["aligned_s"] is not None])), 2
        ),
        "aligned_runs": sum(r["aligned_s"] is not None for r in runs),
        "beyond_3_share_mean": round(float(np.mean(shares)), 4),
        "gaussian_beyond_3": round(GAUSS3, 4),
        "runs_beyond_3_over_twice_gaussian": sum(s > 2 * GAUSS3 for s in shares),
        "rows_beyond_5": sum(r["beyond_5"] for r in runs),
        "largest": max(r["largest"] for r in runs if r["largest"] is not None),
        "alignment_off_ms_abs_max": max(abs(r["alignment_off_ms"]) for r in runs),
        "each": runs,
        "held_up": {
            "runs": len(held),
            "beyond_3_share_mean": round(float(np.mean([r["beyond_3_share"] for r in held])), 4),
            "beyond_3_share_away_mean": round(
                float(np.mean([r["beyond_3_share_away"] for r in held])), 4
            ),
            "runs_beyond_3_over_twice_gaussian": sum(
                r["beyond_3_share"] > 2 * GAUSS3 for r in held
            ),
            "runs_with_rows_beyond_5": sum(r["beyond_5"] > 0 for r in held),
            "rows_beyond_5": sum(r["beyond_5"] for r in held),
            "largest": max(r["largest"] for r in held),
            "each": held,
        },
    }
    print({k: v for k, v in res.items() if k != "each"} | {"held_up": {
        k: v for k, v in res["held_up"].items() if k != "each"}})  # fmt: skip
    for r in runs + held:
        if r["beyond_5"] or (r["beyond_3_share"] or 0) > 2 * GAUSS3:
            print("  ", r)
    print(save_json("fusion_timing", res))


if __name__ == "__main__":
    main()
