"""The markers' identification (visvec.detect.markers): its grid search's test of which
projected markers land near a spot."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from visvec.detect.markers import GATE_CHUNK, SpotGate


@pytest.mark.parametrize("seed", range(6))
def test_the_spot_gate_answers_as_a_bounded_kd_tree_query(seed):
    """The grid and distance transform decide the points clear of the gate, the k-d
    tree the rest: the same answer as the k-d tree alone for every point, among them
    points a hair inside and outside the gate of a spot, over more points than one
    chunk; a point that is not finite is near no spot (the k-d tree refuses one)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    spots = rng.uniform(-0.3, 0.3, (n, 2))
    gate = float(rng.uniform(0.005, 0.05))
    k = rng.integers(0, n, 2000)
    ang = rng.uniform(0.0, 2.0 * np.pi, 2000)
    r = gate * (1.0 + rng.choice([-1e-9, 1e-9, -1e-6, 1e-6, -0.02, 0.02], 2000))
    at_gate = spots[k] + r[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    pts = np.vstack([rng.uniform(-0.5, 0.5, (GATE_CHUNK + 5000, 2)), at_gate])
    want = np.isfinite(cKDTree(spots).query(pts, distance_upper_bound=gate)[0])
    got = SpotGate(spots, gate).near(pts)
    assert np.array_equal(got, want)
    assert 0 < want.sum() < len(pts) and want[-2000:].sum() > 500
    odd = np.array([[np.nan, 0.0], [np.inf, 0.0], [0.0, -np.inf], spots[0]])
    assert SpotGate(spots, gate).near(odd).tolist() == [False, False, False, True]
    assert not SpotGate(np.zeros((0, 2)), gate).near(pts[:10]).any()
