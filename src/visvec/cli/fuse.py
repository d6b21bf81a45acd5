"""`visvec fuse`: inertial samples and late camera fixes fused at the inertial rate."""

from __future__ import annotations

import math
import queue
from contextlib import ExitStack
from dataclasses import replace

import click
import numpy as np

from visvec.cli.common import (
    FiniteFloat,
    KindCommand,
    check_output,
    foxglove_option,
    note_inputs,
    result_options,
    rows_out,
)
from visvec.cli.progress import Work
from visvec.cli.results import check_results, write_results
from visvec.cli.view import foxglove_live, foxglove_server, say_published
from visvec.errors import ConfigError, InputFileError, NoOkRows
from visvec.evaluate import error_stats, read_truth
from visvec.fuse.inputs import read_fixes, read_imu
from visvec.fuse.live import Reader, is_live, run_live
from visvec.fuse.options import FusionOptions, engine_from_options, model_from_options
from visvec.fuse.replay import Fusion
from visvec.fuse.replay import fuse as run_fusion
from visvec.fuse.run import fused_rows, rest_biases
from visvec.output import AttitudeRow, PoseRow
from visvec.rotations import logmap
from visvec.sinks import row_writer
from visvec.sinks.foxglove import Published


@click.command(cls=KindCommand)
@click.option("--imu", "imu_path", required=True, metavar="SOURCE",
              help="Inertial rows: time_s and gz_dps,ax_mps2,ay_mps2 (planar) or "
              "gx_dps,gy_dps,gz_dps (3-D). SOURCE: a CSV file, - (stdin), udp://HOST:PORT "
              "or serial:///dev/DEVICE?baud=N (live).")  # fmt: skip
@click.option("--fixes", "fixes_path", required=True, metavar="SOURCE",
              help="visvec output rows (planar pose or attitude), a SOURCE as --imu; time_s "
              "is the exposure (on the IMU's clock), latency_ms when it became available "
              "(files; live fixes are available when they arrive).")  # fmt: skip
@click.option("--follow", is_flag=True,
              help="Read files as they grow (a recording still being written): live.")  # fmt: skip
@click.option("--max-samples", type=click.IntRange(min=1), default=None,
              help="Live: stop after this many fused rows.")  # fmt: skip
@click.option("--silent-s", type=FiniteFloat(min=0, min_open=True), default=2.0,
              show_default=True,
              help="Live: a source silent this long is reported (rows: fixes_silent).")  # fmt: skip
@click.option("--gyro-range-dps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="The gyro's range (its datasheet's, every axis): readings at it are "
              "saturated, readings beyond it refused [an IMU file's '# gyro_range_dps = N' "
              "header; else learned only from flat tops a turning gyro cannot make].")  # fmt: skip
@click.option("--out", default=None, type=click.Path(dir_okay=False),
              help="Output file, or udp://HOST:PORT for one datagram per row (default: "
              "stdout).")  # fmt: skip
@click.option("--format", "fmt", type=click.Choice(["csv", "jsonl"]), default="csv",
              show_default=True,
              help="Row format: CSV with a header, or JSON lines (one object per row, the "
                   "same keys).")  # fmt: skip
@click.option(
    "--method",
    type=click.Choice(["kalman", "paper"]),
    default="kalman",
    show_default=True,
    help="Planar: Kalman filter with biases, or the paper's reset at each fix.",
)
@click.option("--rest-s", type=FiniteFloat(min=0), default=0.0, show_default=True,
              help="Seconds at rest at the start: average them for the biases.")  # fmt: skip
