"""Pipelines: frame -> detection -> estimate -> row, one module per target kind.

:class:`~visvec.pipeline.base.Pipeline` holds what every kind shares; a subclass turns
one good image into a solution. :func:`make_pipeline` picks the class for a rig and is
the one entry.
"""

from __future__ import annotations

from visvec.errors import ConfigError
from visvec.pipeline.base import AttitudePipeline, Pipeline
from visvec.pipeline.lamps import LampDetection, LampPipeline
from visvec.pipeline.markers import MARKER_METHODS, MarkerDetection, MarkerPipeline
from visvec.pipeline.starfield import RATE_METHODS, RateDetection, RatePipeline
from visvec.pipeline.triangle import TRIANGLE_METHODS, TrianglePipeline, body_rate
from visvec.rig import Rig

METHODS = tuple(dict.fromkeys(TRIANGLE_METHODS + MARKER_METHODS + RATE_METHODS))

DEFAULT_METHODS = {"triangle": "full", "markers": "full", "starfield": "poisson", "lamps": "full"}


def make_pipeline(rig: Rig, method: str | None = None) -> Pipeline:
    """The pipeline for the rig's target kind.

    Parameters
    ----------
    rig : Rig
        A loaded rig (`load_rig`), its calibration files applied.
    method : str, optional
        The estimator: triangle 'full' (default) or 'paper'; markers 'full' (default)
        or a PnP baseline ('pnp-*'); starfield 'poisson' (default) or 'crassidis';
        lamps 'full'. None: the kind's default.

    Returns
    -------
    Pipeline
        ``process(frame)`` gives one row per frame (AttitudeRow, RateRow or PoseRow),
        never raising on a frame's content.

    Examples
    --------
    >>> pipe = make_pipeline(load_rig("configs/triangle.toml"))
    >>> rows = [pipe.process(frame) for frame in open_source("data/sample_frames")]
    """
    method = method or DEFAULT_METHODS.get(rig.kind, "full")
    if rig.kind == "triangle":
        return TrianglePipeline(rig, method)
    if rig.kind == "markers":
        return MarkerPipeline(rig, method)
    if rig.kind == "starfield":
        return RatePipeline(rig, method)
    if rig.kind == "lamps":
        return LampPipeline(rig, method)
    raise ConfigError(f"target kind {rig.kind!r} has no pipeline in this version")


__all__ = [
    "METHODS",
    "AttitudePipeline",
    "LampDetection",
    "LampPipeline",
    "MarkerDetection",
    "MarkerPipeline",
    "Pipeline",
    "RateDetection",
    "RatePipeline",
    "TrianglePipeline",
    "body_rate",
    "make_pipeline",
]
