"""`visvec catalog build`: the Delaunay triangle catalogue of a ceiling lamp map."""

from __future__ import annotations

import warnings

import click

from visvec.cli.common import FiniteFloat, load
from visvec.lamps import build_catalog, read_lamp_map


@click.group()
def catalog() -> None:
    """Lamp-map catalogues (lamps target)."""


@catalog.command()
@click.argument("map_path", metavar="MAP", type=click.Path(dir_okay=False))
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False), help="Catalogue file (.npz)."
)
@click.option(
    "--ceiling-z-mm",
    type=FiniteFloat(min=0, min_open=True),
    default=2500.0,
    show_default=True,
    help="Lamp height where the map has no z_mm.",
)
@click.option("--rig", "rig_path", default=None, type=click.Path(dir_okay=False),
              help="A lamps rig whose camera sees this map: also say how unique the map's "
              "triangles are in its view (three lamps lit identify the pose only where "
              "their triangle has no rival).")  # fmt: skip
def build(map_path, out, ceiling_z_mm, rig_path) -> None:
    """Delaunay triangles of the lamps in MAP (CSV x_mm,y_mm[,z_mm]) with their smallest
    and largest angles, indexed for lookup; written to --out."""
    rig = None
    if rig_path is not None:
        rig = load(rig_path, kind="lamps", what="catalog build --rig")
    lamps = read_lamp_map(map_path, ceiling_z_mm)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cat = build_catalog(lamps)
    for w in caught:
        click.echo(f"visvec: warning: {w.message}", err=True)
    path = cat.save(out)
    click.echo(
        f"{len(lamps)} lamps, {len(cat.triangles)} triangles "
        f"(smallest angle {cat.features[:, 0].min():.1f}-{cat.features[:, 0].max():.1f} deg) "
        f"-> {path}"
    )
    if rig is not None:
        from dataclasses import replace

        from visvec.detect.lamps import LampIdentifier

        seen = replace(rig, target=replace(rig.target, lamps=lamps))
        u = LampIdentifier(seen, cat).uniqueness()
        click.echo(f"in the view of {rig_path}: {u.words()}")
        if u.too_few_unique:
            click.echo(f"visvec: warning: {map_path}: {u.warning()}", err=True)
