"""`visvec plot`: a run's figure for a report."""

from __future__ import annotations

import click

from visvec.cli.common import check_output, note_inputs

FORMATS = (".png", ".svg", ".pdf")


@click.command()
@click.argument("rows", type=click.Path(dir_okay=False))
@click.option("--truth", type=click.Path(dir_okay=False), default=None,
              help="Truth CSV (from `visvec simulate`): add the errors and the histogram of "
              "error over sigma.")  # fmt: skip
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="The figure: .png, .svg or .pdf.")  # fmt: skip
@click.option("--title", default=None, help="The figure's title (default: the file's name).")
def plot(rows, truth, out, title):
    """Draw ROWS (a CSV or JSON-lines file of visvec rows: attitude, rate, planar pose or
    fused rows): the values against time with their 1-sigma bands and the rows' statuses;
    with --truth, the errors with their 1- and 3-sigma bands and the histogram of error
    over sigma against the Gaussian. Needs matplotlib (pip install "visvec[plot]")."""
    if not out.lower().endswith(FORMATS):
        raise click.BadParameter(f"{out}: expected a .png, .svg or .pdf file", param_hint="--out")
    note_inputs(rows, truth)
    check_output(out)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise click.UsageError('visvec plot needs matplotlib: pip install "visvec[plot]"') from None
    from visvec.plot import plot_run

    drew = plot_run(rows, out, truth, title)
    text = f"wrote {out}: {drew['ok']} of {drew['rows']} {drew['kind']} rows ok"
    if "rms" in drew:
        rms = ", ".join(f"{k} {v:.4g}" for k, v in drew["rms"].items() if v is not None)
        text += f"; RMS error {rms}; {100 * drew['beyond_3sigma_share']:.2f} % beyond 3 sigma"
    click.echo(text, err=True)
