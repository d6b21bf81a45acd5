"""`visvec fuse`: inertial samples and late camera fixes fused at the inertial rate."""

from __future__ import annotations

import math
from dataclasses import replace

import click

from visvec.cli.common import open_out
from visvec.evaluate import error_stats, read_truth
from visvec.fuse.inputs import read_fixes, read_imu
from visvec.fuse.models import AttitudeModel, PlanarModel
from visvec.fuse.replay import Limits
from visvec.fuse.replay import fuse as run_fusion
from visvec.fuse.run import fused_rows, rest_biases
from visvec.output import AttitudeRow, PoseRow
from visvec.sinks import open_sink


@click.command()
@click.option("--imu", "imu_path", required=True, type=click.Path(dir_okay=False),
              help="Inertial CSV: time_s and gz_dps,ax_mps2,ay_mps2 (planar) or "
              "gx_dps,gy_dps,gz_dps (3-D).")  # fmt: skip
@click.option("--fixes", "fixes_path", required=True, type=click.Path(dir_okay=False),
              help="visvec output rows (planar pose or attitude); time_s is the exposure, "
              "latency_ms when it became available.")  # fmt: skip
@click.option("--out", default=None, type=click.Path(dir_okay=False),
              help="Output file, or udp://HOST:PORT for one datagram per row (default: "
              "stdout).")  # fmt: skip
@click.option("--format", "fmt", type=click.Choice(["csv", "jsonl"]), default="csv",
              show_default=True)  # fmt: skip
