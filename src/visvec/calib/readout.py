"""A rolling shutter's readout time, measured on a recording of the platform turning.

While the platform turns, each image row sees the triangle at the attitude of its own
exposure. The sensor takes every edge point back to the centre row's exposure with the
rig's ``[camera] readout_ms`` (:func:`visvec.shutter.unroll`); with the wrong
readout the corrected triangle is sheared, no rigid triangle fits its vertices, and
their chi-square (the fit's Mahalanobis residual, 3 degrees of freedom per frame once
the height is known over the frames, 2 before) grows. The readout is the one that
minimises the recording's total chi-square (a least-squares fit of one parameter
shared by all frames); its 1-sigma comes from the curvature of that total (a change of
1 in chi-square), scaled by sqrt(chi2 / dof) when the residuals exceed the vertices'
sigma.

Each trial's run estimates the target's height as the sensor does (``[target]
height_sigma_mm``, carried from frame to frame), so each trial readout has its own
height; where it is not yet known (the first frames) it takes up part of the shear (a
stretch along the columns) and leaves the minimum flatter: sigma about 1.35 ms at
640x480, against 1.1 ms with the height held exact. Holding it at the frames' median
estimate, from the uncorrected frames or near a first estimate, was tried and biased the
readout (RESULTS.md, readout calibration).

Each frame's chi-square is capped at the solver's refusal threshold, and a frame that
is refused, or not corrected (the first after an acquisition), counts the cap: a trial
readout that makes the sensor refuse frames is penalised without the cost jumping as
frames come and go. Nothing can be measured on a platform at rest: the recording must
turn (MIN_RATE_DPS).

The grid's minimum takes the camera model as exact. A principal point a few px off
leaves a keystone fixed in the image which, on a steady one-way turn, turns with the yaw
as a shear does: with it 4 px off, 2 s recordings of a global shutter read up to 15 ms
(13 sigma) turning one way at 10 deg/s and -17 to +12 ms (up to 8 sigma) swinging out
and back (benchmarks/RESULTS.md). So the grid's readout is refined by linearised steps
in which the
principal point, the aspect and a pattern fixed in the triangle's frame are estimated
beside it with their priors (:class:`visvec.estimate.shear.ReadoutEvidence`, the same
evidence the pipeline gathers on a rig that declares no readout), each frame tracked
with the last step's readout; the readout's 1-sigma is its marginal over those model
errors. A turn whose rate changes (a swing) tells them apart; a steady one-way turn
of 2 s keeps the sigma wide (5-8 ms at 640x480 against the grid's 1.35; half such
recordings are refused as poorly determined; a longer turn, through more yaw, narrows
it: 2 ms over 5 s).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from visvec.data import Frame
from visvec.estimate.shear import MAX_FIT_CHI2_DOF, ReadoutEvidence
from visvec.estimate.triangle_full import CHI2_REJECT
from visvec.pipeline import TrianglePipeline, body_rate
from visvec.rig import Rig

# below this median rate (deg/s) the recording does not shear the triangle enough
MIN_RATE_DPS = 3.0
# the least number of frames with the triangle found
MIN_FRAMES = 10
# spacing of the first, coarse search over readout times (ms), then its refinement
COARSE_STEP_MS = 4.0
FINE_STEP_MS = 1.0
# a readout less certain than this fraction of the frame interval is not reported
MAX_SIGMA_FRACTION = 0.25
# the readout of "no rolling shutter" in a trial: tiny, so that every trial treats the
# first frame alike (uncorrected) and only the correction changes
ZERO_MS = 1e-3
# linearised steps with the camera's model errors freed, after the grid search (the
# second moves the readout by a few hundredths of a ms)
MODEL_ERROR_STEPS = 2


@dataclass(frozen=True)
class ReadoutCalibration:
    """Result of :func:`calibrate_readout`.

    readout_ms, sigma_ms : the estimate and its 1-sigma (NaN when not determined), the
        camera's model errors marginalised
    grid_ms, grid_sigma_ms : the grid search's, the camera model taken as exact
    rate_dps : median angular rate of the platform over the recording
    n_frames : frames in the recording; n_used : frames ok and corrected at the estimate
    chi2_per_dof : at the estimate, and ``chi2_per_dof_global`` with no correction
    trials_ms, costs : every trial readout and its capped total chi-square
    converged : False with ``reason`` when the readout could not be determined;
        ``poorly_determined`` when it was found but too loosely (a prior on the
        principal point, ``principal_point_px``, may help)
    """

    readout_ms: float
    sigma_ms: float
    rate_dps: float
    n_frames: int
    n_used: int
    chi2_per_dof: float
    chi2_per_dof_global: float
    trials_ms: np.ndarray
    costs: np.ndarray
    converged: bool
    reason: str = ""
    grid_ms: float = float("nan")
    grid_sigma_ms: float = float("nan")
    poorly_determined: bool = False


@dataclass(frozen=True)
class _Trial:
    """One trial readout: the capped total chi-square of the recording, the frames ok
    and corrected (used) with their chi-square and degrees of freedom, and the
    (time_s, R_nb) of every ok row."""

    total: float
    used: int
    chi2_used: float
    dof_used: int
    attitudes: list

    def per_dof(self) -> float:
        """Chi-square per degree of freedom of the frames used (each capped)."""
        return self.chi2_used / max(self.dof_used, 1)


def _cost_of(frames: Sequence[Frame], rig: Rig, readout_ms: float) -> _Trial:
    """The recording tracked with ``readout_ms``: each used frame counts its chi-square
    capped at its refusal threshold (its degrees of freedom: 3 with the height known
    over the frames, 2 on a frame estimating it alone), every other frame the cap of 3."""
    pipe = TrianglePipeline(replace(rig, readout_ms=readout_ms, readout_sigma_ms=0.0))
    total, used, chi2_used, dof_used, attitudes = 0.0, 0, 0.0, 0, []
    for frame in frames:
        row = pipe.process(frame)
        sol = pipe.last_solution
        if row.ok and sol is not None:
            attitudes.append((frame.time_s, sol.R_nb))
        if row.ok and sol is not None and "rolling_shutter_uncorrected" not in row.warnings:
            chi2 = min(float(sol.chi2), CHI2_REJECT[sol.dof])
            total += chi2
            chi2_used += chi2
            dof_used += sol.dof
            used += 1
        else:
            total += CHI2_REJECT[3]
    return _Trial(total, used, chi2_used, dof_used, attitudes)


def _evidence(
    frames: Sequence[Frame], rig: Rig, readout_ms: float, principal_point_px: float | None
) -> ReadoutEvidence:
    """The recording tracked with ``readout_ms``: every frame ok and corrected (its rate
    known), with the rate since the ok frame before it, adds its residuals to the
    readout's evidence beside the camera's model errors (the principal point's prior
    ``principal_point_px``), as the pipeline's own check does
    (:meth:`TrianglePipeline._add_shear_evidence`)."""
    pipe = TrianglePipeline(replace(rig, readout_ms=readout_ms, readout_sigma_ms=0.0))
    ev = ReadoutEvidence.for_camera(rig.camera, rig.fps, principal_point_px)
    last = None
    for frame in frames:
        row = pipe.process(frame)
        sol, det = pipe.last_solution, pipe.last_detection
        if not row.ok or sol is None:
            last = None
            continue
        omega_b = body_rate(last, (frame.time_s, sol.R_nb)) if last is not None else None
        if omega_b is not None and "rolling_shutter_uncorrected" not in row.warnings:
            rows, lever = det.points_px[:, 1], pipe.detector.lever_c
            omega_c = rig.R_bc.T @ omega_b
            ev.add(sol.residual, det.points_n, rows, rig.camera, omega_c, lever, readout_ms)
        last = (frame.time_s, sol.R_nb)
    return ev


def _median_rate_dps(attitudes: list) -> float:
    """Median angular rate (deg/s) between consecutive ok rows of one turn."""
    rates = [body_rate(a, b) for a, b in zip(attitudes, attitudes[1:], strict=False)]
    speeds = [np.degrees(np.linalg.norm(w)) for w in rates if w is not None]
    return float(np.median(speeds)) if speeds else 0.0


def readout_trials(rig: Rig) -> int:
    """About how many readouts :func:`calibrate_readout` tries (for a progress bar)."""
    span = 1000.0 / rig.fps
    return len(np.arange(-span, span + 1e-9, COARSE_STEP_MS)) + 9


def calibrate_readout(
    frames: Sequence[Frame],
    rig: Rig,
    principal_point_px: float | None = None,
    progress: Callable[[int], None] | None = None,
) -> ReadoutCalibration:
    """The rolling-shutter readout time of the rig's camera from ``frames`` of the
    platform turning (a tracked recording with its times, as `visvec track` or a video
    gives them); triangle rigs.

    Parameters
    ----------
    frames : sequence of Frame
        The platform turning, in order, with their times (s).
    rig : Rig
        A triangle rig, its camera and zero-tilt calibrations applied.
    principal_point_px : float, optional
        How well the rig's principal point is known (1-sigma, px; default
        PRINCIPAL_POINT_PRIOR of the image width, a camera calibrated roughly;
        `calibrate camera` prints its own).
    progress : callable, optional
        ``progress(1)`` after each readout tried.

    Returns
    -------
    ReadoutCalibration
        The readout (ms, negative: the last row read first) and its 1-sigma, whether
        it converged and why not; its TOML sets the rig's ``readout_ms``.

    The search runs over readouts from minus to plus one frame interval (1000 / fps ms;
    negative: the last row read first): a coarse grid, 1 ms steps around its best point,
    then a parabola over the trials within +-2.5 sigma of it. Not converged (with the
    reason) when the platform does not turn, the minimum is flat or at the end of the
    search, or its sigma exceeds a quarter of the frame interval. ``progress(1)`` after
    each readout tried (about :func:`readout_trials`).
    """
    frames = [f for f in frames if f.image is not None]

    def _cost(frames, rig, r):
        out = _cost_of(frames, rig, r)
        if progress is not None:
            progress(1)
        return out

    span = 1000.0 / rig.fps
    base = _cost(frames, rig, ZERO_MS)
    base_dof = base.per_dof()
    attitudes = base.attitudes
    rate = _median_rate_dps(attitudes)
    trials: dict[float, float] = {ZERO_MS: base.total}

    def fail(reason: str, readout: float = float("nan")) -> ReadoutCalibration:
        grid = np.array(sorted(trials))
        return ReadoutCalibration(
            readout, float("nan"), rate, len(frames), 0, float("nan"), base_dof, grid,
            np.array([trials[g] for g in grid]), False, reason,
        )  # fmt: skip

    def too_slow() -> ReadoutCalibration:
        return fail(
            f"the platform turns at {rate:.1f} deg/s: the rows' times cannot be seen at "
            f"under {MIN_RATE_DPS:g} deg/s; record it turning (5-20 deg/s)"
        )

    # uncorrected, a fast turn may have most frames refused (their shear fits no rigid
    # triangle): the frames found and the rate are judged again at the estimate
    if len(attitudes) >= MIN_FRAMES and rate < MIN_RATE_DPS:
        return too_slow()
    best = _grid_search(trials, span, lambda r: _cost(frames, rig, r).total)
    readout, a2 = _parabola(trials, best, span)
    if not a2 > 0:
        return fail("the total chi-square has no minimum near its best trial")
    if abs(readout) > span - FINE_STEP_MS:
        return fail(f"the best readout ({readout:.1f} ms) is at the end of the search", readout)
    final = _cost(frames, rig, readout)
    attitudes = final.attitudes
    rate = _median_rate_dps(attitudes)
    if len(attitudes) < MIN_FRAMES:
        return fail(f"only {len(attitudes)} frames with the triangle found: record more")
    if rate < MIN_RATE_DPS:
        return too_slow()
    chi2_dof = final.per_dof()
    # the curvature of the total chi-square gives the 1-sigma (delta chi2 = 1 at sigma)
    grid_readout = readout
    grid_sigma = float(np.sqrt(1.0 / a2) * np.sqrt(max(1.0, chi2_dof)))
    readout, sigma, reason = _with_model_errors(frames, rig, readout, principal_point_px)
    if reason:
        return fail(reason, readout)
    if sigma > MAX_SIGMA_FRACTION * span:
        why = (
            f"the readout is poorly determined ({readout:.1f} +- {sigma:.1f} ms with the "
            f"camera's principal point and aspect estimated beside it; {grid_readout:.1f} +- "
            f"{grid_sigma:.1f} ms taking them as exact): record longer, or swinging out and "
            "back rather than turning one way, or give a prior on the principal point "
            "from a camera calibration"
        )
        return replace(fail(why, readout), poorly_determined=True)
    final = _cost(frames, rig, readout)
    grid = np.array(sorted(trials))
    return ReadoutCalibration(
        readout, sigma, rate, len(frames), final.used, final.per_dof(), base_dof, grid,
        np.array([trials[g] for g in grid]), True, "", grid_readout, grid_sigma,
    )  # fmt: skip


def _grid_search(trials: dict[float, float], span: float, cost) -> float:
    """Step 1: ``cost(readout)`` on a coarse grid over +-``span`` ms, then in 1 ms steps
    around its best; every trial goes into ``trials``. The best trial."""
    for r in np.arange(-span, span + 1e-9, COARSE_STEP_MS):
        if abs(r) > ZERO_MS:
            trials[float(r)] = cost(float(r))
    best = min(trials, key=trials.get)
    for r in best + FINE_STEP_MS * np.arange(-3, 4):
        if abs(r) <= span and float(r) not in trials:
            trials[float(r)] = cost(float(r))
    return best


def _parabola(trials: dict[float, float], best: float, span: float) -> tuple[float, float]:
    """Step 2: the vertex and curvature (a2; <= 0: no minimum) of a parabola over the
    trials within +-half of the best, the window set to +-2.5 sigma of the last fit:
    wide enough that a shallow minimum's curvature (a small image, a slow turn: sigma of
    several ms) is not the cost's own roughness over a few ms, narrow enough that a
    sharp one's is not flattened by frames reaching the cap."""
    half = 4.0 * COARSE_STEP_MS
    for _ in range(4):
        near = np.array([r for r in trials if abs(r - best) <= half + 1e-9])
        a2, a1, _ = np.polyfit(near, np.array([trials[r] for r in near]), 2)
        if a2 <= 0:
            return float("nan"), float(a2)
        new_half = float(np.clip(2.5 / np.sqrt(a2), 3.0 * FINE_STEP_MS, span))
        if abs(new_half - half) < FINE_STEP_MS:
            break
        half = new_half
    return float(-a1 / (2 * a2)), float(a2)


