"""Frames rendered on the fly at known attitudes (for tests and benchmarks)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from visvec.data import Frame
from visvec.rig import Rig
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene


class SyntheticSource:
    """Renders the rig's scene at each attitude in ``R_nb`` (K, 3, 3).

    Parameters
    ----------
    rig : Rig
        The true geometry to render.
    R_nb : sequence of (3, 3) ndarray
    scene : Scene or sequence of Scene (one per frame)
    fps : float
    rng : numpy Generator or seed
    """

    def __init__(
        self,
        rig: Rig,
        R_nb: Sequence[np.ndarray],
        scene: Scene | Sequence[Scene],
        fps: float = 30.0,
        rng: np.random.Generator | int | None = 0,
    ):
        self.rig = rig
        self.R_nb = list(R_nb)
        self.scenes = [scene] * len(self.R_nb) if isinstance(scene, Scene) else list(scene)
        self.fps = fps
        self.rng = np.random.default_rng(rng)

    def __len__(self) -> int:
        return len(self.R_nb)

    def __iter__(self) -> Iterator[Frame]:
        for i, (R, sc) in enumerate(zip(self.R_nb, self.scenes, strict=True)):
            yield Frame(i, i / self.fps, render_frame(self.rig, R, sc, self.rng), f"sim#{i}")
