"""The triangle target's pipeline (VT's Visual Vector Sensor): edges -> vertices ->
attitude, with the rolling-shutter and height evidence it gathers on the way."""

from __future__ import annotations

import math

import numpy as np

from visvec.data import AttitudeSolution, Detection, Status, inter_frame
from visvec.detect import TriangleDetector
from visvec.errors import ConfigError
from visvec.estimate import ESTIMATORS
from visvec.estimate.shear import (
    ASPECT_MIN,
    CAMERA_NOTE_SIGMAS,
    MAX_FIT_CHI2_DOF,
    PRINCIPAL_POINT_MIN,
    ReadoutEvidence,
)
from visvec.estimate.triangle_full import CHI2_REJECT, HeightTrack
from visvec.pipeline.base import AttitudePipeline, Pipeline
from visvec.rig import Rig
from visvec.rotations import expmap, logmap

TRIANGLE_METHODS = tuple(ESTIMATORS)

# a rolling shutter's rate comes from the last two ok frames only if neither is older
# than this before the next (s), and only if it is below MAX_RATE_DPS: faster, the two
# frames are unrelated (a folder of level frames at different yaws), not a turn
MAX_RATE_GAP_S = 0.5
MAX_RATE_DPS = 60.0
# the run's closing note on the target's height: after this many ok frames, when the
# running estimate is this many of its sigma and this many mm off the rig file's
MIN_HEIGHT_FRAMES = 10
# a refused frame's residuals count as evidence of a rolling shutter up to this
# chi-square (four times the refusal threshold; a shear's, not a wrong triangle's)
SHEAR_EVIDENCE_CHI2 = 4.0 * CHI2_REJECT[3]
HEIGHT_NOTE_SIGMAS = 5.0
HEIGHT_NOTE_MM = 1.0
# the closing note on correlated frames: when the edge points' learned correlation
# widens the lines' variance by this much (mp4v 1.4-2.0, Motion-JPEG at quality 75
# 1.1-1.3, noise smoothed by a camera's (1, 2, 1) / 4 kernel about 1.3, lossless frames
# of white noise and Motion-JPEG at quality 95 exactly 1; visvec.noise.LearnedCorrelation)
CODEC_NOTE_FACTOR = 1.2


def _no_rigid_fit(sol: AttitudeSolution) -> bool:
    """Refused because no attitude fits the vertices as a rigid triangle (a shear, a
    wrong height prior), not for want of a solution."""
    return sol.status is Status.REJECTED and "inconsistent_geometry" in sol.warnings


def body_rate(a: tuple[float, np.ndarray], b: tuple[float, np.ndarray]) -> np.ndarray | None:
    """The platform's body rate (rad/s) between two frames' (time_s, R_nb),
    R_nb(t1) = R_nb(t0) expm([omega_b] dt); None when they are too far apart in time
    (MAX_RATE_GAP_S) or in angle (MAX_RATE_DPS) to be one turn."""
    (t0, R0), (t1, R1) = a, b
    if not 0 < t1 - t0 <= MAX_RATE_GAP_S:
        return None
    omega_b = logmap(R0.T @ R1) / (t1 - t0)
    if math.degrees(math.sqrt(omega_b @ omega_b)) > MAX_RATE_DPS:
        return None
    return omega_b


def codec_advice(rig: Rig, codec: str, past: bool = False) -> str:
    """What a triangle rig's frames through ``codec``, one that predicts frames from
    earlier ones (visvec.data.inter_frame), mean for its rows: the pixel fit is set
    aside on them (a pixel-fit rig), and unless ``[detect] sigma_scale`` was measured
    (by `calibrate zero-tilt` on level frames through the same stream) the rows' sigma
    does not cover the codec's errors (their warning inter_frame_codec).
    benchmarks/triangle_compression.py: through H.264 at x264's default quality with
    the platform tilting, 30-37 of 300 rows beyond 3 sigma and 3-7 beyond 5; with the
    measured sigma_scale 3 and none at 640x480 (1 at 320x240). Empty when neither
    applies (a lines rig with a measured sigma_scale)."""
    were, are = ("were", "came") if past else ("are", "come")
    text = f"the frames {are} through {codec}, a codec that predicts frames from earlier ones"
    parts = []
    if rig.detect.refine == "pixels":
        parts.append(
            f'[detect] refine = "pixels" {"was" if past else "is"} set aside on them (its '
            f"errors there move with the image) for the edge lines"
        )
    if rig.detect.sigma_scale == 1.0:
        parts.append(
            f"their errors {were} wider than the edges' noise model says, and no "
            f"[detect] sigma_scale measured them (rows warned inter_frame_codec): run "
            f"`visvec calibrate zero-tilt` on level frames taken through this same stream "
            f"and use its calibration, or record losslessly (PNG frames, FFV1) or as "
            f"Motion-JPEG"
        )
    return text + ": " + "; ".join(parts) if parts else ""


