"""Which spot is which marker.

Tracking: the markers are projected at the last attitude and each takes the nearest
spot within a gate (one-to-one). Lost: attitude hypotheses on a grid (yaw over the circle,
tilts within the rig's range; with a reference marker, the STASIS scheme narrows yaw:
the spot farthest from the mean of all spots is the reference, Sec. 3.2) are scored by
how many projected markers land near a spot; the best few are refined by alternating
matching and the constrained solve with shrinking gates. Explanations are compared by
their faults (spots named no marker, markers in view without a spot); a layout that two
different identifications explain within one fault is refused as ambiguous: a wrong
identification must never become an ok row.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from visvec.estimate.markers import solve_markers
from visvec.geometry import lab_camera_offset_c
from visvec.rig import Rig
from visvec.rotations import euler_to_matrices

GRID_YAW_STEP_DEG = 2.0
GRID_TILT_STEP_DEG = 4.0
COARSE_GATE_PX = 45.0
REFINE_GATES_PX = (40.0, 12.0, 5.0)
TOP_HYPOTHESES = 6
# a marker projected this far inside the image border is expected to show a spot
VISIBLE_MARGIN_PX = 3.0


# SpotGate's grid: this many cells per gate, its distances' margin (cells) for the
# float32 of cv2.distanceTransform; points are looked up this many at a time (their
# arrays then stay in the cache)
GATE_CELLS = 8
GATE_FLOAT_MARGIN = 1e-3
GATE_CHUNK = 8192


class SpotGate:
    """Whether points lie within ``gate`` of any of the ``spots`` (N, 2), as a k-d tree
    query bounded by the gate says (scipy's cKDTree, distance_upper_bound): the same
    answer, several times sooner for the markers' grid search (220,000 points a frame).

    The spots are marked on a grid of cells gate / GATE_CELLS wide and the grid's
    Euclidean distance transform gives, at each point's cell, the distance D from its
    centre to the nearest marked cell's centre. A point lies within half a cell's
    diagonal of its cell's centre and a spot of its own: the point's distance to the
    nearest spot is within a cell's diagonal of D. Points with D clear of the gate by
    more than that are decided by it; the few within it, by the k-d tree. A point off
    the grid (it reaches a gate and two cells beyond the spots), or not finite, is near
    none."""

    def __init__(self, spots: np.ndarray, gate: float):
        from scipy.spatial import cKDTree

        self.gate = float(gate)
        self.tree = cKDTree(spots) if len(spots) else None
        self.inv = GATE_CELLS / self.gate  # cells per unit
        if self.tree is None:
            return
        margin = self.gate + 2.0 * self.gate / GATE_CELLS
        self.lo = spots.min(axis=0) - margin
        self.size = np.ceil((spots.max(axis=0) + margin - self.lo) * self.inv).astype(int) + 1
        grid = np.full((self.size[1], self.size[0]), 255, np.uint8)
        cells = np.floor((spots - self.lo) * self.inv).astype(int)
        grid[cells[:, 1], cells[:, 0]] = 0
        # one cell all round beyond the grid, infinitely far: where points off it land
        self.dist = np.full((self.size[1] + 2, self.size[0] + 2), np.inf, np.float32)
        self.dist[1:-1, 1:-1] = cv2.distanceTransform(grid, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        slack = np.sqrt(2.0) + GATE_FLOAT_MARGIN
        self.sure, self.unsure = GATE_CELLS - slack, GATE_CELLS + slack

    def near(self, pts: np.ndarray) -> np.ndarray:
        """(K,) bool for the points ``pts`` (K, 2)."""
        out = np.zeros(len(pts), bool)
        if self.tree is None:
            return out
        for start in range(0, len(pts), GATE_CHUNK):
            out[start : start + GATE_CHUNK] = self._near(pts[start : start + GATE_CHUNK])
        return out

    def _near(self, pts: np.ndarray) -> np.ndarray:
        # each point's cell, one beyond the grid where it is off it (nan: below it)
        with np.errstate(invalid="ignore"):
            u = np.floor((pts[:, 0] - self.lo[0]) * self.inv)
            v = np.floor((pts[:, 1] - self.lo[1]) * self.inv)
            u = np.fmin(np.fmax(u, -1.0), self.size[0]) + 1.0
            v = np.fmin(np.fmax(v, -1.0), self.size[1]) + 1.0
        D = self.dist.ravel()[(v * self.dist.shape[1] + u).astype(np.intp)]
        near = D < self.sure
        check = np.flatnonzero((D >= self.sure) & (D <= self.unsure))
        if len(check):
            d, _ = self.tree.query(pts[check], distance_upper_bound=self.gate)
            near[check] = np.isfinite(d)
        return near


@dataclass(frozen=True)
class Identification:
    """ids : (N,) marker id of each spot, -1 for a spot that is no marker;
    R_nb : attitude found while identifying (None if none); reason when it failed."""

    ids: np.ndarray
    R_nb: np.ndarray | None
    reason: str = ""


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2-D similarity (A = s R, b) minimising |dst - (A src + b)|^2 (Umeyama 1991, with
    the reflection branch excluded)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    S, D = src - ms, dst - md
    U, sv, Vt = np.linalg.svd(D.T @ S)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ np.diag([1.0, d]) @ Vt
    scale = (sv[0] + d * sv[1]) / max((S**2).sum(), 1e-300)
    A = scale * R
    return A, md - A @ ms


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1.0, 1.0)))


class MarkerIdentifier:
    """Identifies spots (in undistorted normalised coordinates) as the rig's markers."""

    def __init__(
        self, rig: Rig, sigma_px: float, final_gate_px: float | None = None, six_dof: bool = False
    ):
        self.rig = rig
        # six_dof: refine with a free translation (solvePnP) instead of the constraint,
        # for rigs whose camera distance and body offset are still rough (calibration)
        self.six_dof = six_dof
        self.sigma_px = sigma_px
        # the last matching gate: 5 sigma of the centroid noise when the rig is right; a
        # calibration run whose rig is still rough passes a wider one
        self.final_gate_px = final_gate_px or max(5.0 * sigma_px, 1.0)
        self.f = rig.camera.fx
        self.X = rig.target.points_b
        self.t_c = lab_camera_offset_c(rig)
        self.R_cn = rig.R_nc.T

    def project(self, R_nb: np.ndarray) -> np.ndarray:
        """(M, 2) normalised image positions of all markers at attitude R_nb."""
        p = self.X @ (self.R_cn @ R_nb).T + self.t_c
        return p[:, :2] / p[:, 2:3]

    def pixels(self, R_nb: np.ndarray) -> np.ndarray:
        """(M, 2) the markers' pixels at attitude R_nb (nan past the lens model's field)."""
        xy = self.project(R_nb)
        return self.rig.camera.project(np.column_stack([xy, np.ones(len(xy))]))

    def faults(self, ids: np.ndarray, R_nb: np.ndarray) -> int:
        """What an identification leaves unexplained: spots it names no marker, and
        markers it puts in the image (VISIBLE_MARGIN_PX inside its border) without a
        spot."""
        visible = self.rig.camera.in_image(self.pixels(R_nb), VISIBLE_MARGIN_PX)
        visible[ids[ids >= 0]] = False
        return int(np.sum(ids < 0) + np.sum(visible))

    def match(self, xy: np.ndarray, pred: np.ndarray, gate_px: float) -> np.ndarray:
        """(N,) marker id per spot: mutual nearest neighbours within the gate, else -1."""
        ids = np.full(len(xy), -1)
        if len(xy) == 0 or len(pred) == 0:
            return ids
        g = gate_px / self.f
        # all spot-marker distances at once (tens by tens: cheaper than two k-d trees)
        d2 = (xy[:, 0:1] - pred[:, 0]) ** 2 + (xy[:, 1:2] - pred[:, 1]) ** 2  # (N, M)
        nearest_spot = np.argmin(d2, axis=0)  # per marker
        nearest_marker = np.argmin(d2, axis=1)  # per spot
        m = np.arange(len(pred))
        mutual = (nearest_marker[nearest_spot] == m) & (d2[nearest_spot, m] < g * g)
        ids[nearest_spot[mutual]] = m[mutual]
        return ids

    def refine(
        self, xy: np.ndarray, R_nb: np.ndarray, gates=REFINE_GATES_PX
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Alternate matching and solving with shrinking gates from ``R_nb``."""
        if self.six_dof:
            return self._refine_six_dof(xy, R_nb, gates)
        ids = np.full(len(xy), -1)
        R = R_nb
        for gate in gates:
            ids = self.match(xy, self.project(R), max(gate, self.final_gate_px))
            sel = ids >= 0
            if sel.sum() < 4:
                return ids, None
            sol = solve_markers(xy[sel], ids[sel], self.rig, self.sigma_px, R)
            if sol.status.value not in ("ok", "rejected"):
                return ids, None
            R = sol.R_nb
        ids = self.match(xy, self.project(R), self.final_gate_px)
        return ids, R

    def _refine_six_dof(self, xy, R_nb, gates):
        """Matching for a rig still roughly known: the predicted image is aligned to the
        spots by a 2-D similarity (which absorbs errors of scale, principal point and
        small rotations; Umeyama's least-squares fit), re-matched with shrinking gates,
        and the attitude is then taken from a six-parameter PnP."""
        # the rotation first (the grid start can be tens of pixels off), with the
        # constraint, whose fit stays close although the scale is off
        R = R_nb
        for gate in (gates[0], 30.0):
            ids = self.match(xy, self.project(R), gate)
            sel = ids >= 0
            if sel.sum() < 4:
                return ids, None
            sol = solve_markers(xy[sel], ids[sel], self.rig, self.sigma_px, R)
            if sol.R_nb is None or not np.all(np.isfinite(sol.R_nb)):
                return ids, None
            R = sol.R_nb
        pred = self.project(R)
        A, b = np.eye(2), np.zeros(2)
        for gate in (30.0, 20.0, self.final_gate_px):
            ids = self.match(xy, pred @ A.T + b, gate)
            sel = ids >= 0
            if sel.sum() < 4:
                return ids, None
            A, b = _similarity(pred[ids[sel]], xy[sel])
        ok, rvec, _ = cv2.solvePnP(
            self.X[ids[sel]], xy[sel].astype(np.float64), np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP
        )
        if not ok:
            return ids, None
        return ids, self.rig.R_nc @ cv2.Rodrigues(rvec)[0]

    def reference_yaws(self, xy: np.ndarray) -> np.ndarray | None:
        """Yaws to search when the rig has a reference marker (STASIS Sec. 3.2: the
        reference LED is the spot farthest from the mean of all spots): a window about
        the yaw that puts it there, for each of the three farthest spots (a stray spot
        can be the farthest)."""
        ref = self.rig.target.reference_id
        if ref is None or len(xy) < 4:
            return None
        c = xy.mean(axis=0)
        far = np.argsort(-np.linalg.norm(xy - c, axis=1))[:3]
        zero = self.project(np.eye(3))
        yaw_model = np.arctan2(*(zero[ref] - zero.mean(axis=0))[::-1])
        # the image of a yaw turn turns one way or the other depending on the mount
        sgn = np.sign(np.linalg.det(self.R_cn[:2, :2])) or 1.0
        window = np.radians(np.arange(-20.0, 20.1, GRID_YAW_STEP_DEG))
        return np.concatenate(
            [sgn * (np.arctan2(*(xy[k] - c)[::-1]) - yaw_model) + window for k in far]
        )

    def hypotheses(self, xy: np.ndarray, yaws: np.ndarray | None = None) -> list[np.ndarray]:
        """Best grid attitudes by the count of markers landing near a spot."""
        t = np.radians(self.rig.max_tilt_deg)
        st = np.radians(GRID_TILT_STEP_DEG)
        tilts = np.arange(-np.ceil(t / st), np.ceil(t / st) + 1) * st
        if yaws is None:
            yaws = np.radians(np.arange(-180.0, 180.0, GRID_YAW_STEP_DEG))
        Y, P, Rr = np.meshgrid(yaws, tilts, tilts, indexing="ij")
        Rs = euler_to_matrices(Y.ravel(), P.ravel(), Rr.ravel())
        # each attitude's count of markers within the gate of a spot, a few hundred
        # attitudes at a time (their arrays stay in the cache): every marker in the
        # camera frame, X (R_CN R_NB)^T, as one product (M, 3) x (3, 3 attitudes)
        gate = SpotGate(xy, COARSE_GATE_PX / self.f)
        A = (self.R_cn @ Rs).reshape(-1, 3)  # attitude h's row i is row 3h + i
        M = len(self.X)
        score = np.empty(len(Rs), np.int64)
        step = max(GATE_CHUNK // M, 1)
        for h in range(0, len(Rs), step):
            p = (self.X @ A[3 * h : 3 * (h + step)].T).reshape(M, -1, 3) + self.t_c
            near = gate.near((p[..., :2] / p[..., 2:3]).reshape(-1, 2))
            score[h : h + step] = near.reshape(M, -1).sum(axis=0)
        order = np.argsort(-score)
        picked: list[np.ndarray] = []
        for h in order:
            if len(picked) >= TOP_HYPOTHESES or score[h] < 4:
                break
            if all(_angle(Rs[h], q) > np.radians(8.0) for q in picked):
                picked.append(Rs[h])
        return picked

    def identify(self, xy: np.ndarray, R_last: np.ndarray | None = None) -> Identification:
        """Marker ids of the spots ``xy`` (N, 2), tracking from ``R_last`` if given; a
        spot without a ray (nan: beyond the lens model's field) is no marker."""
        has_ray = np.isfinite(xy).all(axis=1)
        if not has_ray.all():
            found = self.identify(xy[has_ray], R_last)
            ids = np.full(len(xy), -1)
            ids[has_ray] = found.ids
            return replace(found, ids=ids)
        none = np.full(len(xy), -1)
        if len(xy) < 4:
            return Identification(none, None, "too_few_spots")
        if R_last is not None:
            ids, R = self.refine(xy, R_last, gates=(15.0, 5.0))
            if R is not None and (ids >= 0).sum() >= 4:
                return Identification(ids, R)
        results = []
        ref = self.rig.target.reference_id
        ref_yaws = self.reference_yaws(xy)
        for yaws in (ref_yaws, None) if ref_yaws is not None else (None,):
            for R0 in self.hypotheses(xy, yaws):
                ids, R = self.refine(xy, R0)
                if R is not None:
                    results.append((self.faults(ids, R), -int((ids >= 0).sum()), ids, R))
            best = min(results, key=lambda r: r[0]) if results else None
            if best is not None and best[0] == 0 and ref in best[2]:
                # the reference scheme explained every spot and every marker in view,
                # the reference marker among them. Anything less and the whole grid is
                # searched: with stray spots farther out than the reference LED, or
                # markers hidden, its yaw windows can miss the true attitude and hold
                # only the half turn (below), which then looked unique
                # (benchmarks/markers_robustness.py: 47 of 1200 cold frames were ok
                # rows 180 deg off in yaw); with the reference marker out of view the
                # windows mean nothing (a symmetric layout then is ambiguous, and only
                # the whole grid finds both of its explanations)
                break
        if not results:
            return Identification(none, None, "not_identified")
        # the explanation that leaves the fewest spots without a marker and markers in
        # view without a spot (then the most matched)
        results.sort(key=lambda t: (t[0], t[1]))
        faults, _, ids, R = results[0]
        for faults2, _, ids2, _ in results[1:]:
            # another explanation that names some spot differently and leaves at most
            # one fault more is ambiguous. A layout turned half a turn about a
            # symmetric one (tilted the other way) puts every board LED on a spot but
            # leaves the reference LED's spot unexplained and its own reference LED
            # without one: two faults more, told apart (counting matches alone, 20
            # against 21 was refused: 5 % of cold frames within 22 deg, for as long as
            # a platform rests tilted). For the best to be the wrong one, a stray spot
            # would have to sit on that very pixel while the true reference LED is
            # hidden
            both = (ids >= 0) & (ids2 >= 0)
            if faults2 <= faults + 1 and np.any(ids[both] != ids2[both]):
                return Identification(none, None, "ambiguous_layout")
        if (ids >= 0).sum() < 4:
            return Identification(none, None, "not_identified")
        return Identification(ids, R)
