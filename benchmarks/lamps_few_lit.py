"""Ceiling lamps with few lit (issue 35): lost in space with a share of the map's lamps
switched off, the frames identified by how many lamps are in view, and the wrong fixes.

configs/lamps.toml (640x480, 180 lamps 2.35 m above the camera), random poses over the
whole map, each frame cold; 0, 50, 80 and 90 % of the lamps dark (a fresh random set
per share), and the two sparsest again with stray bright spots (20 % of the lamps in
view). "Wrong": an ok row more than 10 mm or 0.5 deg off.

    python benchmarks/lamps_few_lit.py [--frames 400] [--seed 3]
"""

from __future__ import annotations

import argparse

import numpy as np
from lamps import MAP_HALF, WRONG_DEG, WRONG_MM, err, random_pose, still

from visvec.data import Frame
from visvec.pipeline import LampPipeline
from visvec.rig import load_rig
from visvec.sim.lamps import LampScene, lamps_in_view, render_lamps

from _common import CONFIGS, run_record, save_json


def run(rig, rng, n: int, dark_share: float, spurious: float = 0.0) -> dict:
    n_lamps = len(rig.target.lamps.xyz_mm)
    hidden = tuple(int(k) for k in rng.choice(n_lamps, int(dark_share * n_lamps), replace=False))
    scene = LampScene(hidden=hidden, spurious=spurious)
    pipe = LampPipeline(rig)
    by_n: dict[int, list[int]] = {}
    wrong = 0
    reasons: dict[str, int] = {}
    for i in range(n):
        pose = random_pose(rng, MAP_HALF)
        pipe.reset()
        row = pipe.process(Frame(i, 0.0, render_lamps(rig, still(pose), 0, scene, rng)))
        seen = lamps_in_view(rig, pose, hidden=hidden)
        tally = by_n.setdefault(min(seen, 9), [0, 0])
        tally[1] += 1
        if row.ok:
            tally[0] += 1
            e = err(row, pose)
            wrong += bool(np.hypot(e[0], e[1]) > WRONG_MM or abs(e[2]) > WRONG_DEG)
        elif 3 <= seen <= 8:
            key = ";".join(row.warnings) or str(row.status)
            reasons[key] = reasons.get(key, 0) + 1
    return {
        "dark_share": dark_share,
        "spurious": spurious,
        "frames": n,
        "identified_by_lamps_in_view": {str(k): v for k, v in sorted(by_n.items())},
        "wrong_fixes": wrong,
        "refused_with_3_to_8": reasons,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    rig = load_rig(CONFIGS / "lamps.toml")
    rng = np.random.default_rng(args.seed)
    out = []
    for share, spurious in ((0.0, 0.0), (0.5, 0.0), (0.8, 0.0), (0.9, 0.0), (0.8, 0.2), (0.9, 0.2)):
        r = run(rig, rng, args.frames, share, spurious)
        out.append(r)
        cells = ", ".join(f"{k}{'+' if k == '9' else ''}: {a}/{b}"
                          for k, (a, b) in r["identified_by_lamps_in_view"].items())  # fmt: skip
        extra = f", {100 * spurious:.0f} % spurious spots" if spurious else ""
        print(f"{100 * share:.0f} % dark{extra}: identified by lamps in view {cells}; wrong fixes "
              f"{r['wrong_fixes']}; refused (3-8 in view) {r['refused_with_3_to_8']}",
              flush=True)  # fmt: skip
    save_json("lamps_few_lit", {**run_record(), "results": out})


if __name__ == "__main__":
    main()