class TrianglePipeline(AttitudePipeline[Detection]):
    """The triangle target; ``method`` "full" (default) or "paper".

    Parameters
    ----------
    rig : Rig
        A triangle rig.
    method : str
        'full' (camera model, lever arm; default) or 'paper'.
    still : bool
        The platform is held still (a zero-tilt calibration's frames): no rate
        between frames is used.
    check_shutter : bool
        Gather the evidence of a rolling shutter the rig does not declare."""

    methods = TRIANGLE_METHODS
    hints = {
        **Pipeline.hints,
        "inconsistent_geometry": "no attitude of the rig file's triangle explains the three "
        "vertices: check the [camera] model (an aspect fy / fx 0.5 % off or a principal point "
        "10 px off does this; `visvec calibrate zero-tilt` on level frames at several yaws "
        "says which, `visvec calibrate camera` measures it), [target] vertices_mm and [mount]; "
        "on a turning platform, a camera that reads its rows out one after another ([camera] "
        "readout_ms)",
        "no_triangle": "no bright region of the triangle's shape and size: is it in view "
        "(look at the frames with the detection drawn on them), and are [target] vertices_mm "
        "and [camera] fx right?",
        "low_contrast": "the triangle too faint against the board (under [detect] "
        "min_contrast): light it, or a longer exposure",
        "overexposed": "the triangle saturates: a shorter exposure",
        "low_brightness": "frames darker than [detect] brightness_band: a longer exposure",
        "high_brightness": "frames brighter than [detect] brightness_band: a shorter exposure",
        "obstructed": "something over the triangle, or a light touching it",
        "edge_obstructed": "something over the triangle's edges",
        "partly_out_of_view": "the triangle leaves the image: tilts beyond the field of view, "
        "or the target not above the centre of rotation",
        "no_dark_surround": "the triangle needs the dark board around it in view",
        "impossible_tilt": "tilts beyond [platform] max_tilt_deg: check [mount] rotation, or "
        "the limit",
    }

    def __init__(
        self, rig: Rig, method: str = "full", still: bool = False, check_shutter: bool = True
    ):
        if rig.kind != "triangle":
            raise ConfigError(f"TrianglePipeline needs a triangle rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.detector = TriangleDetector(rig)
        self.solve = ESTIMATORS[method]
        # the target's height, a constant of the lab, estimated over the frames ("full")
        self.height = (
            HeightTrack(rig.target.height_sigma_mm)
            if method == "full" and rig.target.height_sigma_mm > 0
            else None
        )
        # a rig that says its camera has a global shutter: do the frames agree? Once
        # they say it rolls, its readout is estimated from them and taken out
        # (``check_shutter`` False: the frames as the rig file says, for comparison)
        self.shear = (
            ReadoutEvidence.for_camera(rig.camera, rig.fps)
            if method == "full" and rig.readout_ms == 0 and not still and check_shutter
            else None
        )
        # ok rows taken out with the frames' own readout estimate
        self.n_estimated_readout = 0
        # the inter-frame codec (Frame.codec) the frames came through (notes)
        self.inter_frame_codec = ""
        # every frame taken at rest (zero-tilt calibration): a rolling shutter has no
        # motion to correct, and unrelated frames need no rate
        self.still = still
        self.R_last: np.ndarray | None = None
        # (time_s, R_nb) of the last two ok frames in a row: the rate for a rolling shutter
        self._recent: list[tuple[float, np.ndarray]] = []
        # (time_s, R_nb) of the last frame refused only because its uncorrected rolling
        # shutter sheared it (a turn faster than the rig's rate bounds): near enough to
        # give the next frame a rate
        self._sheared: tuple[float, np.ndarray] | None = None

    def reset(self) -> None:
        self.detector.reset()
        self.R_last = None
        self._recent = []
        self._sheared = None

    def after_failure(self) -> None:
        sheared = self._sheared
        self.reset()
        self._sheared = sheared

    def after_success(self, sol) -> None:
        if self.height is not None:
            self.height.update(sol)

    def notes(self) -> list[str]:
        """Why many frames were refused; the target's height, when the frames put it off
        the rig file's; the camera's aspect, likewise; a rolling shutter the rig file
        does not declare."""
        notes = super().notes()
        h = self.height
        sigma = np.sqrt(h.var_mm2) if h is not None else 0.0
        if (
            h is not None
            and h.n >= MIN_HEIGHT_FRAMES
            and abs(h.mean_mm) > max(HEIGHT_NOTE_SIGMAS * sigma, HEIGHT_NOTE_MM)
        ):
            where = "higher" if h.mean_mm > 0 else "lower"
            notes.append(
                f"visvec: the triangle looks {abs(h.mean_mm):.2f} +- {sigma:.2f} mm {where} "
                f"than the rig file's [target] vertices_mm put it (the ceiling's height, the "
                f"print's size or the focal length is off); measure it, or let `visvec "
                f"calibrate zero-tilt` write it"
            )
        notes += self._codec_note()
        if self.shear is not None:
            notes += self._camera_note()
        if self.shear is not None and self.shear.suspected():
            # first order, from frames the shear may have refused: a rough figure
            k, s = self.shear.readout_ms()
            notes.append(
                f"visvec: the frames are sheared as by a rolling shutter reading out in about "
                f"{k:.0f} +- {s:.0f} ms ({self.shear.n} turning frames), but the rig's "
                f"[camera] readout_ms is 0: {self.n_estimated_readout} ok rows were taken out "
                f"with this running estimate (warning rolling_shutter_estimated), the ones "
                f"before it biased by the turn or refused. Measure it with `visvec calibrate "
                f"readout` on a recording of the platform swinging out and back"
            )
        return notes

    def _codec_note(self) -> list[str]:
        """The frames' errors shared along the edges (CODEC_NOTE_FACTOR), as a video
        codec's or a camera's own smoothing makes them: the rows' sigma was widened for
        it; the pixel fit is not honest through an inter-frame codec. (The correlation
        does not tell the two apart: mp4v's frames and noise smoothed over 2 px read
        alike, and the pixel fit is honest on the second.)"""
        f = self.detector.correlation.factor
        codec = self.inter_frame_codec
        advice = codec_advice(self.rig, codec, True) if codec else ""
        if advice:
            return [f"visvec: {advice}"]
        if not f >= CODEC_NOTE_FACTOR:
            return []
        note = (
            f"visvec: the frames' errors are shared by neighbouring points of the "
            f"triangle's edges, as a video codec's or a camera's own smoothing makes them "
            f"(their variance {f:.1f}x what the points' scatter says): the edge lines' "
            f"sigma was widened for it. If the frames were recorded through a codec, "
            f"record losslessly (PNG frames, or Motion-JPEG at quality 95)"
        )
        if self.rig.detect.refine == "pixels":
            note += (
                '; [detect] refine = "pixels" is not honest through an inter-frame codec '
                '(rows beyond 5 sigma through mp4v): use refine = "lines" on such '
                "recordings"
            )
        return [note]

    def _camera_note(self) -> list[str]:
        """The camera's aspect fy / fx and principal point, when the frames (at least
        MIN_HEIGHT_FRAMES) say the rig file's are off (CAMERA_NOTE_SIGMAS, and ASPECT_MIN
        or PRINCIPAL_POINT_MIN; see ReadoutEvidence.camera_errors) and the model errors
        explain their residuals: an aspect 0.5 % off refuses every frame as
        inconsistent_geometry, a principal point 10 px off two in three."""
        ev = self.shear
        if ev.n < MIN_HEIGHT_FRAMES or not ev.fit_chi2_per_dof() <= MAX_FIT_CHI2_DOF:
            return []
        (dcx, dcy, e), sig = ev.camera_errors()
        cam = self.rig.camera
        least = np.r_[PRINCIPAL_POINT_MIN * cam.width, PRINCIPAL_POINT_MIN * cam.width, ASPECT_MIN]
        off = np.abs([dcx, dcy, e]) > np.maximum(CAMERA_NOTE_SIGMAS * sig, least)
        parts = []
        if off[2]:
            parts.append(
                f"aspect fy / fx is {cam.fy / cam.fx * (1 + e):.4f} +- "
                f"{cam.fy / cam.fx * sig[2]:.4f}, not the rig file's {cam.fy / cam.fx:.4f} "
                f"(fy about {cam.fy * (1 + e):.1f} px for fx {cam.fx:.1f})"
            )
        if off[0] or off[1]:
            parts.append(
                f"principal point is about cx {cam.cx + dcx:.1f} +- {sig[0]:.1f}, cy "
                f"{cam.cy + dcy:.1f} +- {sig[1]:.1f} px, not the rig file's ({cam.cx:.1f}, "
                f"{cam.cy:.1f})"
            )
        if not parts:
            return []
        return [
            f"visvec: the triangle's shape over {ev.n} frames says the camera's "
            + " and ".join(parts)
            + ": calibrate the camera (`visvec calibrate camera`; `visvec calibrate "
            "zero-tilt` checks it on level frames)"
        ]

    def _solve(self, det, guess) -> AttitudeSolution:
        """The frame's attitude; "full" with the running height as the prior."""
        if self.height is None:
            return self.solve(det, self.rig, guess)
        sol = self.solve(det, self.rig, guess, self.height.prior())
        refused = _no_rigid_fit(sol)
        if refused and self.height.n > 0:
            # the running height may be what refuses it (the lab changed: a lens
            # refocused, a zoom): judged against the rig file's prior alone, a frame
            # that passes restarts the track from itself
            alone = self.solve(det, self.rig, guess)
            if alone.status is Status.OK:
                self.height.restart()
                return alone
        return sol

    def _rate(self, a: tuple[float, np.ndarray], b: tuple[float, np.ndarray]) -> np.ndarray | None:
        """The camera's angular rate (rad/s, camera frame) between two frames' (time_s,
        R_nb); None when they are not one turn (see :func:`body_rate`)."""
        omega_b = body_rate(a, b)
        return None if omega_b is None else self.rig.R_bc.T @ omega_b

    def _camera_rate(self, t: float) -> np.ndarray | None:
        """The rate for a rolling-shutter frame at time t: zero for still frames, else
        from the last two ok frames; None without both or when they are stale."""
        if self.detector.readout_ms == 0:
            return None
        if self.still:
            return np.zeros(3)
        if len(self._recent) < 2 or not 0 < t - self._recent[-1][0] <= MAX_RATE_GAP_S:
            return None
        return self._rate(*self._recent)

    def _predicted(self, t: float) -> np.ndarray | None:
        """The attitude at time t from the last ok frame's, turned on at the rate between
        the last two (R_nb(t) = R_nb(t1) expm([omega_b] (t - t1))); the last frame's when
        there is no rate. A Gauss-Newton start one iteration nearer than the last
        attitude alone (tracking at 10 deg/s: 2 iterations instead of 3)."""
        if self.R_last is None or self.still or len(self._recent) < 2:
            return self.R_last
        omega_b = body_rate(*self._recent)
        dt = t - self._recent[-1][0]
        if omega_b is None or not 0 < dt <= MAX_RATE_GAP_S:
            return self.R_last
        return self.R_last @ expmap(omega_b * dt)

    def estimate(self, frame):
        rolling = self.detector.readout_ms != 0
        estimated = rolling and self.shear is not None
        omega_c = self._camera_rate(frame.time_s)
        coded = self.detector.inter_frame = inter_frame(frame.codec)
        if coded:
            self.inter_frame_codec = frame.codec  # (the closing note)
        det = self.detector.detect(frame.image, omega_c)
        self.last_detection = det
        if det.status is not Status.OK:
            return det.status, None, det.warnings
        # tracked vertices moved little since the last frame: its attitude, turned on
        # at the last rate, is a closer start for Gauss-Newton than the closed form,
        # and cheaper (same minimum)
        guess = self._predicted(frame.time_s) if self.detector.last_was_tracked else None
        sol = self._solve(det, guess)
        sheared = _no_rigid_fit(sol)
        if omega_c is None and rolling and (sol.status is Status.OK or sheared):
            det, sol, omega_c = self._redetect(frame, det, sol)
            sheared = _no_rigid_fit(sol)
        if self.shear is not None and (sol.status is Status.OK or sheared):
            applied = self.detector.readout_ms if omega_c is not None else 0.0
            self._add_shear_evidence(frame.time_s, det, sol, applied)
            self._use_estimated_readout()
        self._sheared = (frame.time_s, sol.R_nb) if sheared and omega_c is None else None
        self.R_last = sol.R_nb if sol.status is Status.OK else None
        warnings = det.warnings + sol.warnings
        if sol.status is Status.OK:
            self._recent = [*self._recent[-1:], (frame.time_s, sol.R_nb)]
            if omega_c is None and rolling:
                # the rate is not known (first frame, or after a loss): the rows'
                # exposure times could not be taken out; the sigma covers max_rate_dps
                warnings += ("rolling_shutter_uncorrected",)
            if estimated:
                self.n_estimated_readout += 1
                warnings += ("rolling_shutter_estimated",)
            if coded and self.rig.detect.sigma_scale == 1.0:
                # a codec that predicts frames from earlier ones: its errors are wider
                # than the edges' noise model says, and no sigma_scale measured them
                # (CODEC_WARNING)
                warnings += ("inter_frame_codec",)
        return sol.status, sol, warnings

    def _add_shear_evidence(self, t: float, det, sol: AttitudeSolution, applied_ms: float) -> None:
        """A frame ok, or refused for a shear a rolling shutter could make (chi-square
        under SHEAR_EVIDENCE_CHI2: at 20 deg/s every frame of a rolling-shutter webcam
        may be refused), with the rate since the last such frame: its residuals measure
        the readout (see :mod:`visvec.estimate.shear`) beyond the ``applied_ms`` its
        vertices were already taken out with."""
        last = self._recent[-1] if self._recent else self._sheared
        if last is None or sol.residual is None or not sol.chi2 < SHEAR_EVIDENCE_CHI2:
            return
        omega = self._rate(last, (t, sol.R_nb))
        if omega is not None:
            rows, cam, lever = det.points_px[:, 1], self.rig.camera, self.detector.lever_c
            self.shear.add(sol.residual, det.points_n, rows, cam, omega, lever, applied_ms)

    def _use_estimated_readout(self) -> None:
        """The readout the detector takes out: the frames' running estimate (and its
        sigma, in the vertices' covariance) while they say the camera rolls
        (:meth:`ReadoutEvidence.suspected`), else none, as the rig file says. A camera
        the rig file calls global-shutter is then corrected from the frame after the
        evidence passes 5 sigma; the frames before are biased by the turn or refused."""
        if self.shear.suspected():
            k, s = self.shear.readout_ms()
        else:
            k, s = 0.0, 0.0
        self.detector.readout_ms, self.detector.readout_sigma_ms = k, s

    def _redetect(self, frame, det, sol):
        """A rolling-shutter frame detected without a rate (the second after an
        acquisition, or one whose uncorrected shear no rigid triangle fits): its own
        attitude and the last frame's (ok, or refused only for that shear) give the rate,
        and it is detected again with it. (det, sol, omega_c), unchanged (omega_c None)
        when there is no such last frame or the second pass fails."""
        last = self._recent[-1] if self._recent else self._sheared
        if last is None:
            return det, sol, None
        omega_c = self._rate(last, (frame.time_s, sol.R_nb))
        if omega_c is None:
            return det, sol, None
        det2 = self.detector.redetect(frame.image, omega_c)
        if det2.status is not Status.OK:
            return det, sol, None
        sol2 = self._solve(det2, sol.R_nb)
        if sol2.status is not Status.OK:
            return det, sol, None
        self.last_detection = det2
        return det2, sol2, omega_c
