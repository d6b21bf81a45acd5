"""`visvec montecarlo`: the STASIS paper's Monte Carlo study (Sec. 3.5) for a markers rig."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click

from visvec.bench.markers import METHODS, RunSpec, run_one, summarise
from visvec.cli.common import load, rig_options, scheduler_options
from visvec.cli.progress import Work
from visvec.distribute import TaskPool


def _floats(text: str, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(
            f"{text!r}: expected comma-separated numbers", param_hint=what
        ) from None
    if not vals or any(not math.isfinite(v) or v < 0 for v in vals):
        raise click.BadParameter(f"{text!r}: expected non-negative numbers", param_hint=what)
    return vals


@click.command()
@rig_options
@click.option(
    "--runs",
    type=click.IntRange(min=1),
    default=20,
    show_default=True,
    help="Runs per (centroid noise, marker error) point.",
)
@click.option(
    "--centroid-noise",
    default="0.06,0.12,0.24",
    show_default=True,
    help="Centroid noise levels, px (comma-separated).",
)
@click.option(
    "--marker-error",
    default="0,0.05,0.1",
    show_default=True,
    help="Marker placement errors, mm (comma-separated).",
)
@click.option(
    "--frames",
    type=click.IntRange(min=10),
    default=350,
    show_default=True,
    help="Calibration frames per run.",
)
@click.option(
    "--poses",
    type=click.IntRange(min=10),
    default=500,
    show_default=True,
    help="Fresh poses estimated per run.",
)
@click.option(
    "--no-calibration",
    is_flag=True,
    help="Skip the virtual calibration: estimate with the true lab geometry.",
)
@scheduler_options
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for montecarlo.json and montecarlo.png.",
)
def montecarlo(
    rig_path,
    calibration,
    runs,
    centroid_noise,
    marker_error,
    frames,
    poses,
    no_calibration,
    scheduler,
    workers,
    seed,
    out_dir,
):
    """Accuracy of the constrained solver and the PnP baselines over perturbed labs:
    each run draws a lab within STASIS Table-3-like ranges, places the LEDs with error,
    calibrates virtually, then estimates fresh poses. Reports the 1-sigma errors, the
    Cramer-Rao bound, our efficiency and each baseline's ratio to ours."""
    rig = load(rig_path, calibration, "markers", "the Monte Carlo study")
    cs = _floats(centroid_noise, "--centroid-noise")
    ms = _floats(marker_error, "--marker-error")
    specs = [
        RunSpec(
            rig,
            c,
            m,
            seed * 1_000_003 + i * 7919 + j * 104729 + k,
            frames,
            poses,
            not no_calibration,
        )
        for i, c in enumerate(cs)
        for j, m in enumerate(ms)
        for k in range(runs)
    ]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    head = {"rig": str(rig_path), "runs_per_point": runs, "frames": frames, "poses": poses,
            "calibrated": not no_calibration}  # fmt: skip
    finished: dict[int, dict] = {}
    with TaskPool(scheduler, workers) as pool:
        click.echo(f"visvec: {len(specs)} runs on {pool.where}", err=True)
        try:
            with Work("montecarlo", len(specs), unit="run") as bar:
                results = pool.map(
                    run_one, specs, lambda i, r: (finished.__setitem__(i, r), bar.update(1))
                )
        except KeyboardInterrupt:
            # every finished run kept, in task order, for a study to be resumed or read
            done = [finished[i] for i in sorted(finished)]
            _write(out, {**head, "interrupted": True, "runs_finished": len(done),
                         "summary": summarise(done) if done else [], "runs": done})  # fmt: skip
            click.echo(f"visvec: interrupted: {len(done)} of {len(specs)} runs finished, "
                       f"written to {out / 'montecarlo.json'}", err=True)  # fmt: skip
            sys.exit(130)
    summary = summarise(results)
    _write(out, {**head, "summary": summary, "runs": results})
    for p in summary:
        click.echo(
            f"sigma_c {p['sigma_c_px']:.3f} px, sigma_m {p['sigma_m_mm']:.3f} mm: "
            f"full {p['std_arcsec']['full']} arcsec (bound {p['crb_arcsec']}, "
            f"efficiency {p['efficiency']}); IPPE x{p['ratio_to_full']['pnp-ippe']}, "
            f"P3P x{p['ratio_to_full']['pnp-p3p']}"
        )
    if _plot(summary, cs, ms, out / "montecarlo.png"):
        click.echo(f"wrote {out / 'montecarlo.json'} and {out / 'montecarlo.png'}")
    else:
        click.echo(f"wrote {out / 'montecarlo.json'} (install matplotlib for the plots)")


def _write(out: Path, study: dict) -> None:
    (out / "montecarlo.json").write_text(json.dumps(study, indent=1))


def _plot(summary, cs, ms, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    axes_names = ("yaw", "pitch", "roll")
    for m in ms:
        pts = [p for p in summary if p["sigma_m_mm"] == m]
        x = [p["sigma_c_px"] for p in pts]
        for k in range(3):
            axes[k].plot(
                x,
                [p["std_arcsec"]["full"][k] for p in pts],
                "o-",
                label=f"ours, marker error {m} mm",
            )
            axes[k].plot(x, [p["crb_arcsec"][k] for p in pts], "k:", lw=1)
    for k in range(3):
        axes[k].set_title(f"{axes_names[k]} 1-sigma (arcsec); dotted: Cramer-Rao bound")
        axes[k].set_xlabel("centroid noise (px)")
        axes[k].legend(fontsize=7)
    base = [p for p in summary if p["sigma_m_mm"] == ms[0]]
    for meth in METHODS[1:]:
        if meth == "pnp-ap3p":
            continue  # identical to P3P with four points
        axes[3].semilogy(
            [p["sigma_c_px"] for p in base],
            [max(p["ratio_to_full"][meth][1:]) for p in base],
            "o-",
            label=meth,
        )
    axes[3].set_title(f"baseline / ours, pitch-roll (marker error {ms[0]} mm)")
    axes[3].set_xlabel("centroid noise (px)")
    axes[3].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return True
