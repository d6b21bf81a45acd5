"""Perturbed labs for marker Monte Carlo studies (STASIS Sec. 3.5, Table 3)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from visvec.rig import Pattern, Rig
from visvec.rotations import euler_to_matrix


def perturbed_lab(rig: Rig, rng: np.random.Generator) -> Rig:
    """A lab that differs from the rig file within ranges like STASIS Table 3."""
    cam = rig.camera
    cam2 = replace(
        cam,
        fx=cam.fx + rng.uniform(-50, 50),
        fy=cam.fy + rng.uniform(-50, 50),
        cx=cam.cx + rng.uniform(-50, 50),
        cy=cam.cy + rng.uniform(-50, 50),
        dist=np.array([rng.uniform(-0.15, 0.15), 0.0, 0.0, 0.0, 0.0]),
    )
    # the boards stay coplanar (they are): each moves +-10 mm in the plane and turns
    # +-1 deg about b3 (not the first: it defines B); the plane moves +-10 mm up or down
    dz = rng.uniform(-10, 10)
    pats = tuple(
        Pattern(
            p.position_mm + [*rng.uniform(-10, 10, 2), dz],
            euler_to_matrix(np.radians(rng.uniform(-1, 1)) * (j > 0), 0, 0) @ p.rotation,
            p.points_mm,
        )
        for j, p in enumerate(rig.target.patterns)
    )
    t = rig.t_n + np.array([*rng.uniform(-10, 10, 2), rng.uniform(-50, 50)])
    return replace(
        rig,
        camera=cam2,
        mount=replace(rig.mount, position_mm=t),
        target=replace(rig.target, patterns=pats),
    )