@click.option(
    "--method",
    type=click.Choice(["kalman", "paper"]),
    default="kalman",
    show_default=True,
    help="Planar: Kalman filter with biases, or the paper's reset at each fix.",
)
@click.option("--rest-s", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Seconds at rest at the start: average them for the biases.")  # fmt: skip
@click.option("--max-rate-dps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Rates beyond this are faults [planar: 50 (the paper), 3-D: 2000].")  # fmt: skip
@click.option("--max-accel-mps2", type=click.FloatRange(min=0, min_open=True), default=0.5,
              show_default=True, help="Planar: accelerations beyond this are faults.")  # fmt: skip
@click.option("--gyro-noise-dps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Gyro white noise per sample [planar 0.05, 3-D 0.3].")  # fmt: skip
@click.option("--accel-noise-mps2", type=click.FloatRange(min=0, min_open=True),
              default=0.002, show_default=True,
              help="Planar: accelerometer white noise per sample (the paper's).")  # fmt: skip
@click.option("--fix-sigma-deg", type=click.FloatRange(min=0, min_open=True), default=None,
              help="3-D: fix attitude noise, overriding the fixes' sigma columns.")  # fmt: skip
@click.option(
    "--no-misalignment",
    is_flag=True,
    help="3-D: do not estimate the gyro misalignment to the fixes' body axes.",
)
@click.option("--history-s", type=click.FloatRange(min=0.1), default=10.0, show_default=True,
              help="Inertial history kept for replaying late fixes.")  # fmt: skip
@click.option("--truth", default=None, type=click.Path(dir_okay=False),
              help="Truth per inertial sample (frame = sample index): print error "
              "statistics.")  # fmt: skip
def fuse(imu_path, fixes_path, out, fmt, method, rest_s, max_rate_dps, max_accel_mps2,
         gyro_noise_dps, accel_noise_mps2, fix_sigma_deg, no_misalignment, history_s,
         truth):  # fmt: skip
    """Fuse an IMU with late camera fixes: one row per inertial sample, causal (the row
    at time t uses the samples up to t and the fixes available by t)."""
    fixes = read_fixes(fixes_path)
    imu = read_imu(imu_path, planar=fixes.planar)
    for k in imu.gaps:
        click.echo(
            f"visvec: {imu_path}: line {imu.lines[k]}: gap of {imu.t[k] - imu.t[k - 1]:.3f} s "
            f"after t = {imu.t[k - 1]:.3f} s (period {imu.period_s:.4f} s): not integrated "
            "over; fusion restarts at the next fix",
            err=True,
        )
    if not fixes.fixes:
        click.echo(f"visvec: {fixes_path}: no ok fixes among {fixes.n_rows} rows", err=True)
    if fixes.planar:
        if fix_sigma_deg is not None or no_misalignment:
            raise click.UsageError("--fix-sigma-deg and --no-misalignment apply to 3-D fixes")
        model = PlanarModel(method=method, accel_noise=accel_noise_mps2 * 1000.0)
        if gyro_noise_dps is not None:
            model = replace(model, gyro_noise=math.radians(gyro_noise_dps))
        limits = Limits(max_rate_dps or 50.0, max_accel_mps2)
    else:
        if method != "kalman":
            raise click.UsageError("--method paper applies to planar fixes")
        model = AttitudeModel(misalignment_sigma=0.0 if no_misalignment else math.radians(5),
                              sample_s=imu.period_s)  # fmt: skip
        if gyro_noise_dps is not None:
            model = replace(model, gyro_noise=math.radians(gyro_noise_dps))
        if fix_sigma_deg is not None:
            model = replace(model, fix_sigma=math.radians(fix_sigma_deg))
            fixes = replace(fixes, fixes=tuple(replace(f, cov=None) for f in fixes.fixes))
        limits = Limits(max_rate_dps or 2000.0, None)
    if rest_s > 0:
        try:
            rb = rest_biases(imu, rest_s, limits)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
        if fixes.planar:
            model = replace(
                model,
                gyro_bias0=float(rb.gyro[2]),
                accel_bias0=tuple(float(x) * 1000.0 for x in rb.accel),
                gyro_bias_sigma=math.radians(0.02),
                accel_bias_sigma=2.0,
            )
        else:
            model = replace(model, gyro_bias0=tuple(float(x) for x in rb.gyro),
                            gyro_bias_sigma=math.radians(0.05))  # fmt: skip
        click.echo(
            f"visvec: biases from {rb.n} samples at rest: gyro "
            f"{[round(math.degrees(x), 4) for x in rb.gyro]} deg/s"
            + (f", accel {[round(float(x), 5) for x in rb.accel]} m/s^2" if rb.accel is not None
               else ""),
            err=True,
        )  # fmt: skip
    samples = run_fusion(imu, fixes.fixes, model, limits=limits, history_s=history_s)
    nis: list[float] = []

    def tap(it):
        for fs in it:
            nis.extend(x for x in fs.nis if math.isfinite(x))
            yield fs

    rows = []
    columns = PoseRow.columns if fixes.planar else AttitudeRow.columns
    with open_out(out) as stream:
        sink = open_sink(fmt, stream, columns)
        for row in fused_rows(tap(samples), model):
            sink.write(row.as_dict())
            rows.append(row)
    n_ok = sum(r.ok for r in rows)
    n_fault = sum("imu_fault" in r.warnings for r in rows)
    n_rej = sum("fix_rejected" in r.warnings for r in rows)
    click.echo(
        f"visvec: {len(rows)} inertial samples, {n_ok} fused; {len(fixes.fixes)} ok fixes, "
        f"{rows[-1].n_points if rows else 0} applied, {n_rej} refused; {n_fault} faulty "
        "samples not integrated",
        err=True,
    )
    if len(nis) >= 5:
        mean = sum(nis) / len(nis)
        advice = ""
        if mean > 6.0:
            advice = "; the filter is overconfident: raise --gyro-noise-dps (or --accel-noise-mps2)"
        elif mean < 1.0:
            advice = "; the filter is too cautious: the noise settings can be lowered"
        click.echo(
            f"visvec: fix innovations: mean NIS {mean:.2f} over {len(nis)} fixes (3 expected "
            f"for a consistent filter){advice}",
            err=True,
        )
    if truth and rows:
        names = rows[0].value_columns
        stats = error_stats(rows, read_truth(truth, names), names)
        for line in stats.lines():
            click.echo(line, err=out is None)
