"""Yaw zero: a camera turned on its mount, calibrated from stops at known yaws.

A simulated 640x480 lab whose camera is turned 0.3 deg about its own optical axis,
tilted 0.5 / -0.4 deg on its mount, and whose target hangs 12 / -9 mm off the rotation
axis. `visvec calibrate zero-tilt` on 16 level stops, of which the lab knows the yaw of
two (to `--yaw-sigma-deg`, the reference's 1-sigma, drawn as its real error too); then
`visvec batch` on 200 fresh frames at random attitudes (tilts up to 7 deg) with the
calibration, against the truth, beside the calibration without the known yaws.

Targets: yaw within 0.01 deg of the reference (the mean yaw error), tilts within 0.002
deg RMS, and the turn within its sigma check (|error| / sigma).

    python benchmarks/triangle_yaw_zero.py [--reference-sigma-deg 0.005] [--seed 0]
"""

from __future__ import annotations

import argparse
import csv
import shutil
import tempfile
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from visvec.cli.main import cli

from _common import CONFIGS, run_record, save_json

TURN, ASKEW, OFFSET = 0.3, (0.5, -0.4), (12.0, -9.0)


def run(*args) -> str:
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    if r.exit_code != 0:
        raise SystemExit(f"visvec {' '.join(map(str, args))}: exit {r.exit_code}\n{r.output}")
    return r.output


def lab(*extra) -> list:
    return ["--camera-turn-deg", TURN, "--camera-askew-deg", *ASKEW,
            "--target-offset-mm", *OFFSET, *extra]  # fmt: skip


def errors(rows_csv: Path, truth_csv: Path) -> dict:
    truth = {int(r["frame"]): r for r in csv.DictReader(open(truth_csv))}
    e = []
    for r in csv.DictReader(open(rows_csv)):
        if r["status"] != "ok":
            continue
        t = truth[int(r["frame"])]
        d = np.array([float(r[k]) - float(t[k]) for k in ("yaw_deg", "pitch_deg", "roll_deg")])
        d[0] = (d[0] + 180) % 360 - 180
        e.append(d)
    E = np.array(e)
    return {
        "ok": len(E),
        "yaw_mean": float(E[:, 0].mean()),
        "yaw_rms": float(np.sqrt(np.mean(E[:, 0] ** 2))),
        "tilt_rms": float(np.sqrt(np.mean(E[:, 1:] ** 2))),
        "pitch_rms": float(np.sqrt(np.mean(E[:, 1] ** 2))),
        "roll_rms": float(np.sqrt(np.mean(E[:, 2] ** 2))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference-sigma-deg", type=float, default=0.005)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rig = CONFIGS / "triangle.toml"
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        run("simulate", "--rig", rig, "--out", tmp / "level", "--frames", 16, "--motion", "level",
            "--seed", args.seed, *lab())  # fmt: skip
        truth = list(csv.DictReader(open(tmp / "level" / "truth.csv")))
        stops, yaws = [], []
        for k, r in enumerate(truth):
            d = tmp / f"stop{k:02d}"
            d.mkdir()
            shutil.copy(tmp / "level" / r["file"], d / r["file"])
            stops.append(d)
            # the lab knows two stops' yaws, to its reference's accuracy
            known = float(r["yaw_deg"]) + rng.normal(0, args.reference_sigma_deg)
            yaws.append(f"{known:.6f}" if k in (0, 5) else "-")
        out = {}
        for name, yaw_args in (("without known yaws", []),
                               ("two stops at known yaws",
                                [x for y in yaws for x in ("--yaw-deg", y)]
                                + ["--yaw-sigma-deg", args.reference_sigma_deg])):  # fmt: skip
            cal = tmp / f"cal-{len(yaw_args)}.toml"
            text = run("calibrate", "zero-tilt", *stops, "--rig", rig, "--out", cal, *yaw_args)
            turn_line = [x for x in text.splitlines() if "yaw zero" in x]
            run("simulate", "--rig", rig, "--out", tmp / f"test-{len(yaw_args)}", "--frames", 200,
                "--seed", args.seed + 1, "--max-tilt-deg", 5, *lab())  # fmt: skip
            rows = tmp / f"rows-{len(yaw_args)}.csv"
            run("batch", tmp / f"test-{len(yaw_args)}", "--rig", rig, "--calibration", cal,
                "--out", rows)  # fmt: skip
            res = errors(rows, tmp / f"test-{len(yaw_args)}" / "truth.csv")
            res["calibration"] = turn_line[0].strip() if turn_line else ""
            if yaw_args:
                import tomllib

                rep = tomllib.loads(cal.read_text())["report"]
                res["turn_deg"] = rep["camera_turn_deg"]
                res["sigma_turn_deg"] = rep["sigma_camera_turn_deg"]
                res["turn_error_over_sigma"] = (rep["camera_turn_deg"] - TURN) / rep[
                    "sigma_camera_turn_deg"
                ]
            out[name] = res
            turn = (
                f"; turn {res['turn_deg']:+.4f} +- {res['sigma_turn_deg']:.4f} deg "
                f"({res['turn_error_over_sigma']:+.2f} sigma)"
                if yaw_args
                else ""
            )
            print(f"{name}: {res['ok']} ok; yaw mean error {res['yaw_mean']:+.4f} deg, RMS "
                  f"{res['yaw_rms']:.4f}; tilts RMS {res['tilt_rms']:.5f} deg (pitch "
                  f"{res['pitch_rms']:.5f}, roll {res['roll_rms']:.5f}){turn}")  # fmt: skip
    best = out["two stops at known yaws"]
    met = {
        "yaw within 0.01 deg": abs(best["yaw_mean"]) <= 0.01,
        "tilts within 0.002 deg RMS": best["tilt_rms"] <= 0.002,
        "turn within 3 sigma": abs(best["turn_error_over_sigma"]) <= 3,
    }
    print("targets: " + ", ".join(f"{k}: {'met' if v else 'NOT met'}" for k, v in met.items()))
    save_json("triangle_yaw_zero", {**run_record(), "true_turn_deg": TURN,
                                    "reference_sigma_deg": args.reference_sigma_deg,
                                    "results": out, "met": met})  # fmt: skip


if __name__ == "__main__":
    main()
