"""The fusion's options, for the command line and for scripts."""

import math

import pytest
from fusion_cases import _fixes, _sim3d

from visvec.fuse.attitude import AttitudeModel
from visvec.fuse.inputs import ImuData
from visvec.fuse.options import FusionOptions, engine_from_options, model_from_options
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import fuse


def test_the_options_make_the_model_the_command_line_makes():
    m, lim = model_from_options(False, 0.005, FusionOptions(gyro_noise_dps=0.2,
                                                            misalignment=False))  # fmt: skip
    assert isinstance(m, AttitudeModel) and m.sample_s == 0.005
    assert m.gyro_noise == pytest.approx(math.radians(0.2)) and m.misalignment_sigma == 0.0
    assert lim.max_rate_dps == 2000.0
    p, lim = model_from_options(True, 0.01, FusionOptions())
    assert isinstance(p, PlanarModel) and lim.max_rate_dps == 50.0 and lim.max_accel_mps2 == 0.5
    eng = engine_from_options(False, 0.01, FusionOptions(gyro_range_dps=250.0))
    assert eng.saturation.declared == pytest.approx(math.radians(250.0))


@pytest.mark.parametrize(
    "opts, words",
    [
        (FusionOptions(gyro_range_dps=0.0), "gyro_range_dps = 0.0: expected a positive"),
        (FusionOptions(gyro_range_dps=math.inf), "gyro_range_dps = inf"),
        (FusionOptions(gyro_noise_dps=-1.0), "gyro_noise_dps = -1.0"),
        (FusionOptions(clock_jitter_ms=math.nan), "clock_jitter_ms = nan"),
        (FusionOptions(method="fast"), "method 'fast'"),
    ],
)
def test_bad_options_are_refused_before_work(opts, words):
    with pytest.raises(ValueError, match=words):
        model_from_options(False, 0.01, opts)


def test_options_of_the_other_kind_are_refused():
    with pytest.raises(ValueError, match="apply to 3-D fixes"):
        model_from_options(True, 0.01, FusionOptions(fix_sigma_deg=0.1))
    with pytest.raises(ValueError, match="planar fixes"):
        model_from_options(False, 0.01, FusionOptions(method="paper"))


def test_a_script_fuses_as_the_command_line_does():
    """The public API's path: options -> engine -> fused samples."""
    from visvec import api

    t, R, gyro, rng = _sim3d(n=800)
    imu = ImuData(t, gyro, None, t * 0, (), 0.01)
    eng = api.engine_from_options(False, imu.period_s, api.FusionOptions())
    out = list(fuse(imu, _fixes(t, R, rng), None, engine=eng))
    assert out[-1].state is not None and out[-1].n_fixes >= 10
