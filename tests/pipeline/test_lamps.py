"""Lamp maps, the Delaunay catalogue and the lamps rig (the ZARM LuVeX method)."""

import numpy as np
import pytest
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.errors import ConfigError
from visvec.lamps import build_catalog, load_catalog, read_lamp_map, triangle_features
from visvec.rig import load_rig

from conftest import CONFIGS, rig_variant

MAP = CONFIGS / "lamps.csv"


def write(tmp_path, text, name="map.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_example_map_and_its_catalogue():
    lamps = read_lamp_map(MAP, 2500.0)
    assert len(lamps) == 180 and np.all(lamps.xyz_mm[:, 2] == 2500.0)
    cat = build_catalog(lamps)
    assert 300 <= len(cat.triangles) <= 360  # the paper: 322 triangles for ~180 lamps
    f = cat.features
    assert np.all((f[:, 0] >= 3.0) & (f[:, 0] <= 60.0) & (f[:, 1] >= 60.0) & (f[:, 1] < 180))
    # each vertex's angle from the dot product of its two edges (not the law of
    # cosines the catalogue uses)
    p = cat.lamps_mm[cat.triangles][:, :, :2]

    def angle(at, u, v):
        e1, e2 = u - at, v - at
        cos = np.sum(e1 * e2, axis=1) / np.linalg.norm(e1, axis=1) / np.linalg.norm(e2, axis=1)
        return np.degrees(np.arccos(cos))

    ang = np.column_stack([angle(p[:, 0], p[:, 1], p[:, 2]), angle(p[:, 1], p[:, 2], p[:, 0]),
                           angle(p[:, 2], p[:, 0], p[:, 1])])  # fmt: skip
    np.testing.assert_allclose(f, np.column_stack([ang.min(axis=1), ang.max(axis=1)]), atol=1e-9)
    # canonical order: the smallest angle's lamp first, then counter-clockwise
    assert np.all(ang[:, 0] <= ang[:, 1:].min(axis=1) + 1e-9)
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    assert np.all(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)


def test_lookup_is_invariant_to_position_heading_and_scale(rng):
    cat = build_catalog(read_lamp_map(MAP, 2500.0))
    for k in rng.choice(len(cat.triangles), 20, replace=False):
        p = cat.lamps_mm[cat.triangles[k], :2]
        a = rng.uniform(-np.pi, np.pi)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        q = (p @ R.T) * rng.uniform(0.1, 3.0) + rng.uniform(-1e3, 1e3, 2)
        q = q[rng.permutation(3)]  # any vertex order
        order, feat = triangle_features(q[None])
        hits = cat.lookup(feat[0], 0.2)
        assert k in hits
        # the canonical order gives the same lamps in the same order
        np.testing.assert_allclose(
            ((q[order[0]] - q[order[0]].mean(0)) @ R)
            / np.linalg.norm(q[order[0]][1] - q[order[0]][0]),
            (p - p.mean(0)) / np.linalg.norm(p[1] - p[0]),
            atol=1e-9,
        )


def test_catalogue_round_trip_and_cli(tmp_path):
    out = tmp_path / "cat.npz"
    res = CliRunner().invoke(cli, ["catalog", "build", str(MAP), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "180 lamps" in res.output
    cat = load_catalog(out)
    ref = build_catalog(read_lamp_map(MAP, 2500.0))
    np.testing.assert_array_equal(cat.triangles, ref.triangles)
    np.testing.assert_allclose(cat.lookup(ref.features[3], 0.01), [3])
    res = CliRunner().invoke(
        cli, ["catalog", "build", str(tmp_path / "nope.csv"), "--out", str(out)]
    )
    assert res.exit_code == 2 and "nope.csv" in res.output


def test_bad_maps_are_refused_naming_the_line(tmp_path):
    with pytest.raises(ConfigError, match="columns x_mm,y_mm"):
        read_lamp_map(write(tmp_path, "x,y\n1,2\n"), 2500)
    with pytest.raises(ConfigError, match="line 3"):
        read_lamp_map(write(tmp_path, "x_mm,y_mm\n0,0\n1,abc\n5,5\n"), 2500)
    with pytest.raises(ConfigError, match="lines 2 and 4"):
        read_lamp_map(write(tmp_path, "x_mm,y_mm\n0,0\n900,0\n0.5,0.2\n0,900\n"), 2500)
    with pytest.raises(ConfigError, match="one line"):
        read_lamp_map(write(tmp_path, "x_mm,y_mm\n0,0\n500,500\n1000,1000\n"), 2500)
    with pytest.raises(ConfigError, match="above the camera"):
        read_lamp_map(write(tmp_path, "x_mm,y_mm,z_mm\n0,0,-5\n500,0,\n0,500,\n"), 2500)


def test_collinear_lamps_inside_the_map_are_warned(tmp_path):
    # a row of lamps nearly on one line, far from the others: Delaunay must join them
    # in slivers, which cannot be told apart by shape
    row = [(0, 0), (1000, 5), (2000, 0), (3000, 5), (4000, 0), (5000, 5), (6000, 0)]
    far = [(3000, 90_000), (3000, -90_000), (-80_000, 0), (86_000, 0)]
    text = "x_mm,y_mm\n" + "".join(f"{x},{y}\n" for x, y in row + far)
    lamps = read_lamp_map(write(tmp_path, text), 2500)
    with pytest.warns(UserWarning, match="nearly collinear"):
        cat = build_catalog(lamps)
    assert cat.features[:, 0].min() >= 3.0


def test_lamps_rig(tmp_path):
    rig = load_rig(CONFIGS / "lamps.toml")
    assert rig.kind == "lamps" and len(rig.target.lamps) == 180
    text = (CONFIGS / "lamps.toml").read_text()
    (tmp_path / "lamps.csv").write_text(MAP.read_text())
    bad = write(tmp_path, text.replace('on = "platform"', 'on = "lab"'), "a.toml")
    with pytest.raises(ConfigError, match="on = 'lab'"):
        load_rig(bad)
    bad = write(tmp_path, text.replace('map = "lamps.csv"', 'map = "none.csv"'), "b.toml")
    with pytest.raises(ConfigError, match="none.csv"):
        load_rig(bad)
    down = text.replace("rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]",
                        "rotation = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]")  # fmt: skip
    with pytest.raises(ConfigError, match="looks down"):
        load_rig(write(tmp_path, down, "c.toml"))


@pytest.mark.slow  # 4-7 s: the default run stays under 5 minutes
def test_catalog_build_and_check_say_how_unique_the_maps_triangles_are(tmp_path):
    """Issue 35: with a rig, `catalog build` says how many map triangles fit in its view
    and the share with a rival within the few-lamps lookup's tolerance; a regular grid
    (every triangle repeated by a translation: all rivals, separated by 0 mm) is warned
    about, here and by `visvec check`; the shipped map is not."""
    rig = CONFIGS / "lamps.toml"
    res = CliRunner().invoke(cli, ["catalog", "build", str(MAP), "--out", str(tmp_path / "c.npz"),
                                   "--rig", str(rig)])  # fmt: skip
    assert res.exit_code == 0, res.output
    share = float(res.output.split("lamp triangles fit in the view; ")[1].split(" %")[0])
    assert share < 5.0 and "warning" not in res.output
    grid = tmp_path / "grid.csv"
    grid.write_text("x_mm,y_mm\n" + "".join(f"{500 * x},{500 * y}\n" for x in range(-7, 8)
                                            for y in range(-5, 6)))  # fmt: skip
    res = CliRunner().invoke(cli, ["catalog", "build", str(grid), "--out",
                                   str(tmp_path / "g.npz"), "--rig", str(rig)])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "100.0 % have a rival" in res.output and "differ by 0.00 mm" in res.output
    assert f"warning: {grid}: 100 % of the map's triangles in view have a rival" in res.output
    gridded = rig_variant(rig, "map", '"lamps.csv"', f'"{grid}"', tmp_path / "grid.toml")
    res = CliRunner().invoke(cli, ["check", "--rig", str(gridded)])
    assert res.exit_code == 0, res.output
    assert "lamp map: " in res.output and "100 % of the map's triangles" in res.output
    triangle = str(CONFIGS / "triangle.toml")
    res = CliRunner().invoke(cli, ["catalog", "build", str(grid), "--out",
                                   str(tmp_path / "x.npz"), "--rig", triangle])  # fmt: skip
    assert res.exit_code == 2 and not (tmp_path / "x.npz").exists()
