"""A row's status and warning codes in words, for a person watching the live view."""

from __future__ import annotations

STATUS_WORDS = {
    "ok": "ok",
    "no_target": "no target in the frame",
    "rejected": "target found but not usable",
    "not_converged": "the solution did not converge",
    "read_error": "the frame could not be read",
}

WARNING_WORDS = {
    "low_brightness": "the image is too dark",
    "high_brightness": "the image is too bright",
    "near_fov_edge": "the target is near the edge of the view",
    "no_triangle": "no region with the triangle's shape",
    "partly_out_of_view": "part of the target is outside the image",
    "obstructed": "something covers the target",
    "edge_obstructed": "an edge of the triangle is covered or bent",
    "low_contrast": "too little contrast between the target and its surround",
    "overexposed": "the target is overexposed (clipped)",
    "no_dark_surround": "the target has no dark surround",
    "beyond_lens_model": "the target is beyond the lens model's field",
    "inconsistent_geometry": "no attitude explains what is seen",
    "impossible_tilt": "the tilt is beyond the platform's range",
    "not_converged": "the solution did not converge",
    "internal_error": "an internal error (please report it)",
    "too_few_markers": "too few markers identified",
    "missing_markers": "some markers are missing",
    "merged_spot": "two spots merged",
    "extra_spots": "spots that are not markers",
    "not_identified": "the spots could not be identified",
    "ambiguous_layout": "the markers' layout is ambiguous from here",
    "too_few_lamps": "too few lamps identified",
    "no_lamps": "no lamps in the frame",
    "no_catalogue_match": "the lamps match no place in the map",
    "outlier_lamps": "some lamps did not fit the pose",
    "lamps_collinear": "the lamps seen lie on one line",
    "not_a_star_field": "the frame is not a star field",
    "too_few_stars": "too few stars",
    "few_stars": "few stars",
    "too_few_matches": "too few stars matched between frames",
    "no_consistent_motion": "the stars do not move as one rotation",
    "rate_beyond_max": "the rate is beyond the rig's maximum",
    "frame_jump": "frames were missed before this one",
    "first_frame": "the first frame (a rate needs two)",
    "rolling_shutter_uncorrected": "a rolling shutter is not corrected",
    "rolling_shutter_estimated": "the rolling shutter's readout is estimated",
    "inter_frame_codec": "the video codec's errors are not measured (calibrate zero-tilt "
    "through this stream)",
    "read_late": "the frame waited before it was read: its time is late (no fix)",
}


def in_words(status: str, warnings: str) -> str:
    """``status`` with its ``;``-separated warning codes, in words."""
    text = STATUS_WORDS.get(status, status.replace("_", " "))
    codes = [c for c in warnings.split(";") if c]
    if codes:
        text += ": " + "; ".join(WARNING_WORDS.get(c, c.replace("_", " ")) for c in codes)
    return text
