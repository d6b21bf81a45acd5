"""Pipelines: frame -> detection -> attitude -> row, one per target kind.

:class:`Pipeline` holds what every kind shares (frame checks, the safety net for bugs,
the physically-possible tilt check, latency); a subclass turns one good image into an
attitude solution. :func:`make_pipeline` picks the class for a rig.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, fields

import numpy as np

from visvec.data import AttitudeSolution, Frame, Status
from visvec.detect import TriangleDetector
from visvec.detect.flow import MARGIN_PX, Matches, match_stars, signal
from visvec.detect.lamps import LampIdentifier
from visvec.detect.markers import VISIBLE_MARGIN_PX, MarkerIdentifier
from visvec.detect.spots import Spots, find_spots
from visvec.detect.stars import (
    Residual,
    StarField,
    background,
    residual,
    segment_edges,
    stars_of,
)
from visvec.errors import ConfigError
from visvec.estimate import ESTIMATORS
from visvec.estimate.markers import solve_markers
from visvec.estimate.planar import MIN_LAMPS, PlanarSolution, solve_planar
from visvec.estimate.pnp import PNP_FLAGS, solve_pnp
from visvec.estimate.rate import MIN_STARS, RateSolution, estimate_rate, unit_vectors
from visvec.estimate.shear import (
    ASPECT_MIN,
    CAMERA_NOTE_SIGMAS,
    MAX_FIT_CHI2_DOF,
    PRINCIPAL_POINT_MIN,
    ReadoutEvidence,
)
from visvec.estimate.triangle_full import CHI2_REJECT, HeightTrack
from visvec.lamps import Catalog
from visvec.output import AttitudeRow, PoseRow, RateRow, Row, attitude_row
from visvec.rig import Rig
from visvec.rotations import expmap, logmap

TRIANGLE_METHODS = tuple(ESTIMATORS)
MARKER_METHODS = ("full", *PNP_FLAGS)
METHODS = tuple(dict.fromkeys(TRIANGLE_METHODS + MARKER_METHODS + ("poisson", "crassidis")))


# the run's closing note on its refused frames: when at least this share of its frames
# and at least this many were not ok
REFUSED_NOTE_SHARE = 0.1
REFUSED_NOTE_MIN = 3
# the reasons the note names (the most frequent first)
REFUSED_NOTE_REASONS = 4


class Pipeline:
    """Shared frame loop of every target kind. Subclasses implement :meth:`estimate`
    and :meth:`make_row`."""

    methods: tuple[str, ...] = ()
    row_type: type[Row] = Row
    # what to check when many frames are refused with a warning code (or a status)
    hints: dict[str, str] = {
        "read_error": "frames unreadable or not the rig's [camera] width x height",
        "internal_error": "a bug met on those frames (each printed above): please report it",
    }

    def __init__(self, rig: Rig, method: str = "full"):
        if method not in self.methods:
            raise ConfigError(
                f"method = {method!r} for a {rig.kind} rig: expected one of {list(self.methods)}"
            )
        self.rig = rig
        self.method = method
        self.last_detection: object | None = None
        self.last_solution: AttitudeSolution | None = None
        self.last_error = ""
        # the run's rows, and its refused ones by reason (their warnings, or the status)
        self.n_rows = 0
        self.refused: Counter[str] = Counter()

    def check_frame(self, frame: Frame) -> str:
        """Why a frame cannot be used at all ("" if it can)."""
        if frame.image is None:
            return frame.error or "unreadable frame"
        img = frame.image
        cam = self.rig.camera
        if img.ndim != 2 or img.size == 0:
            return f"{frame.name}: expected a grey image, got shape {img.shape}"
        if img.shape != (cam.height, cam.width):
            return (
                f"{frame.name}: image is {img.shape[1]}x{img.shape[0]}, expected "
                f"{cam.width}x{cam.height} (the rig's camera)"
            )
        return ""

    def reset(self) -> None:
        """Forget the previous frame."""

    def after_failure(self) -> None:
        """Called after a frame without an ok row (forgets the previous frame)."""
        self.reset()

    def estimate(self, frame: Frame) -> tuple[Status, object | None, tuple[str, ...]]:
        """Status, solution (or None) and warnings of one readable frame."""
        raise NotImplementedError

    def make_row(
        self,
        frame: Frame,
        status: Status,
        sol: object | None,
        warnings: tuple[str, ...],
        latency_ms: float,
    ) -> Row:
        raise NotImplementedError

    def check_solution(
        self, status: Status, sol: object | None, warnings: tuple[str, ...]
    ) -> tuple[Status, tuple[str, ...]]:
        """A last physical check of an ok solution (none by default)."""
        return status, warnings

    def after_success(self, sol: object) -> None:
        """Called with the solution of every row that is ok (nothing by default)."""

    def notes(self) -> list[str]:
        """What the run found out about the rig, for the operator at its end: here, why
        its frames were refused when many were (:meth:`refused_note`)."""
        note = self.refused_note()
        return [note] if note else []

    def refused_note(self) -> str:
        """The refused rows by reason, with what to check for each (``hints``), when
        REFUSED_NOTE_SHARE of the run's rows (at least REFUSED_NOTE_MIN) were not ok;
        "" otherwise."""
        n_bad = sum(self.refused.values())
        if n_bad < max(REFUSED_NOTE_MIN, REFUSED_NOTE_SHARE * self.n_rows):
            return ""
        top = self.refused.most_common(REFUSED_NOTE_REASONS)
        counts = ", ".join(f"{reason} {n}" for reason, n in top)
        if len(self.refused) > len(top):
            counts += ", other reasons " + str(n_bad - sum(n for _, n in top))
        codes = dict.fromkeys(c for reason, _ in top for c in reason.split(";"))
        hints = [f"{c}: {self.hints[c]}" for c in codes if c in self.hints]
        text = f"visvec: {n_bad} of {self.n_rows} frames not ok ({counts})"
        return text + ("; " + "; ".join(hints) if hints else "")

    def process(self, frame: Frame, t_in: float | None = None) -> Row:
        """The row of one frame; never raises on frame content."""
        row = self._process(frame, t_in)
        self.n_rows += 1
        if not row.ok:
            self.refused[row.reason] += 1
        return row

    def _process(self, frame: Frame, t_in: float | None) -> Row:
        t_in = time.perf_counter() if t_in is None else t_in
        self.last_detection, self.last_solution, self.last_error = None, None, ""
        if self.check_frame(frame):
            self.reset()
            return self.make_row(frame, Status.READ_ERROR, None, ("read_error",), _ms(t_in))
        try:
            status, sol, warnings = self.estimate(frame)
        except Exception as exc:  # noqa: BLE001 - one bad frame must not end the run
            # a bug met on this frame's content: refuse the frame, keep the run going,
            # and keep the message for the caller to report
            self.last_error = f"{type(exc).__name__}: {exc}"
            self.reset()
            return self.make_row(frame, Status.REJECTED, None, ("internal_error",), _ms(t_in))
        self.last_solution = sol
        if status is Status.OK and sol is not None:
            status, warnings = self.check_solution(status, sol, warnings)
        if status is Status.OK:
            self.after_success(sol)
        else:
            self.after_failure()
        return self.make_row(frame, status, sol, warnings, _ms(t_in))

    def run(
        self, frames: Iterable[Frame], on_frame: Callable[[Frame, Row], None] | None = None
    ) -> Iterator[Row]:
        """Rows of all frames, lazily; ``on_frame`` sees each frame with its row."""
        for frame in frames:
            row = self.process(frame)
            if on_frame is not None:
                on_frame(frame, row)
            yield row


class AttitudePipeline(Pipeline):
    """Attitude rows (triangle, markers), with the physically-possible tilt check."""

    row_type = AttitudeRow

    def make_row(self, frame, status, sol, warnings, latency_ms):
        return attitude_row(frame.index, frame.time_s, sol, status, warnings, latency_ms)

    def check_solution(self, status, sol, warnings):
        tilt = np.degrees(np.arccos(np.clip(sol.R_nb[2, 2], -1.0, 1.0)))
        if tilt > self.rig.max_tilt_deg:
            return Status.REJECTED, warnings + ("impossible_tilt",)
        return status, warnings


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
    if np.degrees(np.linalg.norm(omega_b)) > MAX_RATE_DPS:
        return None
    return omega_b


class TrianglePipeline(AttitudePipeline):
    """The triangle target; ``method`` "full" (default) or "paper"."""

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
        "(look with --overlay DIR), and are [target] vertices_mm and [camera] fx right?",
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


@dataclass(frozen=True)
class MarkerDetection:
    """Spots of one marker frame and their marker ids (-1: not a marker)."""

    spots: Spots
    ids: np.ndarray
    reason: str = ""


# merged spots (two LEDs, or an LED and a reflection) are longer than round ones
MAX_ELONGATION = 1.8
TRACK_WINDOW_PX = 24


class MarkerPipeline(AttitudePipeline):
    """LED markers seen by a camera fixed in the lab; ``method`` "full" (the constrained
    3-parameter solver) or a PnP baseline ("pnp-sqpnp", "pnp-ippe", ...)."""

    methods = MARKER_METHODS
    hints = {
        **Pipeline.hints,
        "not_identified": "the spots do not match the rig's marker layout: check [target] "
        "and the exposure (LEDs only)",
        "too_few_markers": "too few markers identified (LEDs hidden or out of view)",
        "inconsistent_geometry": "no attitude about the centre of rotation fits the markers: "
        "`visvec calibrate system`",
    }

    def __init__(self, rig: Rig, method: str = "full"):
        if rig.kind != "markers":
            raise ConfigError(f"MarkerPipeline needs a markers rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.sigma_px = rig.detect.centroid_sigma_px
        self.identifier = MarkerIdentifier(rig, self.sigma_px)
        self.R_last: np.ndarray | None = None

    def reset(self) -> None:
        self.R_last = None

    def _spots(self, image: np.ndarray, R_pred: np.ndarray | None) -> Spots:
        d = self.rig.detect
        windows = None
        if R_pred is not None:
            uv = self._markers_px(R_pred)
            h = TRACK_WINDOW_PX
            windows = [(u - h, v - h, u + h + 1, v + h + 1) for u, v in uv if np.isfinite(u)]
        return find_spots(image, d.threshold, d.min_spot_px, d.max_spot_px, windows)

    def estimate(self, frame):
        image = frame.image
        warnings: list[str] = []
        tracking = self.R_last is not None
        spots = self._spots(image, self.R_last)
        ident = None
        for attempt in ("track", "search") if tracking else ("search",):
            if attempt == "search" and tracking:
                spots = self._spots(image, None)
            xy = self.rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
            # a spot beyond the lens model's field has no ray (nan): left out, as merged
            # spots are
            beyond = ~np.isfinite(xy).all(axis=1)
            good = (spots.elongation <= MAX_ELONGATION) & ~beyond
            ident = self.identifier.identify(xy[good], self.R_last if attempt == "track" else None)
            ids = np.full(len(spots), -1)
            ids[np.nonzero(good)[0]] = ident.ids
            if ident.R_nb is not None:
                break
        self.last_detection = MarkerDetection(spots, ids, ident.reason)
        if np.any(~good & ~beyond):
            warnings.append("merged_spot")
        if np.any(beyond):
            warnings.append("beyond_lens_model")
        if ident.R_nb is None:
            status = Status.NO_TARGET if len(spots) == 0 else Status.REJECTED
            return status, None, tuple(warnings + [ident.reason or "not_identified"])
        sel = ids >= 0
        n_vis = self._visible_count(ident.R_nb)
        if sel.sum() < n_vis:
            warnings.append("missing_markers")
        if np.any(~sel & good):
            warnings.append("extra_spots")
        if self.method == "full":
            sol = solve_markers(xy[sel], ids[sel], self.rig, self.sigma_px, ident.R_nb)
        else:
            sol = solve_pnp(spots.centroids_px[sel], ids[sel], self.rig, self.method, self.sigma_px)
        if sol.status is Status.OK:
            self.R_last = sol.R_nb if self.method == "full" else ident.R_nb
        return sol.status, sol, tuple(warnings) + sol.warnings

    def _markers_px(self, R_nb: np.ndarray) -> np.ndarray:
        """(K, 2) the markers' pixels at attitude R_nb (nan past the lens model's field)."""
        return self.identifier.pixels(R_nb)

    def _visible_count(self, R_nb: np.ndarray) -> int:
        return int(np.sum(self.rig.camera.in_image(self._markers_px(R_nb), VISIBLE_MARGIN_PX)))


RATE_METHODS = ("poisson", "crassidis")
SATURATED_FRACTION = 0.02
BOOTSTRAP_STARS = 12
FULL_SEARCH_EVERY = 20
# a detection whose peak is less than 1 sigma over the mu + 3 sigma threshold is not
# matched once the rate is known: at 4 sigma, pure noise still lights about 40 pixels
# of a 1280 x 1024 frame (at 3 sigma about 1800), and such faint stars would weigh
# little anyway
MIN_PEAK_SNR = 1.0
BACKGROUND_EVERY = 5
FRAME_GAP_TOLERANCE = 1.5  # a frame later than this many periods is a jump


@dataclass(frozen=True)
class RateDetection:
    """Stars of the current frame and the matches from the previous one."""

    stars: StarField
    matches: Matches | None = None
    inliers: np.ndarray | None = None


@dataclass
class _PreviousFrame:
    time_s: float
    stars: StarField
    sig: np.ndarray


class RatePipeline(Pipeline):
    """Angular rate of a star camera from consecutive frames (Fasano et al. 2013);
    ``method`` "poisson" (the paper, default) or "crassidis". One row per frame: the
    rate over the interval from the previous frame to this one.

    Beyond the paper, stars are tracked: once a rate is known, a frame's stars are the
    ones matched into it from the previous frame plus those found in the bands along
    the image edges where new stars enter; the whole frame is searched again every
    FULL_SEARCH_EVERY (20) frames, after any failure, or when few stars remain. This
    skips the connected-component labelling of most frames, the largest cost at
    1280 x 1024. The smooth background is re-estimated every BACKGROUND_EVERY (5)
    frames while tracking (every frame otherwise); noise and threshold every frame.
    """

    methods = RATE_METHODS
    hints = {
        **Pipeline.hints,
        "too_few_stars": "too few stars: a longer exposure, or a part of the sky with more",
        "saturated": "the frames saturate: a shorter exposure",
        "frame_jump": "frames not 1 / fps apart (dropped frames, or a folder without its times)",
        "rate_beyond_max": "a rate above [target] max_rate_dps",
    }
    row_type = RateRow

    def __init__(self, rig: Rig, method: str = "poisson"):
        if rig.kind != "starfield":
            raise ConfigError(f"RatePipeline needs a starfield rig, not {rig.kind!r}")
        super().__init__(rig, method)
        cam = rig.camera
        self.f_px = float(min(cam.fx, cam.fy))
        self.dt_nominal = 1.0 / rig.fps
        self.w_max = np.radians(rig.target.max_rate_dps)
        self.exposure_s = (rig.exposure_ms / 1000.0) if rig.exposure_ms else self.dt_nominal
        corner = np.hypot(cam.width, cam.height) / 2.0 / self.f_px
        self.flow_gain = self.f_px * (1.0 + corner**2)  # px per rad at the field's corner
        self.streak_px = self.w_max * self.exposure_s * self.flow_gain
        self.sigma_px = rig.detect.centroid_sigma_px
        self.prev: _PreviousFrame | None = None
        self.omega: np.ndarray | None = None
        self.since_full = 0
        self.bg: np.ndarray | None = None

    def reset(self) -> None:
        self.prev = None
        self.omega = None

    def after_failure(self) -> None:
        """:meth:`estimate` keeps the frame as the next one's predecessor when it can."""

    def _full_radius(self, dt: float) -> int:
        return int(np.ceil(self.w_max * dt * self.flow_gain)) + 2

    def _shifts(self, uv1: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
        """Predicted pixel displacement of each star after dt at rate omega."""
        cam = self.rig.camera
        u = unit_vectors(cam.undistort(uv1))
        p = u @ expmap(-omega * dt).T
        # a star beyond the lens model's field (nan): no prediction, searched where it was
        return np.nan_to_num(cam.project(p) - uv1)

    def _solve(self, m: Matches, dt: float, noise: tuple[float, float]) -> RateSolution:
        """The rate from matched stars; ``noise`` the pixel noise sigma of the first
        and second frame, which with each centroid's spread gives its variance."""
        cam = self.rig.camera
        xy1 = cam.undistort(m.uv1) if len(m) else np.zeros((0, 2))
        xy2 = cam.undistort(m.uv2) if len(m) else np.zeros((0, 2))
        var = (noise[0] ** 2 * m.spread1 + noise[1] ** 2 * m.spread2) / 2.0  # per axis
        return estimate_rate(xy1, xy2, dt, self.f_px, self.sigma_px, self.method, var)

    def _match(
        self, prev: _PreviousFrame, sig: np.ndarray, dt: float, noise: tuple[float, float]
    ) -> Matches:
        first = prev.stars
        n = len(first)
        zero = np.zeros((n, 2))
        omega = self.omega
        if omega is None:
            # bootstrap: the brightest stars searched over the whole range give a first rate
            bright = np.argsort(-first.flux)[:BOOTSTRAP_STARS]
            rad = np.full(n, self._full_radius(dt))
            m = self._with_rays(match_stars(first, prev.sig, sig, zero, rad, bright))
            if len(m) >= MIN_STARS:
                sol = self._solve(m, dt, noise)
                if sol.ok:
                    omega = sol.omega
            if omega is None:
                return self._with_rays(match_stars(first, prev.sig, sig, zero, rad))
        shifts = self._shifts(first.centroids_px, omega, dt)
        # detections whose peak is clearly above the noise (carried stars have an
        # infinite one: they were matched before)
        which = np.nonzero(first.peak_snr >= MIN_PEAK_SNR)[0]
        radius = np.full(n, self._radius(omega, dt))
        return self._with_rays(match_stars(first, prev.sig, sig, shifts, radius, which))

    def _with_rays(self, m: Matches) -> Matches:
        """The matches whose stars both have a ray: one beyond the lens model's field
        (CameraModel.field_r2) has none, and is left out."""
        cam = self.rig.camera
        if not cam.has_distortion or len(m) == 0:
            return m
        ok = (np.isfinite(cam.undistort(m.uv1)) & np.isfinite(cam.undistort(m.uv2))).all(axis=1)
        return m if ok.all() else Matches(*(getattr(m, f.name)[ok] for f in fields(Matches)))

    def _bands(self, dt: float) -> tuple[int, int, int, int]:
        """Widths (top, bottom, left, right) of the edge bands where this frame may hold
        stars that tracking did not carry: on each edge the largest inward flow (new
        stars), plus the search radius and margin (stars near an edge whose search
        window left the image), plus a star's extent (its streak and 8 px of blur)."""
        cam = self.rig.camera
        w, h = cam.width - 1.0, cam.height - 1.0
        s = np.linspace(0.0, 1.0, 9)
        z, one = np.zeros(9), np.ones(9)
        pts = np.vstack(
            [np.c_[s * w, z], np.c_[s * w, one * h], np.c_[z, s * h], np.c_[one * w, s * h]]
        )
        d = self._shifts(pts, self.omega, dt).reshape(4, 9, 2)
        inward = (d[0, :, 1].max(), -d[1, :, 1].min(), d[2, :, 0].max(), -d[3, :, 0].min())
        streak = np.linalg.norm(d, axis=2).max(axis=1) * self.exposure_s / dt
        extent = self._radius(self.omega, dt) + MARGIN_PX + 8 + 4
        return tuple(
            int(np.ceil(max(a, 0.0) + b + extent)) for a, b in zip(inward, streak, strict=True)
        )

    def _radius(self, omega: np.ndarray, dt: float) -> int:
        """Search half-width around a tracked star's predicted shift: the rate may have
        changed by 10 % (and 3 px) since it was measured."""
        return 3 + int(np.ceil(0.1 * np.linalg.norm(omega) * dt * self.flow_gain))

    def _carry(self, m: Matches, inliers: np.ndarray, res: Residual, dt: float) -> StarField:
        """This frame's stars when tracking: the matched ones, and new ones entering
        through the bands along the edges."""
        cents, boxes = [m.uv2[inliers]], [m.bbox2[inliers]]
        flux, area = [m.flux2[inliers]], [self.prev.stars.area_px[m.index[inliers]]]
        snr = [np.full(len(cents[0]), np.inf)]  # carried: matched whatever their peak
        seg = segment_edges(res, self._bands(dt), self.streak_px)
        if len(seg.cents):
            d = np.linalg.norm(seg.cents[:, None] - cents[0][None], axis=2)
            new = d.min(axis=1) > 4.0 if d.size else np.ones(len(seg.cents), bool)
            cents.append(seg.cents[new])
            boxes.append(seg.boxes[new])
            flux.append(seg.flux[new])
            area.append(seg.area[new])
            snr.append(seg.snr[new])
        c = np.vstack(cents)
        spread = np.zeros(len(c))
        spread[: len(boxes[0])] = m.spread2[inliers]
        return StarField(
            c, np.concatenate(flux), np.concatenate(area), np.concatenate(snr), True, "",
            res.sigma, 0.0, 1.0, threshold=res.threshold, signal=res.sig,
            bbox_px=np.vstack(boxes), windowed=np.arange(len(c)) < len(boxes[0]),
            spread=spread,
        )  # fmt: skip

    def estimate(self, frame):
        img = frame.image
        top = 255 if img.dtype == np.uint8 else int(np.iinfo(img.dtype).max)
        if img.max() >= top and np.count_nonzero(img >= top) > SATURATED_FRACTION * img.size:
            self.reset()
            return Status.REJECTED, None, ("saturated",)
        if self.bg is None or not self.since_full % BACKGROUND_EVERY or self.omega is None:
            self.bg = background(img)  # a smooth sky changes slowly: refreshed every 5
        res = residual(img, self.bg)
        sig = signal(res)
        prev = self.prev
        dt = frame.time_s - prev.time_s if prev is not None else 0.0
        jump = prev is not None and not 0.0 < dt <= FRAME_GAP_TOLERANCE * self.dt_nominal
        tracking = (
            prev is not None
            and not jump
            and self.omega is not None
            and self.since_full < FULL_SEARCH_EVERY
        )
        stars = None
        if not tracking:
            stars = stars_of(res, self.streak_px)
            self.since_full = 0
            self.last_detection = RateDetection(stars)
            if not stars.usable:
                self.reset()
                return Status.NO_TARGET, None, (stars.reason,)
        if prev is None or jump:
            self.prev, self.omega = _PreviousFrame(frame.time_s, stars, sig), None
            return (Status.NO_TARGET, None, ("first_frame",)) if not jump else (
                Status.REJECTED, None, ("frame_jump",))  # fmt: skip
        noise = (prev.stars.noise_sigma, res.sigma)
        m = self._match(prev, sig, dt, noise)
        sol = self._solve(m, dt, noise)
        if stars is None:
            if sol.ok:
                stars = self._carry(m, sol.inliers, res, dt)
                self.since_full += 1
            if stars is None or len(stars) < 4 * MIN_STARS:
                stars = stars_of(res, self.streak_px)
                self.since_full = 0
        self.last_detection = RateDetection(stars, m, sol.inliers)
        self.prev = _PreviousFrame(frame.time_s, stars, sig)
        if not sol.ok:
            self.omega = None
            return Status.REJECTED, sol, (sol.reason,)
        if np.linalg.norm(sol.omega) > 1.2 * self.w_max:
            self.omega = None
            return Status.REJECTED, sol, ("rate_beyond_max",)
        self.omega = sol.omega
        warnings = ("few_stars",) if sol.n_points < 3 * MIN_STARS else ()
        return Status.OK, sol, warnings

    def make_row(self, frame, status, sol, warnings, latency_ms):
        if status is not Status.OK or sol is None:
            n = sol.n_points if sol is not None else 0
            return RateRow(frame.index, frame.time_s, status, np.nan, n, latency_ms, warnings)
        return RateRow(
            frame.index,
            frame.time_s,
            status,
            sol.rms_px,
            sol.n_points,
            latency_ms,
            warnings,
            w_dps=np.degrees(sol.omega),
            sigma_dps=np.degrees(np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))),
        )