def _with_model_errors(frames, rig: Rig, readout: float,
                       principal_point_px: float | None) -> tuple[float, float, str]:  # fmt: skip
    """Step 3: the readout and its 1-sigma with the camera's principal point and aspect
    estimated beside it (MODEL_ERROR_STEPS rounds), or the reason it cannot be."""
    sigma = float("nan")
    for _ in range(MODEL_ERROR_STEPS):
        ev = _evidence(frames, rig, readout, principal_point_px)
        readout, sigma = ev.readout_ms()
        if not np.isfinite(readout):
            return readout, sigma, "no frame with its rate known to measure the readout on"
        fit = ev.fit_chi2_per_dof()
        if fit > MAX_FIT_CHI2_DOF:
            why = (
                f"the residuals are {fit:.1f}x the vertices' noise with the readout and the "
                f"camera's model errors taken out: not a rolling shutter's shear (is the "
                f"[camera] model calibrated?)"
            )
            return readout, sigma, why
        sigma = float(sigma * np.sqrt(max(1.0, fit)))
    return readout, sigma, ""


def readout_sections(res: ReadoutCalibration) -> dict[str, dict[str, object]]:
    """Sections of the calibration file (``[camera] readout_ms`` with its 1-sigma, which
    the rows' sigma then carries, and a report)."""
    return {
        "camera": {
            "readout_ms": round(res.readout_ms, 2),
            "readout_sigma_ms": round(res.sigma_ms, 2),
        },
        "report": {
            "sigma_readout_ms": round(res.sigma_ms, 3),
            # the grid search's, with the camera model taken as exact
            "readout_ms_camera_exact": round(res.grid_ms, 2),
            "sigma_readout_ms_camera_exact": round(res.grid_sigma_ms, 3),
            "rate_dps": round(res.rate_dps, 2),
            "frames": res.n_frames,
            "frames_used": res.n_used,
            "chi2_per_dof": round(res.chi2_per_dof, 4),
            "chi2_per_dof_uncorrected": round(res.chi2_per_dof_global, 4),
        },
    }
