"""A camera's tone curve: what it does to the light before the 8-bit grey levels.

A webcam does not deliver linear light: it encodes it through a tone curve, nearly
always the sRGB transfer function (IEC 61966-2-1, Sec. 5.2: linear below 0.0031308,
1.055 x^(1/2.4) - 0.055 above) or a plain power 1/gamma. The triangle's fits model a
blurred step in linear light (visvec.detect.edges, visvec.detect.photometric): through
a tone curve the step's profile is bent toward its dark side and every edge moves
(benchmarks/RESULTS.md, webcam chain: both fits' tilts 2-4x their sigma). Declared in
the rig (``[camera] tone_curve``), the fits read each grey level as the linear level it
encodes (`tone_lut`), on the same 0-255 scale; the search and the checks keep the
camera's levels.
"""

from __future__ import annotations

import numpy as np

TONE_CURVES = ("linear", "srgb")  # or a number: a power law's gamma
GAMMA_RANGE = (0.2, 5.0)


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's decoding: encoded levels [0, 1] to linear light [0, 1]."""
    v = np.clip(np.asarray(v, float), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def tone_lut(tone_curve: str | float) -> np.ndarray | None:
    """(256,) float32: each 8-bit level's linear level (0-255, white stays 255) under the
    tone curve ``tone_curve`` ("srgb", or a gamma: level = 255 (code / 255)^gamma); None
    for "linear" (the levels are linear already)."""
    if tone_curve == "linear" or tone_curve == 1.0:
        return None
    v = np.arange(256) / 255.0
    lin = srgb_to_linear(v) if tone_curve == "srgb" else v ** float(tone_curve)
    return (255.0 * lin).astype(np.float32)


def check_tone_curve(value: object, where: str) -> str | float:
    """The rig's ``tone_curve`` as visvec takes it, or a ValueError naming ``where``."""
    if isinstance(value, str) and value in TONE_CURVES:
        return value
    if isinstance(value, int | float) and not isinstance(value, bool):
        g = float(value)
        if GAMMA_RANGE[0] <= g <= GAMMA_RANGE[1]:
            return g
    raise ValueError(
        f'{where} = {value!r}: expected "linear", "srgb" or a gamma from '
        f"{GAMMA_RANGE[0]:g} to {GAMMA_RANGE[1]:g} (2.2: level = (code / 255)^2.2)"
    )
