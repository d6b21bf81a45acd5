"""`visvec check`: the view envelope and the simulated accuracy of a rig's geometry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from visvec.check import envelope, field_of_view_deg, in_view, simulated_accuracy, tilted
from visvec.data import Frame, Status
from visvec.pipeline import TrianglePipeline
from visvec.rig import load_rig
from visvec.rotations import euler_to_matrix, expmap
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

from conftest import CONFIGS, run


def test_tilted_is_a_yaw_then_a_tilt_about_a_horizontal_axis(rng):
    for _ in range(20):
        y, d, t = rng.uniform(-np.pi, np.pi), rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.5)
        R = tilted(np.array([y]), np.array([d]), np.array([t]))[0]
        ref = euler_to_matrix(y, 0.0, 0.0) @ expmap(t * np.array([np.cos(d), np.sin(d), 0.0]))
        np.testing.assert_allclose(R, ref, atol=1e-12)
        # the tilt the pipeline bounds (impossible_tilt): the angle of b3 from n3
        assert math.acos(R[2, 2]) == pytest.approx(t, abs=1e-9)


def test_the_envelope_edge_is_where_the_detector_loses_the_triangle():
    """The example rig: the whole triangle in view up to 10-11 deg of tilt. Rendered at
    the attitude where the grid first lost it (the platform's range opened to 30 deg so
    that impossible_tilt does not decide): ok half a degree inside, refused as partly
    out of view half a degree beyond."""
    rig = load_rig(CONFIGS / "triangle.toml")
    env = envelope(rig)
    assert 10.0 <= env.full_tilt_deg <= 11.0 and env.limit is not None
    assert env.share_at_max == 1.0 and env.level_share == 1.0 and env.fewest_at_max == 3
    wide = replace(rig, max_tilt_deg=30.0)
    pipe = TrianglePipeline(wide)
    yaw, d = np.radians(env.limit)
    rows = {}
    for dt in (-0.5, 0.75):
        R = tilted(np.array([yaw]), np.array([d]), np.radians([env.full_tilt_deg + dt]))[0]
        pipe.reset()
        rows[dt] = pipe.process(Frame(0, 0.0, render_frame(wide, R, Scene(), 3)))
    assert rows[-0.5].status is Status.OK, rows[-0.5].warnings
    assert rows[0.75].status is Status.REJECTED
    assert "partly_out_of_view" in rows[0.75].warnings


def test_a_target_hung_far_off_the_axis_is_out_of_view_at_some_yaws_even_level():
    rig = load_rig(CONFIGS / "triangle.toml")
    tgt = rig.target
    hung = replace(rig, target=replace(tgt, vertices_mm=tgt.vertices_mm + [800.0, 0.0, 0.0]))
    env = envelope(hung)
    assert math.isnan(env.full_tilt_deg)
    assert 0.0 < env.level_share < 1.0
    # the envelope's grid agrees with the points it is made of
    R = tilted(np.zeros(1), np.zeros(1), np.zeros(1))
    assert in_view(hung, R).shape == (1, 3)


def test_markers_envelope_counts_the_leds():
    rig = load_rig(CONFIGS / "markers.toml")
    env = envelope(rig)
    n = len(rig.target.points_b)
    assert env.n_points == n and env.fewest_at_max == n and env.share_at_max == 1.0
    # a camera 5 % nearer sees every LED level, but loses one from 9 deg of tilt
    near = replace(rig, mount=replace(rig.mount, position_mm=rig.mount.position_mm * [1, 1, 0.95]))
    env2 = envelope(near)
    assert env2.level_share == 1.0 and env2.fewest_at_max == n - 1
    assert 5.0 < env2.full_tilt_deg < 12.0 and env2.share_at_max < 1.0


def test_field_of_view_of_a_pinhole():
    rig = load_rig(CONFIGS / "triangle.toml")
    cam = rig.camera
    h, v, diag = field_of_view_deg(rig)
    assert h == pytest.approx(2 * math.degrees(math.atan(cam.width / 2 / cam.fx)), abs=0.05)
    assert v == pytest.approx(2 * math.degrees(math.atan(cam.height / 2 / cam.fy)), abs=0.05)
    assert h < diag < h + v


@pytest.mark.parametrize("kind", ["triangle-320", "markers"])
def test_simulated_accuracy_is_ok_and_within_sigma(kind):
    rig = load_rig(CONFIGS / f"{kind}.toml")
    out = simulated_accuracy(rig, 3, seed=4)
    assert out.n == 3 and out.n_ok == 3, out.reasons()
    assert out.n_outside(3.0) == 0


def test_check_command(tmp_path):
    r = run("check", "--rig", CONFIGS / "triangle-320.toml", "--frames", 3)
    assert r.exit_code == 0, r.output
    assert "field 56.1 x 43.6 deg" in r.stdout
    assert "in view: the whole triangle at every yaw and tilt direction up to" in r.stdout
    assert "ok 3 of 3; RMS error yaw" in r.stdout
    assert "warning" not in r.stderr
    # a platform that tilts further than the camera sees: a warning
    rig = (CONFIGS / "triangle-320.toml").read_text()
    assert "max_tilt_deg = 10.0" in rig
    wide = tmp_path / "wide.toml"
    wide.write_text(rig.replace("max_tilt_deg = 10.0", "max_tilt_deg = 15.0"))
    r = run("check", "--rig", wide, "--frames", 0)
    assert r.exit_code == 0, r.output
    assert "at [platform] max_tilt_deg 15: the whole triangle in view at" in r.stdout
    assert "warning: the target leaves the view within the platform's range" in r.stderr
    assert "simulated" not in r.stdout
    # other kinds: the rig is checked, the rest said not to apply
    r = run("check", "--rig", CONFIGS / "starfield.toml")
    assert r.exit_code == 0 and "for triangle and markers rigs" in r.stdout
    # a bad rig file: exit 2 before anything
    bad = tmp_path / "bad.toml"
    bad.write_text(rig.replace("fx = ", "fxx = ", 1))
    r = run("check", "--rig", bad)
    assert r.exit_code == 2 and "fx" in r.stderr
