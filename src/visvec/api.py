"""The public API of visvec: rigs, sources, the pipelines of the four target kinds,
the fusion engine, the calibrations and the simulator.

Examples
--------
Rows of a recording:

>>> from visvec.api import load_rig, make_pipeline, FolderSource
>>> rig = load_rig("configs/triangle.toml")
>>> rows = list(make_pipeline(rig).run(FolderSource("data/sample_frames")))

Fusion, fed live (each IMU sample as it comes, each fix when it arrives):

>>> engine = Fusion(AttitudeModel(sample_s=0.01))
>>> engine.add_fix(fix)                       # doctest: +SKIP
>>> state = engine.step(t, gyro_rad_s, None)  # doctest: +SKIP

What `track --imu` does, scripted: a camera's rows as fixes (their full covariance
kept), the engine from the options, fused rows from a recording:

>>> opts = FusionOptions(gyro_range_dps=2000.0)
>>> engine = engine_from_options(planar=False, period_s=0.01, opts=opts)
>>> fixes = [f for f in map(lambda r: fix_from_row(r, False), rows) if f]  # doctest: +SKIP
>>> out = list(fused_rows(fuse(read_imu("imu.csv", planar=False), fixes, None,
...                            engine=engine), engine.model))  # doctest: +SKIP
"""

from visvec.calib.camera import calibrate_camera
from visvec.calib.readout import calibrate_readout
from visvec.calib.system import calibrate_system
from visvec.calib.zero_tilt import calibrate_zero_tilt
from visvec.camera import CameraModel
from visvec.data import AttitudeSolution, Detection, Frame, Status
from visvec.detect import TriangleDetector
from visvec.errors import ConfigError, InputFileError, SourceError, VisvecError
from visvec.estimate import solve_full, solve_paper
from visvec.fuse.attitude import AttitudeModel
from visvec.fuse.inputs import Fix, fix_from_row, read_fixes, read_imu
from visvec.fuse.options import FusionOptions, engine_from_options, model_from_options
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import Fusion, fuse
from visvec.fuse.run import fused_rows
from visvec.output import ATTITUDE_COLUMNS, AttitudeRow
from visvec.pipeline import (
    LampPipeline,
    MarkerPipeline,
    Pipeline,
    RatePipeline,
    TrianglePipeline,
    make_pipeline,
)
from visvec.rig import Rig, load_rig
from visvec.sim.render import render_frame
from visvec.sim.scene import Light, Occluder, Scene
from visvec.sim.simulate import simulate, true_rig
from visvec.sources import FolderSource, SyntheticSource, VideoSource, open_source

__all__ = [
    "ATTITUDE_COLUMNS",
    "AttitudeRow",
    "AttitudeModel",
    "Fix",
    "Fusion",
    "FusionOptions",
    "PlanarModel",
    "engine_from_options",
    "fix_from_row",
    "fuse",
    "fused_rows",
    "model_from_options",
    "read_fixes",
    "read_imu",
    "AttitudeSolution",
    "CameraModel",
    "ConfigError",
    "Detection",
    "FolderSource",
    "Frame",
    "InputFileError",
    "Light",
    "Occluder",
    "Rig",
    "Scene",
    "SourceError",
    "Status",
    "SyntheticSource",
    "TriangleDetector",
    "TrianglePipeline",
    "MarkerPipeline",
    "RatePipeline",
    "LampPipeline",
    "Pipeline",
    "make_pipeline",
    "VideoSource",
    "VisvecError",
    "calibrate_camera",
    "calibrate_readout",
    "calibrate_system",
    "calibrate_zero_tilt",
    "load_rig",
    "open_source",
    "render_frame",
    "simulate",
    "solve_full",
    "solve_paper",
    "true_rig",
]
