"""What a user tells the fusion, and the filter and engine it makes: the options of
`visvec fuse`, `track --imu` and `batch --imu` in one place, for scripts too."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from visvec.fuse.attitude import AttitudeModel
from visvec.fuse.planar import PlanarModel
from visvec.fuse.replay import Fusion, Limits


@dataclass(frozen=True)
class FusionOptions:
    """The fusion's settings; every one optional (None: the default or what is
    learned).

    Attributes
    ----------
    method : str
        Planar only: "kalman" (the filter with biases, default) or "paper" (LuVeX's
        reset at each fix).
    gyro_noise_dps : float or None
        The gyro's white noise per sample (deg/s) [planar 0.05; 3-D 0.3, then learned].
    accel_noise_mps2 : float
        Planar: the accelerometers' white noise per sample (m/s^2).
    fix_sigma_deg : float or None
        3-D: the fixes' attitude noise (deg), overriding their own sigmas.
    misalignment : bool
        3-D: estimate the gyro's misalignment to the fixes' body axes.
    max_rate_dps : float or None
        Rates beyond this are faults (deg/s) [planar 50, 3-D 2000].
    max_accel_mps2 : float
        Planar: accelerations beyond this are faults (m/s^2).
    clock_jitter_ms : float or None
        3-D: the 1-sigma jitter of the gyro's clock against the fixes' (ms) [one IMU
        sample period; 0 when one clock triggers both].
    gyro_range_dps : float or None
        The gyro's range (deg/s, every axis), from its datasheet; None: learned only from
        flat tops no gyro that turns can produce (visvec.fuse.saturation).
    history_s : float
        The inertial history kept for replaying late fixes (s).
    """

    method: str = "kalman"
    gyro_noise_dps: float | None = None
    accel_noise_mps2: float = 0.002
    fix_sigma_deg: float | None = None
    misalignment: bool = True
    max_rate_dps: float | None = None
    max_accel_mps2: float = 0.5
    clock_jitter_ms: float | None = None
    gyro_range_dps: float | None = None
    history_s: float = 10.0

    def check(self) -> None:
        """Refuse a value that is not a positive finite number where one is asked.

        Raises
        ------
        ValueError
            Naming the setting and what was expected.
        """
        if self.method not in ("kalman", "paper"):
            raise ValueError(f"method {self.method!r}: expected 'kalman' or 'paper'")
        for name in ("gyro_noise_dps", "accel_noise_mps2", "fix_sigma_deg", "max_rate_dps",
                     "max_accel_mps2", "gyro_range_dps", "history_s"):  # fmt: skip
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}: expected a positive finite number")
        if self.clock_jitter_ms is not None and not (
            math.isfinite(self.clock_jitter_ms) and self.clock_jitter_ms >= 0
        ):
            raise ValueError(f"clock_jitter_ms = {self.clock_jitter_ms!r}: expected a finite "
                             "number >= 0")  # fmt: skip


def model_from_options(planar: bool, period_s: float | None, opts: FusionOptions):
    """The filter and the fault limits the options ask for.

    Parameters
    ----------
    planar : bool
        Planar pose fixes (lamps) or attitudes.
    period_s : float or None
        The IMU's sample period (s), where known (a file); None for a live stream.
    opts : FusionOptions
        The settings.

    Returns
    -------
    (PlanarModel or AttitudeModel, Limits)

    Raises
    ------
    ValueError
        A setting that does not apply to the kind (3-D settings with planar fixes, the
        paper's method with attitudes), or a bad value (FusionOptions.check).
    """
    opts.check()
    if planar:
        if opts.fix_sigma_deg is not None or not opts.misalignment or \
                opts.clock_jitter_ms is not None:  # fmt: skip
            raise ValueError("fix_sigma_deg, clock_jitter_ms and misalignment apply to 3-D "
                             "fixes")  # fmt: skip
        model = PlanarModel(method=opts.method, accel_noise=opts.accel_noise_mps2 * 1000.0)
        if opts.gyro_noise_dps is not None:
            model = replace(model, gyro_noise=math.radians(opts.gyro_noise_dps))
        return model, Limits(opts.max_rate_dps or 50.0, opts.max_accel_mps2)
    if opts.method != "kalman":
        raise ValueError("the paper's method applies to planar fixes")
    model = AttitudeModel(misalignment_sigma=math.radians(5) if opts.misalignment else 0.0)
    if period_s is not None:
        model = replace(model, sample_s=period_s)
    if opts.gyro_noise_dps is not None:
        model = replace(model, gyro_noise=math.radians(opts.gyro_noise_dps))
    if opts.fix_sigma_deg is not None:
        model = replace(model, fix_sigma=math.radians(opts.fix_sigma_deg))
    if opts.clock_jitter_ms is not None:
        model = replace(model, jitter_sigma=opts.clock_jitter_ms / 1000.0)
    return model, Limits(opts.max_rate_dps or 2000.0, None)


def engine_from_options(planar: bool, period_s: float | None, opts: FusionOptions) -> Fusion:
    """The fusion engine with the filter the options ask for (model_from_options).

    Parameters
    ----------
    planar : bool
        True: the planar filter (x, y, heading with a yaw gyro and two
        accelerometers); False: the 3-D attitude filter.
    period_s : float or None
        The IMU's sample period (s), where known (it sets the white noise's
        correlation time and the clock jitter's prior); None: the filter's default.
    opts : FusionOptions
        What `visvec fuse` takes as options (gyro noise, gyro range, history, ...).

    Returns
    -------
    Fusion
        Fed inertial samples (`Fusion.step`) and fixes (`Fusion.add_fix`) in their
        order of arrival; its ``model`` gives the rows (`fused_rows`).

    Raises
    ------
    ValueError
        An option that does not apply to the kind of filter, or out of range.

    Examples
    --------
    >>> eng = engine_from_options(False, 1 / 286, FusionOptions(gyro_range_dps=2000))
    >>> rows = list(fused_rows(fuse(imu, fixes, None, engine=eng), eng.model))
    """
    model, limits = model_from_options(planar, period_s, opts)
    return Fusion(model, limits=limits, history_s=opts.history_s,
                  gyro_range_dps=opts.gyro_range_dps)  # fmt: skip