@click.option("--max-rate-dps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="Rates beyond this are faults [planar: 50 (the paper), 3-D: 2000].")  # fmt: skip
@click.option("--max-accel-mps2", type=FiniteFloat(min=0, min_open=True), default=0.5,
              show_default=True, help="Planar: accelerations beyond this are faults.")  # fmt: skip
@click.option("--gyro-noise-dps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="Gyro white noise per sample [planar 0.05, 3-D 0.3].")  # fmt: skip
@click.option("--accel-noise-mps2", type=FiniteFloat(min=0, min_open=True),
              default=0.002, show_default=True,
              help="Planar: accelerometer white noise per sample (the paper's).")  # fmt: skip
@click.option("--fix-sigma-deg", type=FiniteFloat(min=0, min_open=True), default=None,
              help="3-D: fix attitude noise, overriding the fixes' sigma columns.")  # fmt: skip
@click.option("--clock-jitter-ms", type=FiniteFloat(min=0), default=None,
              help="3-D: 1-sigma jitter of the gyro's clock against the fixes' [one IMU "
              "sample period; 0 when one clock triggers both].")  # fmt: skip
@click.option(
    "--no-misalignment",
    is_flag=True,
    help="3-D: do not estimate the gyro misalignment to the fixes' body axes.",
)
@click.option("--history-s", type=FiniteFloat(min=0.1), default=10.0, show_default=True,
              help="Inertial history kept for replaying late fixes.")  # fmt: skip
@click.option("--truth", default=None, type=click.Path(dir_okay=False),
              help="Truth per inertial sample (frame = sample index): print error "
              "statistics.")  # fmt: skip
@foxglove_option
@result_options
def fuse(imu_path, fixes_path, follow, max_samples, silent_s, gyro_range_dps, out, fmt, method,
         rest_s, max_rate_dps, max_accel_mps2, gyro_noise_dps, accel_noise_mps2, fix_sigma_deg,
         clock_jitter_ms, no_misalignment, history_s, truth, errors, summary):  # fmt: skip
    """Fuse an IMU with late camera fixes: one row per inertial sample, causal (the row
    at time t uses the samples up to t and the fixes available by t). From files, or
    live from streams (stdin, UDP, a serial device, a file being written)."""
    opts = FusionOptions(method, gyro_noise_dps, accel_noise_mps2, fix_sigma_deg,
                         not no_misalignment, max_rate_dps, max_accel_mps2, clock_jitter_ms,
                         gyro_range_dps, history_s)  # fmt: skip
    note_inputs(imu_path, fixes_path, truth)
    check_results(truth, errors, summary)
    check_output(out)
    if is_live(imu_path, follow) or is_live(fixes_path, follow):
        if truth or rest_s or errors or summary:
            raise click.UsageError("--truth, --errors, --summary and --rest-s apply to files, "
                                   "not live sources")  # fmt: skip

        setup = live_setup(opts)
        _run_live(imu_path, fixes_path, follow, max_samples, silent_s, setup, out, fmt)
        return
    if click.get_current_context().meta.get("visvec.foxglove") is not None:
        raise click.UsageError(
            "--foxglove applies to live sources (a stream, --follow); a file's fused rows: "
            "--out run.mcap, then open it in Foxglove"
        )
    fixes = read_fixes(fixes_path)
    imu = read_imu(imu_path, planar=fixes.planar)
    _check_files(imu, fixes, imu_path, fixes_path)
    opts = with_declared_range(opts, imu.gyro_range_dps, imu_path)
    model, limits = options_model(fixes.planar, imu.period_s, opts)
    if fix_sigma_deg is not None:
        fixes = replace(fixes, fixes=tuple(replace(f, cov=None) for f in fixes.fixes))
    if rest_s > 0:
        model = _with_rest_biases(model, imu, rest_s, limits, fixes.planar)
    engine_ = Fusion(model, limits=limits, history_s=history_s,
                     gyro_range_dps=opts.gyro_range_dps)  # fmt: skip
    samples = run_fusion(imu, fixes.fixes, model, engine=engine_)
    nis: list[float] = []
    last = [None]

    def tap(it):
        for fs in it:
            nis.extend(x for x in fs.nis if math.isfinite(x))
            if fs.state is not None:
                last[0] = fs.state
            yield fs

    rows = []
    columns = PoseRow.columns if fixes.planar else AttitudeRow.columns
    with rows_out(out, fmt, columns) as sink, Work("fuse", len(imu.t), unit="sample") as bar:
        write = row_writer(sink)
        for row in fused_rows(tap(samples), model):
            write(row)
            rows.append(row)
            bar.update(1)
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
        click.echo(nis_line(nis, fixes.planar), err=True)
    echo_learned(engine_, last[0])
    if rows and n_ok == 0:
        raise NoOkRows(f"none of the {len(rows)} inertial samples gave a fused row (no fix "
                       "could start the filter)")  # fmt: skip
    if rows and (truth or summary):
        names = rows[0].value_columns
        truth_rows = read_truth(truth, names) if truth else None
        stats = error_stats(rows, truth_rows, names) if truth_rows is not None else None
        for line in stats.lines() if stats is not None else ():
            click.echo(line, err=out is None)
        write_results(errors, summary, rows, truth_rows, stats, names)


def _check_files(imu, fixes, imu_path: str, fixes_path: str) -> None:
    """Said before fusing: the IMU's gaps, and fixes outside its time span (refused
    when none is inside: the two are not on one clock)."""
    for k in imu.gaps:
        click.echo(
            f"visvec: {imu_path}: line {imu.lines[k]}: gap of {imu.t[k] - imu.t[k - 1]:.3f} s "
            f"after t = {imu.t[k - 1]:.3f} s (period {imu.period_s:.4f} s): not integrated "
            "over; fusion restarts at the next fix",
            err=True,
        )
    if not fixes.fixes:
        click.echo(f"visvec: {fixes_path}: no ok fixes among {fixes.n_rows} rows", err=True)
        return
    ft = [f.time_s for f in fixes.fixes]
    inside = sum(imu.t[0] <= x <= imu.t[-1] for x in ft)
    if inside == 0:
        raise InputFileError(
            f"{fixes_path}: none of the {len(ft)} ok fixes lies within the IMU's time span "
            f"({imu.t[0]:.3f} to {imu.t[-1]:.3f} s; the fixes' time_s run from "
            f"{min(ft):.3f} to {max(ft):.3f} s): both must be on one clock"
        )
    if inside < len(ft):
        click.echo(
            f"visvec: {fixes_path}: {len(ft) - inside} of {len(ft)} ok fixes lie outside "
            f"the IMU's time span ({imu.t[0]:.3f} to {imu.t[-1]:.3f} s) and are not used",
            err=True,
        )


def _with_rest_biases(model, imu, rest_s: float, limits, planar: bool):
    """The model with its biases started from the first ``rest_s`` seconds (--rest-s),
    said on stderr."""
    try:
        rb = rest_biases(imu, rest_s, limits)
    except ValueError as exc:
        raise click.UsageError(f"--rest-s {rest_s:g}: {exc}") from None
    if planar:
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
    return model


def nis_line(nis: list[float], planar: bool) -> str:
    """The fixes' mean normalised innovation squared against the 3 a consistent filter
    gives, and what a mean far from it says."""
    mean = sum(nis) / len(nis)
    advice = ""
    if mean > 6.0 and not planar:
        advice = ("; the fixes disagree with the gyro beyond its learned noise: glitches in "
                  "the fixes, or a gyro beyond its range")  # fmt: skip
    elif mean > 6.0:
        advice = "; the filter is overconfident: raise --gyro-noise-dps (or --accel-noise-mps2)"
    elif mean < 1.0 and not planar:
        advice = ("; the fixes agree better than the noise learned so far says (it starts "
                  "from a cautious prior: a short run)")  # fmt: skip
    elif mean < 1.0:
        advice = "; the filter is too cautious: the noise settings can be lowered"
    return (f"visvec: fix innovations: mean NIS {mean:.2f} over {len(nis)} fixes (3 expected "
            f"for a consistent filter){advice}")  # fmt: skip


def options_model(planar: bool, period_s: float | None, opts: FusionOptions):
    """The filter and fault limits the options ask for (model_from_options), an option
    that does not apply refused as a usage error."""
    try:
        return model_from_options(planar, period_s, opts)
    except ValueError as exc:
        raise click.UsageError(f"{exc}") from None


def live_setup(opts: FusionOptions):
    """A live fusion's ``setup(planar)`` (visvec.fuse.live.run_live): the engine the
    options ask for, made once the first inertial row tells the kind, and its filter."""

    def setup(planar: bool):
        eng = engine(planar, None, opts)
        return eng, eng.model

    return setup


def engine(planar: bool, period_s: float | None, opts: FusionOptions) -> Fusion:
    """The fusion engine the options ask for (engine_from_options), an option that does
    not apply refused as a usage error."""
    try:
        return engine_from_options(planar, period_s, opts)
    except ValueError as exc:
        raise click.UsageError(f"{exc}") from None


def with_declared_range(opts: FusionOptions, declared: float | None, where: str,
                        ) -> FusionOptions:  # fmt: skip
    """The options with the gyro's range a description declares (an IMU file's header,
    a rig's [imu]) where --gyro-range-dps gives none; said on stderr, and a
    disagreement with the option too (the option wins)."""
    if declared is None:
        return opts
    if opts.gyro_range_dps is None:
        click.echo(f"visvec: {where}: gyro range {declared:g} deg/s (declared)", err=True)
        return replace(opts, gyro_range_dps=declared)
    if declared != opts.gyro_range_dps:
        click.echo(f"visvec: --gyro-range-dps {opts.gyro_range_dps:g} overrides {where}'s "
                   f"{declared:g} deg/s", err=True)  # fmt: skip
    return opts


def learned_of(engine, s=None) -> str | None:
    """The closing line of what the filter learned by the state ``s`` (default the
    engine's newest), or None (no state yet; the planar reset rule, which learns
    nothing)."""
    if s is None and engine is not None:
        s = engine.state
    if s is None:
        return None
    if engine.model.planar:
        if engine.model.method != "kalman":
            return None
        return planar_learned_line(s, engine.model.time_offset_sigma)
    return learned_line(engine, s)


def echo_learned(engine, s=None) -> None:
    """Say on stderr what the filter learned (learned_of), when it learned anything."""
    line = learned_of(engine, s)
    if line:
        click.echo(line, err=True)


# the fixes' time offset counts as learned once its sigma is under this share of the
# prior's (PlanarModel.time_offset_sigma): before that (one fix, fixes too far apart
# in time for the motion to show it) the line says so, not the prior's +- 50 ms
OFFSET_LEARNED_SHARE = 0.5


def planar_learned_line(s, prior_s: float) -> str:
    """What the planar Kalman filter learned (visvec.fuse.planar.PlanarModel), with
    1-sigma: the fixes' time offset (``prior_s``: its prior sigma), the gyro's and the
    accelerometers' biases."""
    sd = np.sqrt(np.clip(np.diag(s.P), 0.0, None))
    x = s.x
    if not sd[8] < OFFSET_LEARNED_SHARE * prior_s:
        offset = (f"fixes' time offset not yet (too few fixes with motion between them; "
                  f"prior +- {1000 * prior_s:.0f} ms)")  # fmt: skip
    else:
        offset = (f"fixes' time offset {1000 * x[8]:+.1f} +- {1000 * sd[8]:.1f} ms (their "
                  "time_s after their exposure)")  # fmt: skip
    return (
        f"visvec: learned: {offset}; gyro bias {math.degrees(x[5]):+.3f} +- "
        f"{math.degrees(sd[5]):.3f} deg/s; accelerometer biases {x[6] / 1000:+.4f}, "
        f"{x[7] / 1000:+.4f} +- {sd[6] / 1000:.4f} m/s^2"
    )


def learned_line(engine, s) -> str:
    """What the 3-D filter learned of the gyro (model doc: visvec.fuse.attitude)."""
    qa, qw = s.noise.theta()
    per_sample = math.degrees(math.sqrt(qa / engine.model.sample_s))
    parts = [f"gyro noise {per_sample:.3g} deg/s per sample",
             f"rate error {100 * math.sqrt(qw):.2g} % (held between fixes)",
             f"time offset {1000 * s.tau:+.1f} ms (clock drift {1e6 * s.drift:+.0f} ppm)",
             f"misalignment {math.degrees(float(np.linalg.norm(logmap(s.Rm)))):.2f} deg",
             f"scale factors {', '.join(f'{100 * k:+.2f}' for k in s.k)} %",
             f"bias {', '.join(f'{math.degrees(b):+.3f}' for b in s.b)} deg/s"]  # fmt: skip
    if engine.rest is not None:
        parts.append(f"rest segment {engine.rest.n} samples")
    parts.append(range_words(engine.saturation))
    return "visvec: learned: " + "; ".join(parts)


def range_words(sat) -> str:
    """What the run knows of the gyro's range (visvec.fuse.saturation.Saturation)."""
    if sat.declared is not None:
        words = (f"gyro range {math.degrees(sat.declared):g} deg/s (declared), "
                 f"{sat.n_saturated} samples at it")  # fmt: skip
        if sat.n_beyond:
            words += f", {sat.n_beyond} beyond it refused (gyro_beyond_range)"
        return words
    maybe = (f"; {sat.n_maybe} samples on flat tops too quiet for its noise kept as read, "
             "with a sigma as if clipped" if sat.n_maybe else "")  # fmt: skip
    if not sat.learned:
        return "gyro range not seen (no flat top of a clipping gyro; none assumed)" + maybe
    levels = ", ".join(f"{'+' if side == 0 else '-'}{math.degrees(v):.1f} on {'xyz'[ax]}"
                       for ax, side, v in sat.learned)  # fmt: skip
    return (f"gyro range learned from its flat tops: {levels} deg/s, {sat.n_saturated} "
            "samples at it" + maybe)  # fmt: skip


def live_summary(summary) -> str:
    """The end-of-run line of a live fusion."""
    lat = summary.latencies_ms
    med = f", row latency median {lat.median():.2f} ms" if len(lat) else ""
    bad = "; ".join(f"{n} malformed {k} rows skipped" for k, n in summary.bad.items())
    return (
        f"visvec: {summary.samples} inertial samples, {summary.ok} fused; {summary.fixes} ok "
        f"fixes{med}" + (f"; {bad}" if bad else "")
        + ("; stopped early (Ctrl-C or a signal)" if summary.interrupted else "")
    )  # fmt: skip


def _run_live(imu_src, fixes_src, follow, max_samples, silent_s, setup, out, fmt):
    events: queue.Queue = queue.Queue()
    readers = [Reader("imu", imu_src, events, follow), Reader("fix", fixes_src, events, follow)]
    if imu_src == "-" and fixes_src == "-":
        raise click.UsageError("--imu and --fixes cannot both be - (standard input)")
    for r in readers:
        try:
            r.check()
        except (ConfigError, InputFileError) as exc:
            raise click.BadParameter(str(exc), param_hint="--imu" if r.name == "imu" else
                                     "--fixes") from None  # fmt: skip
    with ExitStack() as stack:
        fox = foxglove_server()  # a port in use: exit 2, before the streams are read
        if fox is not None:
            stack.callback(fox.stop)

        def open_rows(planar: bool):
            # opened once the kind is known (the first rows say it)
            cols = PoseRow.columns if planar else AttitudeRow.columns
            sink = stack.enter_context(rows_out(out, fmt, cols))
            if fox is None:
                return sink
            live = foxglove_live(fox, cols, None, image=False)
            stack.callback(say_published, live, False)
            return Published(sink, live)

        summary = run_live(*readers, setup, open_rows, max_samples=max_samples,
                           silent_s=silent_s, echo=lambda m: click.echo(m, err=True))  # fmt: skip
    click.echo(live_summary(summary), err=True)
    echo_learned(summary.engine)
