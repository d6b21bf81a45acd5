"""Spots (visvec.detect.spots): windows found in one pass are the windows found one by
one."""

import numpy as np

from visvec.detect.spots import find_spots
from visvec.rotations import euler_to_matrix
from visvec.sim.markers import SpotScene, render_markers

from conftest import CONFIGS


def test_windows_in_one_pass_find_what_each_window_finds_alone():
    """A tracked markers frame searches a window per LED, all on one canvas: the same
    spots as each window searched alone (a spot cut by its window's edge left out, one
    seen in two overlapping windows counted once, windows reaching past the frame
    clipped), to rounding."""
    from visvec.rig import load_rig

    rig = load_rig(CONFIGS / "markers.toml")
    rng = np.random.default_rng(5)
    img = render_markers(rig, euler_to_matrix(0.4, 0.1, -0.05), SpotScene(reflections=3), 2)
    full = find_spots(img)
    assert len(full.centroids_px) >= 10
    wins = []
    for u, v in full.centroids_px:
        dx, dy = rng.integers(-8, 8, 2)
        wins.append((int(u) - 12 + int(dx), int(v) - 12, int(u) + 12, int(v) + 12 + int(dy)))
    u0, v0 = full.centroids_px[0].astype(int)
    wins += [(u0 - 20, v0 - 20, u0 + 20, v0 + 20), (-5, -5, 30, 30), (100, 100, 101, 300)]
    together = find_spots(img, 0.0, 3, 400, wins)
    alone = [find_spots(img, together.threshold, 3, 400, [w]) for w in wins]
    pts = np.concatenate([a.centroids_px for a in alone if len(a.centroids_px)])
    # each window alone, the same spot from two windows once
    uniq = []
    for p in pts:
        if not any(np.hypot(*(p - q)) < 0.5 for q in uniq):
            uniq.append(p)
    uniq = np.array(uniq)
    got = together.centroids_px
    assert len(got) == len(uniq)
    assert len(got) < len(wins)  # some windows cut their spot, two share one
    np.testing.assert_allclose(got[np.lexsort(got.T)], uniq[np.lexsort(uniq.T)], atol=1e-9)
