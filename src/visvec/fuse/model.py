"""What the fusion engine (visvec.fuse.replay.Fusion) asks of a filter: the protocol
that the planar (visvec.fuse.planar) and the 3-D filter (visvec.fuse.attitude) both
follow. A model is an immutable description (its priors and options); its states are
immutable too, so that the engine can keep one per inertial sample and replay from any
of them."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from visvec.fuse.inputs import Fix


class FusionModel(Protocol):
    """A filter the engine drives.

    Attributes
    ----------
    planar : bool
        True for a pose (x, y, heading) filter, False for an attitude one.
    """

    planar: bool

    def init(self, fix: Fix) -> Any:
        """The state at a first fix's exposure time."""

    def propagate(self, s: Any, gyro: np.ndarray, accel: np.ndarray | None, dt: float) -> Any:
        """The state ``dt`` seconds later.

        Parameters
        ----------
        s : state
            The state at the interval's start.
        gyro : ndarray, shape (3, 3)
            ``visvec.fuse.history.History.reading``: the interval's mean rate (rad/s), its
            rate of change (rad/s^2) and a saturated reading's extra 1-sigma (rad/s).
        accel : ndarray, shape (2,), or None
            The accelerometers' mean reading over the interval (m/s^2, body x, y).
        dt : float
            The interval (s).
        """

    def update(self, s: Any, fix: Fix) -> tuple[Any, bool, float]:
        """The state after ``fix`` (applied at ``s``'s time), whether it was taken, and
        its normalised innovation squared."""

    def values(self, s: Any) -> tuple[np.ndarray, np.ndarray]:
        """What a row reports: the value and its uncertainty (the planar filter: pose
        and 1-sigma (3,); the 3-D one: R_NB (3, 3) and the body-axis covariance)."""
