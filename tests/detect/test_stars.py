"""Star detection on real night-sky frames (../shared/data) and refusal of non-sky photos."""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from visvec.detect.stars import find_stars

from conftest import shared

# the requirement: >= 90 % of a star tracker's centroids found within 0.5 px
MATCH_PX = 0.5
MIN_FOUND = 0.9


def test_tetra3_frames_centroids_match_the_reference():
    d = shared("tetra3")
    ref = json.loads((d / "cedar_solve_0.5.1_reference_run.json").read_text())
    found = total = 0
    for name, entry in ref.items():
        img = cv2.imread(str(d / name), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.dtype == np.uint16
        stars = find_stars(img)
        assert stars.usable, (name, stars.reason)
        # the reference puts (0, 0) at the corner of the top-left pixel: shift by 0.5
        ref_uv = np.array(entry["centroids_yx"])[:, ::-1] - 0.5
        dist, _ = cKDTree(stars.centroids_px).query(ref_uv)
        assert np.mean(dist < MATCH_PX) >= MIN_FOUND, name
        found += int(np.sum(dist < MATCH_PX))
        total += len(ref_uv)
    assert found / total >= MIN_FOUND


@pytest.mark.parametrize(
    "name, usable",
    [
        ("tree.jpg", False),
        ("roof.jpg", False),
        ("pleiades.jpg", True),
        ("orion_belt.jpg", True),
        ("jan1_g90_e50ms.jpg", True),
        ("jan1_g90_e100ms.jpg", True),
        ("hale_bopp.jpg", True),
    ],
)
def test_non_sky_photos_are_refused(name, usable):
    img = cv2.imread(str(shared("cedar_solve_extra", name)), cv2.IMREAD_COLOR)
    stars = find_stars(img)
    assert stars.usable is usable, (
        name,
        stars.reason,
        stars.bright_fraction,
        stars.compact_fraction,
    )
    if not usable:
        assert stars.reason == "not_a_star_field"


def test_empty_and_saturated_frames_are_not_star_fields():
    assert find_stars(np.zeros((100, 120), np.uint8)).reason == "too_few_stars"
    assert not find_stars(np.full((100, 120), 255, np.uint8)).usable
    r = np.random.default_rng(0)
    noise = r.normal(100, 3, (200, 200)).clip(0, 255).astype(np.uint8)
    assert not find_stars(noise).usable


def test_hot_pixel_is_not_a_star():
    img = np.full((100, 100), 10, np.uint8)
    img[50, 50] = 255  # a single hot pixel: under 3 pixels
    assert len(find_stars(img)) == 0
