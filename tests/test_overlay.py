"""Overlays of the markers, lamps and star-field pipelines: each identified spot, lamp or
star is drawn where the detection put it, in the colour that says what it is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from visvec.cli.main import cli
from visvec.overlay import draw_overlay
from visvec.pipeline import make_pipeline
from visvec.rig import load_rig
from visvec.sources import open_source

from conftest import ROOT

GREEN, BLUE, YELLOW = (60, 200, 60), (230, 120, 30), (0, 220, 230)


def frames_of(kind: str, tmp_path: Path, n: int, *extra):
    rig_path = ROOT / "configs" / f"{kind}.toml"
    rec = tmp_path / kind
    r = CliRunner().invoke(cli, ["simulate", "--rig", str(rig_path), "--out", str(rec),
                                 "--frames", str(n), *map(str, extra)])  # fmt: skip
    assert r.exit_code == 0, r.output
    rig = load_rig(rig_path)
    return rig, list(open_source(str(rec), fps=rig.fps))


def colour_near(img: np.ndarray, uv, colour, radius: int) -> int:
    """Pixels of ``colour`` (within 40 levels on each channel) within ``radius`` of uv."""
    u, v = int(round(uv[0])), int(round(uv[1]))
    h, w = img.shape[:2]
    box = img[
        max(v - radius, 0) : min(v + radius + 1, h), max(u - radius, 0) : min(u + radius + 1, w)
    ]
    return int(np.sum(np.all(np.abs(box.astype(int) - colour) < 40, axis=2)))


def test_markers_overlay_circles_every_identified_led(tmp_path):
    rig, frames = frames_of("markers", tmp_path, 2)
    pipe = make_pipeline(rig)
    row = pipe.process(frames[0])
    det = pipe.last_detection
    assert row.ok and (det.ids >= 0).sum() >= 6
    img = draw_overlay(frames[0].image, det, row, rig)
    assert img.shape[:2] == frames[0].image.shape and img.ndim == 3
    for uv, k in zip(det.spots.centroids_px, det.ids, strict=True):
        if k >= 0:  # a green ring of radius 14 around each identified LED
            assert colour_near(img, uv, GREEN, 16) > 20
    # the overlay is not green where there is no LED
    assert colour_near(img, (5, img.shape[0] - 5), GREEN, 4) == 0


def test_lamps_overlay_marks_the_map_at_the_fitted_pose(tmp_path):
    rig, frames = frames_of("lamps", tmp_path, 2)
    pipe = make_pipeline(rig)
    row = pipe.process(frames[0])
    det = pipe.last_detection
    assert row.ok
    img = draw_overlay(frames[0].image, det, row, rig)
    ident = det.spots.centroids_px[det.ids >= 0]
    # (not under the row's text box in the top-left corner, which darkens what it covers)
    ident = ident[(ident[:, 1] > 100) | (ident[:, 0] > 400)]
    assert len(ident) >= 4
    for uv in ident:
        # each identified lamp ringed in green, and the map's lamp projected at the fitted
        # pose (a blue cross) on it
        assert colour_near(img, uv, GREEN, 10) > 5
        assert colour_near(img, uv, BLUE, 4) > 3


def test_star_flow_overlay_draws_stars_and_their_motion(tmp_path):
    rig, frames = frames_of("starfield", tmp_path, 3, "--case", 2)
    pipe = make_pipeline(rig)
    pipe.process(frames[0])
    row = pipe.process(frames[1])
    det = pipe.last_detection
    assert row.ok and det.matches is not None and len(det.matches) > 5
    img = draw_overlay(frames[1].image, det, row, rig)
    stars = det.stars.centroids_px
    ringed = sum(colour_near(img, uv, YELLOW, 11) > 5 for uv in stars)
    assert ringed >= 0.9 * len(stars)
    # the inliers' arrows start at the stars of the previous frame
    inl = det.inliers if det.inliers is not None else np.ones(len(det.matches), bool)
    starts = det.matches.uv1[inl]
    assert sum(colour_near(img, uv, GREEN, 3) > 0 for uv in starts) >= 0.9 * len(starts)


def test_overlay_text_sits_on_a_dark_box_without_black_outlines():
    """The overlay's header is white text on a darkened box. A thick black outline under
    the text was misaligned with it under OpenCV 5 (wider glyph spacing) and made the
    numbers unreadable; nothing may be darker than the darkened background."""
    from visvec.data import Status
    from visvec.output import AttitudeRow
    from visvec.overlay import _text

    grey = np.full((120, 400, 3), 150, np.uint8)
    row = AttitudeRow(
        frame=7,
        time_s=0.2,
        status=Status.OK,
        euler_deg=np.array([-42.11, -2.434, -0.775]),
        sigma_deg=np.array([0.014, 0.001, 0.001]),
        rms_px=0.02,
        n_points=3,
        latency_ms=1.0,
        warnings=("near_fov_edge",),
    )
    out = _text(grey.copy(), row)
    assert out.min() >= 150 // 3  # no black outline pixels
    assert out.max() >= 250  # the white text is there
    assert (out[5:60, 5:200] < 150).mean() > 0.5  # on a darkened box
    assert np.array_equal(out[100:, :], grey[100:, :])  # below the box: untouched


def test_overlay_draws_where_the_lens_models_field_ends(rig640):
    """A rig whose lens model folds over 345 px out (short of the 400 px corners): the
    overlay draws that edge, beyond which nothing is measured; a rig whose model holds
    to the corners draws none."""
    from dataclasses import replace

    from visvec.data import Status
    from visvec.output import AttitudeRow
    from visvec.overlay import draw_overlay

    frame = np.full((480, 640), 100, np.uint8)
    row = AttitudeRow(frame=0, time_s=0.0, status=Status.NO_TARGET, rms_px=np.nan,
                      n_points=0, latency_ms=1.0, warnings=("no_triangle",))  # fmt: skip
    dist = np.array([-0.32, 0.12, 0.0, 0.0, -0.02])
    folding = replace(rig640, camera=replace(rig640.camera, fx=340.0, fy=340.0, dist=dist))
    r = folding.camera.field_radius_px
    u, v = int(round(319.5 + 0.8 * r)), int(round(239.5 + 0.6 * r))  # towards a corner
    assert np.any(draw_overlay(frame, None, row, folding)[v - 1 : v + 2, u - 1 : u + 2] != 100)
    plain = draw_overlay(frame, None, row, rig640)
    assert np.all(plain[200:, :] == 100)  # below the header: the frame alone
