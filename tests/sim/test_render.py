"""The renderer (visvec.sim.render): edges where the geometry puts them, the tone curve,
the rolling shutter's row bands."""

from dataclasses import replace

import numpy as np
import pytest

from visvec.geometry import project_target
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene


def test_rolling_shutter_rendering_exposes_each_row_band_at_its_own_attitude(rig640):
    """With a readout time and a body rate, each band of rows is the global-shutter image
    at the attitude of its exposure time (the centre row's attitude given); at rest it is
    the global-shutter image."""
    from visvec.rotations import expmap
    from visvec.sim.render import ROLLING_BAND_ROWS, render_clean

    cam = rig640.camera
    R = euler_to_matrix(0.4, 0.03, -0.02)
    w, ro = np.radians([3.0, -2.0, 20.0]), 25.0  # ms
    np.testing.assert_array_equal(
        render_clean(rig640, R, Scene(), ro, np.zeros(3)), render_clean(rig640, R, Scene())
    )
    img = render_clean(rig640, R, Scene(), ro, w)
    for r0 in (120, 200, 300):  # bands across the triangle
        t = (r0 + 0.5 * (ROLLING_BAND_ROWS - 1) - cam.cy) / cam.height * ro / 1000.0
        ref = render_clean(rig640, R @ expmap(w * t), Scene())
        rows = slice(r0 + 1, r0 + ROLLING_BAND_ROWS - 1)  # away from the band's edges
        np.testing.assert_array_equal(img[rows], ref[rows])
        assert np.abs(ref[rows] - render_clean(rig640, R, Scene())[rows]).max() > 1.0


@pytest.mark.parametrize("phase_px", [0.03, 0.31, 0.47, 0.72])
def test_rendered_edge_along_a_pixel_column_is_where_the_geometry_puts_it(rig320, phase_px):
    """Partial coverage is unbiased for an edge along the pixel grid: at zero yaw the
    triangle's base is a column; moved to sub-pixel phases, the mean coverage of the
    pixels it crosses is the exact fraction within 0.2 % (a regular 8 x 8 sub-pixel grid
    snapped the whole edge to its sub-columns: up to 1/16 px off, which the sensor read
    as a tilt of up to 4 sigma)."""
    from visvec.sim.render import render_clean, subpixel_offsets

    base_u = float(project_target(rig320, np.eye(3))[1, 0])
    # the target moved along n1 so that the base column sits at the phase wanted
    dx_mm = (np.floor(base_u) + phase_px - base_u) * (
        float(rig320.target.vertices_mm[1, 2] - rig320.t_b[2]) / rig320.camera.fx
    )
    world = replace(
        rig320,
        target=replace(rig320.target, vertices_mm=rig320.target.vertices_mm + [dx_mm, 0.0, 0.0]),
    )
    p = project_target(world, np.eye(3))
    u_edge = float(p[1, 0])
    assert abs(u_edge - np.floor(u_edge) - phase_px) < 1e-6
    sc = Scene(gradient_per_m=0.0)
    img = render_clean(world, np.eye(3), sc)
    col = int(np.floor(u_edge + 0.5))  # the column whose pixels the edge crosses
    rows = slice(int(p[:, 1].min()) + 10, int(p[:, 1].max()) - 10)  # clear of the corners
    # the triangle lies on the +u side of its base (the apex points along n1)
    frac = (img[rows, col] - sc.board_level) / sc.contrast
    exact = col + 0.5 - u_edge
    assert abs(frac.mean() - exact) < 0.002
    assert np.abs(frac - exact).max() < 1.0 / 64 + 1e-9  # n-rooks: 64 sub-columns a pixel
    # each pixel's sub-rays: one in each of the n^2 sub-columns and sub-rows
    ou, ov = subpixel_offsets(np.array([3, 7]), np.array([5, 5]), 320, 8)
    for o in (ou, ov):
        assert np.all((o >= -0.5) & (o < 0.5))
        assert np.all(np.diff(np.sort(np.floor((o + 0.5) * 64), axis=1), axis=1) == 1)


def test_tone_curve_keeps_the_output_levels_and_moves_the_edges_outwards(rig640):
    """A webcam's gamma (2.2): the board, triangle and ceiling keep their output grey
    levels, but the blurred edge is bent towards the dark side, so the triangle's
    bright region grows (each edge 0.1-0.2 px outwards: tens of pixels over the
    triangle's outline of about 470 px)."""
    R = euler_to_matrix(0.4, 0.03, -0.02)
    sc = Scene(noise_sigma=0.0, gradient_per_m=0.0, blur_sigma_px=1.0)
    lin = render_frame(rig640, R, sc, rng=0).astype(float)
    bent = render_frame(rig640, R, replace(sc, tone_gamma=2.2), rng=0).astype(float)
    c = np.rint(project_target(rig640, R).mean(axis=0)).astype(int)
    assert bent[c[1], c[0]] == lin[c[1], c[0]] == 98.0  # inside the triangle
    assert bent[5, 5] == lin[5, 5] == 150.0  # the ceiling
    # pixels nearer the triangle's grey than the board's, inside a box round the board
    box = (slice(c[1] - 120, c[1] + 120), slice(c[0] - 120, c[0] + 120))
    grow = np.sum(bent[box] > 84.0) - np.sum(lin[box] > 84.0)
    assert 40 < grow < 250, grow


@pytest.mark.slow  # 4-7 s: the default run stays under 5 minutes
def test_motion_blur_takes_the_exposure_in_ms_as_the_rig_does(rig640):
    """exposure_ms (ms, as [camera] exposure_ms) averages the frame over the attitudes of
    the exposure, centred on R_nb: a 20 ms exposure is the mean of frames spread over
    -10 to +10 ms (to a tenth of its smear: the renderer takes fewer), and smears less
    than the end frame departs; nothing at rest or with no exposure."""
    from visvec.rotations import expmap
    from visvec.sim.render import render_clean

    R = euler_to_matrix(0.4, 0.03, -0.02)
    w = np.radians([0.0, 0.0, 30.0])
    sharp = render_clean(rig640, R, Scene())
    np.testing.assert_array_equal(render_clean(rig640, R, Scene(), 0.0, w, 0.0), sharp)
    np.testing.assert_array_equal(render_clean(rig640, R, Scene(), 0.0, np.zeros(3), 20.0), sharp)
    blurred = render_clean(rig640, R, Scene(), 0.0, w, 20.0)
    taus = ((np.arange(40) + 0.5) / 40 - 0.5) * 0.02  # s
    spread = np.mean([render_clean(rig640, R @ expmap(w * t), Scene()) for t in taus], axis=0)
    smear = np.abs(blurred - sharp).sum()
    assert np.abs(blurred - spread).sum() < 0.1 * smear, (np.abs(blurred - spread).sum(), smear)
    end = np.abs(render_clean(rig640, R @ expmap(w * 0.01), Scene()) - sharp).sum()
    assert 0.05 * end < smear < 0.5 * end, (smear, end)