@dataclass(frozen=True)
class LampDetection:
    """Spots of one lamp frame, their lamp ids (-1: none) and how they were found."""

    spots: Spots
    ids: np.ndarray
    mode: str = ""  # "track" or "lost_in_space"
    reason: str = ""
    votes: int = 0


EDGE_PX = 5.0  # lamp spots closer than this to the image border may be cut
MIN_TRACKED_FRACTION = 0.5  # of the spots, matched from the predicted pose, to keep tracking


class LampPipeline(Pipeline):
    """Position and heading of a mock-up from ceiling lamps (LuVeX, Keldysh preprint
    2011-24): spots, identification (tracking from the predicted pose, else the paper's
    Delaunay lookup), and a least-squares fit over every identified lamp."""

    methods = ("full",)
    hints = {
        **Pipeline.hints,
        "no_lamps": "no bright spots: are the lamps on and in view?",
        "too_few_lamps": "too few lamps seen or identified",
        "no_catalogue_match": "the lamps' triangles match none of the lamp map's: check the "
        "map and the [camera] model",
        "no_consensus": "no pose agreed by the lamps' triangles: check the map and the "
        "[camera] model",
    }
    row_type = PoseRow

    def __init__(self, rig: Rig, method: str = "full", catalog: Catalog | None = None):
        if rig.kind != "lamps":
            raise ConfigError(f"LampPipeline needs a lamps rig, not {rig.kind!r}")
        super().__init__(rig, method)
        self.identifier = LampIdentifier(rig, catalog)
        self.sigma_px = rig.detect.centroid_sigma_px
        self.track_state: tuple[float, np.ndarray, np.ndarray | None] | None = None

    def reset(self) -> None:
        self.track_state = None

    def _predict(self, t: float) -> np.ndarray | None:
        if self.track_state is None:
            return None
        t0, pose, vel = self.track_state
        return pose if vel is None else pose + vel * (t - t0)

    def _fit(self, xy: np.ndarray, ident) -> PlanarSolution:
        sel = ident.ids >= 0
        lamps = self.identifier.lamps[ident.ids[sel]]
        return solve_planar(xy[sel], lamps, self.rig, self.sigma_px, ident.pose)

    def estimate(self, frame):
        d = self.rig.detect
        spots = find_spots(frame.image, d.threshold, d.min_spot_px, d.max_spot_px)
        # a lamp cut by the image border has a biased centroid: left out (and one beyond
        # the lens model's field, which has no ray: nan)
        xy = self.rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
        keep = self.rig.camera.in_image(spots.centroids_px, EDGE_PX) & np.isfinite(xy).all(1)
        if not keep.all():
            spots = Spots(*(a[keep] for a in (spots.centroids_px, spots.flux, spots.area_px,
                                               spots.elongation, spots.saturated)),
                          spots.threshold)  # fmt: skip
            xy = xy[keep]
        self.last_detection = LampDetection(spots, np.full(len(spots), -1))
        if len(spots) == 0:
            return Status.NO_TARGET, None, ("no_lamps",)
        pred = self._predict(frame.time_s)
        sol, ident, mode = None, None, "track"
        if pred is not None:
            ident = self.identifier.track(xy, pred)
            if ident.n_identified >= max(MIN_LAMPS + 1, MIN_TRACKED_FRACTION * len(xy)):
                sol = self._fit(xy, ident)
        if sol is None or not sol.ok:
            mode = "lost_in_space"
            ident = self.identifier.lost_in_space(xy)
            if ident.pose is None:
                self.last_detection = LampDetection(spots, ident.ids, mode, ident.reason)
                return Status.REJECTED, None, (ident.reason,)
            sol = self._fit(xy, ident)
        ids = ident.ids.copy()
        if sol.inliers is not None:
            ids[np.nonzero(ids >= 0)[0][~sol.inliers]] = -1
        self.last_detection = LampDetection(spots, ids, mode, ident.reason, ident.votes)
        if not sol.ok:
            return sol.status, sol, sol.warnings
        warnings = list(sol.warnings)
        if np.sum(ids < 0) > 0:
            warnings.append("extra_spots")
        if self.track_state is not None and frame.time_s > self.track_state[0]:
            t0, p0, _ = self.track_state
            dp = sol.pose - p0
            dp[2] = (dp[2] + np.pi) % (2 * np.pi) - np.pi
            vel = dp / (frame.time_s - t0)
        else:
            vel = None
        self.track_state = (frame.time_s, sol.pose.copy(), vel)
        return Status.OK, sol, tuple(warnings)

    def make_row(self, frame, status, sol, warnings, latency_ms):
        if status is not Status.OK or sol is None:
            n = sol.n_points if sol is not None else 0
            return PoseRow(frame.index, frame.time_s, status, np.nan, n, latency_ms, warnings)
        sig = np.sqrt(np.clip(np.diag(sol.cov), 0.0, None))
        sig[2] = np.degrees(sig[2])
        pose = np.array([sol.pose[0], sol.pose[1], np.degrees(sol.pose[2])])
        return PoseRow(
            frame.index, frame.time_s, status, sol.rms_px, sol.n_points, latency_ms, warnings,
            pose=pose, sigma=sig,
        )  # fmt: skip


DEFAULT_METHODS = {"triangle": "full", "markers": "full", "starfield": "poisson", "lamps": "full"}


def make_pipeline(rig: Rig, method: str | None = None) -> Pipeline:
    """The pipeline for the rig's target kind (``method`` None: the kind's default)."""
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


def _ms(t_in: float) -> float:
    return (time.perf_counter() - t_in) * 1000.0
