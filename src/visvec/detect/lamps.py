"""Identification of ceiling lamps in a frame: lost-in-space by Delaunay triangles, and
tracking from the last pose.

Lost in space follows the LuVeX paper (Keldysh preprint 2011-24, Sec. 2, Figs. 3-5):
the Delaunay triangles of the lamps in the frame are looked up in the catalogue of the
map's Delaunay triangles by their smallest and largest angle within a tolerance; each
match gives a position, and triangles that agree on one position give the fix.

Beyond the paper:
- the lamps are first put on the ceiling plane in body coordinates through the camera
  model (the table is level and the ceiling height known), so a frame's triangles are
  the map's up to a rotation and a shift: their size is checked as well as their shape,
  and each match gives a full hypothesis (x, y, heading) by a 3-point 2-D Procrustes fit;
- votes count the distinct frame triangles whose hypotheses agree (within 50 mm and
  2 deg); the winner is verified against every detected spot (each must fall near a map
  lamp, one spot per lamp), needs 2 votes and 5 verified lamps, and a second, different
  hypothesis with comparable support makes the frame ambiguous: no fix rather than a
  guess;
- tracking matches spots to the map from the predicted pose and falls back to lost in
  space when too few match.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np

from visvec.lamps import (
    SLIVER_DEG,
    Catalog,
    build_catalog,
    build_neighbour_catalog,
    neighbour_triangles,
    triangle_features,
)
from visvec.rig import Rig

# scipy.spatial is imported where it is used: its import (0.2 s, scipy's start) is then
# not in every command line's start, only in a lamps rig's
if TYPE_CHECKING:
    from scipy.spatial import cKDTree

ANGLE_TOL_DEG = 2.0  # feature lookup tolerance (smallest and largest angle)
SIZE_TOL = 0.05  # relative perimeter tolerance of a matched triangle
CLUSTER_MM = 50.0  # hypotheses this close (and CLUSTER_DEG) agree
CLUSTER_DEG = 2.0
MIN_VOTES = 2  # distinct frame triangles agreeing on the pose
MIN_VERIFIED = 5  # spots explained by the winning pose
# ... and at least this share of the spots: a pose that leaves most spots unexplained
# matched a few stray ones by chance (the lit lamps are always explained: every lamp is
# on the map), as tracking asks of its matches (MIN_TRACKED_FRACTION)
MIN_VERIFIED_SHARE = 0.5
VERIFY_GATE_PX = 6.0  # a spot this close (on the ceiling) to a predicted lamp is that lamp
TRACK_GATE_PX = 15.0
# through the dark (2 to 4 lamps tracked from the predicted pose): no other lamp within
# this many tracking gates of a spot's predicted place (with the lamp within one gate,
# a prediction off by up to a gate cannot swap it for another)
DARK_CLEAR = 2.0
# The place the lamps fit, against every other place they may fit. A pose's chi-square
# against the spots: each identified spot's squared distance from its lamp (after a
# rigid fit of all of them) over the map's and the centroids' variance, and each spot it
# leaves unexplained counted as one at the verify gate. Another pose within RIVAL_CHI2 of
# the best is a rival: the spots fit both, and the frame is ambiguous (on a regular
# grid every shift by a pitch fits as well as the truth, and dark lamps are no evidence
# against it); the candidates put two identified spots far apart on any two lamps as far
# apart, within RIVAL_SIDE_GATES verify gates
RIVAL_CHI2 = 25.0
CENTROID_PX = 0.1  # the centroids' 1-sigma taken with the map's (configs' prior)
RIVAL_SIDE_GATES = 2.0
# dark lamps: each spot's triangles with pairs of its FRAME_NEIGHBOURS nearest spots are
# looked up among each lamp's triangles with pairs of its MAP_NEIGHBOURS nearest lamps
# (a lit lamp's nearest lit neighbours are among its nearest few on the map)
FALLBACK_REASONS = frozenset({"no_catalogue_match", "no_consensus"})
FRAME_NEIGHBOURS = 4
MAP_NEIGHBOURS = 10
# few lamps lit: frames of at most FEW_MAX spots, none of whose Delaunay or neighbour
# triangles found a pose, have every triangle of their spots looked up among every map
# triangle that fits in the view, by its three side lengths within FEW_SIDE_MM
FEW_MAX = 8
FEW_SIDE_MM = 2.0
# a map where more than this share of the triangles in view have a rival gets a warning
# (`visvec check`, `catalog build --rig`): three lamps lit there mostly cannot be told
MAX_RIVAL_SHARE = 0.5


@dataclass(frozen=True)
class TriangleUniqueness:
    """The few-lamps lookup's view of a map (LampIdentifier.uniqueness): how many map
    triangles fit in the view, the share that have a rival (another within the lookup's
    tolerance on every side, or a mirror image), and the smallest separation (mm, the
    largest side difference to the nearest other triangle)."""

    n_triangles: int
    rival_share: float
    smallest_mm: float

    def words(self) -> str:
        return (f"{self.n_triangles} lamp triangles fit in the view; "
                f"{100 * self.rival_share:.1f} % have a rival within {FEW_SIDE_MM:g} mm on "
                f"every side (three lamps lit there are refused as ambiguous: a fourth "
                f"is needed); the closest two differ by {self.smallest_mm:.2f} mm")  # fmt: skip

    @property
    def too_few_unique(self) -> bool:
        return self.rival_share > MAX_RIVAL_SHARE

    def warning(self) -> str:
        """What a map with too few unique triangles means for the lab."""
        return (f"{100 * self.rival_share:.0f} % of the map's triangles in view have a "
                "rival: frames with three lamps lit will mostly be refused; light lamps "
                "that break the pattern")  # fmt: skip


@dataclass(frozen=True)
class Identification:
    """Lamp index of each spot (-1: none), the pose hypothesis (x_mm, y_mm, heading
    rad) or None, its votes (frame triangles agreeing) and why it failed."""

    ids: np.ndarray
    pose: np.ndarray | None
    votes: int = 0
    reason: str = ""

    @property
    def n_identified(self) -> int:
        return int(np.sum(self.ids >= 0))


class LampIdentifier:
    """Identifies spots (undistorted normalised coordinates) as lamps of the rig's map."""

    def __init__(self, rig: Rig, catalog: Catalog | None = None):
        self.rig = rig
        self.lamps = rig.target.lamps.xyz_mm
        self.catalog = catalog if catalog is not None else build_catalog(rig.target.lamps)
        from scipy.spatial import cKDTree

        self.map_tree = cKDTree(self.lamps[:, :2])
        self.z_ceiling = float(np.median(self.lamps[:, 2]))
        depth = self.z_ceiling - float(rig.t_b[2])
        self.mm_per_px = depth / float(rig.camera.fx)
        self.verify_gate_mm = VERIFY_GATE_PX * self.mm_per_px
        cat_pts = self.lamps[self.catalog.triangles, :2]
        self.cat_perimeter = _perimeter(cat_pts)
        # the nearest-neighbour catalogue, built on first need (dark lamps)
        self._neighbours: Catalog | None = None
        self._neighbour_perimeter = np.zeros(0)
        # every map triangle that fits in the view, built on first need (few lamps lit)
        self._few_cat: tuple[np.ndarray, np.ndarray, cKDTree] | None = None
        # every pair of lamps within the view, by distance (lost in space's rival places)
        self._pairs = _lamp_pairs(self.lamps[:, :2], self.map_tree, rig.camera, self.mm_per_px)

    def body_points(self, xy_n: np.ndarray) -> np.ndarray:
        """Spots put on the ceiling plane, in body coordinates (x, y mm; level table)."""
        rays = np.column_stack([xy_n, np.ones(len(xy_n))]) @ self.rig.R_bc.T
        t = self.rig.t_b
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (self.z_ceiling - t[2]) / rays[:, 2]
        s = np.where(rays[:, 2] > 1e-6, s, np.nan)
        return t[:2] + rays[:, :2] * s[:, None]

    def match_to_map(self, pts_b: np.ndarray, pose: np.ndarray, gate_mm: float) -> np.ndarray:
        """Lamp index of each body point at ``pose`` within ``gate_mm`` (-1: none); where
        two points claim one lamp, the nearer keeps it."""
        m = _to_map(pts_b, pose)
        ids = np.full(len(pts_b), -1)
        good = np.all(np.isfinite(m), axis=1)
        if not good.any():
            return ids
        d, j = self.map_tree.query(m[good], distance_upper_bound=gate_mm)
        idx = np.nonzero(good)[0]
        hit = np.isfinite(d)
        ids[idx[hit]] = j[hit]
        dist = np.full(len(pts_b), np.inf)
        dist[idx[hit]] = d[hit]
        for lamp in np.unique(ids[ids >= 0]):
            claim = np.nonzero(ids == lamp)[0]
            if len(claim) > 1:
                ids[claim[claim != claim[np.argmin(dist[claim])]]] = -1
        return ids

    def track(self, xy_n: np.ndarray, pose_pred: np.ndarray, gate_px: float = TRACK_GATE_PX):
        """Spots matched to the map lamps nearest the predicted pose."""
        pts = self.body_points(xy_n)
        ids = self.match_to_map(pts, pose_pred, gate_px * self.mm_per_px)
        return Identification(ids, pose_pred if (ids >= 0).any() else None)

    def track_few(self, xy_n: np.ndarray, pose_pred: np.ndarray,
                  gate_px: float = TRACK_GATE_PX) -> Identification:  # fmt: skip
        """Spots matched from the predicted pose when too few lamps are lit for the
        usual tracking (through the dark): every spot must be a map lamp within
        ``gate_px`` of its prediction, and no other lamp may lie within DARK_CLEAR
        gates of it, so that a prediction off by up to a gate cannot swap lamps."""
        pts = self.body_points(xy_n)
        gate_mm = gate_px * self.mm_per_px
        ids = self.match_to_map(pts, pose_pred, gate_mm)
        if len(ids) == 0 or np.any(ids < 0):
            return Identification(np.full(len(xy_n), -1), None, reason="too_few_lamps")
        d, _ = self.map_tree.query(_to_map(pts, pose_pred), k=2)
        if np.any(d[:, 1] < DARK_CLEAR * gate_mm):
            return Identification(np.full(len(xy_n), -1), None, reason="ambiguous")
        return Identification(ids, pose_pred)

    def lost_in_space(self, xy_n: np.ndarray) -> Identification:
        """The paper's Delaunay-triangle lookup with votes, then verification; when that
        finds no pose (dark lamps: the frame's Delaunay triangles are not the map's), the
        same with every spot's triangles with its nearest spots, looked up among every
        lamp's triangles with its nearest lamps."""
        n = len(xy_n)
        none = np.full(n, -1)
        pts = self.body_points(xy_n)
        fin = np.all(np.isfinite(pts), axis=1)
        if fin.sum() < 3:
            return Identification(none, None, reason="too_few_lamps")
        idx = np.nonzero(fin)[0]
        from scipy.spatial import Delaunay, QhullError

        try:
            tri = idx[Delaunay(pts[fin]).simplices]
        except (QhullError, ValueError):
            collinear = Identification(none, None, reason="lamps_collinear")
            return self._few_or(collinear, pts, idx) if len(idx) <= FEW_MAX else collinear
        first = self._lookup(pts, tri, self.catalog, self.cat_perimeter)
        if first.pose is None and first.reason == "no_triangles" and len(idx) <= FEW_MAX:
            return self._few_or(first, pts, idx)
        if first.pose is not None or first.reason not in FALLBACK_REASONS:
            return first
        if self._neighbours is None:
            self._neighbours = build_neighbour_catalog(self.rig.target.lamps, MAP_NEIGHBOURS)
            self._neighbour_perimeter = _perimeter(self.lamps[self._neighbours.triangles, :2])
        tri_nb = idx[neighbour_triangles(pts[fin], FRAME_NEIGHBOURS)]
        second = self._lookup(pts, tri_nb, self._neighbours, self._neighbour_perimeter)
        if second.pose is not None or not 3 <= len(idx) <= FEW_MAX:
            return second if second.pose is not None else first
        return self._few_or(first, pts, idx)

    def _few_or(self, other: Identification, pts: np.ndarray, idx: np.ndarray):
        """The few-lamps lookup's result, or ``other`` where it finds nothing to say."""
        few = self._few(pts, idx)
        return few if few.pose is not None or few.reason == "ambiguous" else other

    def _few(self, pts: np.ndarray, idx: np.ndarray) -> Identification:
        """Few lamps lit: every triangle of the spots (their side lengths on the ceiling)
        looked up among every map triangle that fits in the view, each match's pose
        verified against every spot. A pose must explain every spot (all but one from
        six on: a stray reflection); poses that explain as many and disagree make the
        frame ambiguous. Three lamps fix a pose when their triangle is unique in the
        map, more leave little doubt (issue 35)."""
        none = np.full(len(pts), -1)
        T, feats, tree = self._all_triangles()
        src_list, dst_list, tri_of = [], [], []
        for k, comb in enumerate(combinations(idx, 3)):
            tri = np.array(comb)
            f, order = _sides(pts[tri][None])
            near = tree.query_ball_point(f[0], FEW_SIDE_MM * np.sqrt(3.0))
            if not near:
                continue
            near = np.array(near)
            near = near[np.all(np.abs(feats[near] - f[0]) <= FEW_SIDE_MM, axis=1)]
            ordered = tri[order[0]]
            for c in near:
                # the canonical order, and with the two closest sides swapped (an
                # isosceles triangle's order is not fixed by its sides)
                for swap in ((0, 1, 2), (1, 0, 2), (0, 2, 1)):
                    src_list.append(pts[ordered[list(swap)]])
                    dst_list.append(self.lamps[T[c], :2])
                    tri_of.append(k)
        if not src_list:
            return Identification(none, None, reason="no_catalogue_match")
        hyp, perr = _procrustes(np.array(src_list), np.array(dst_list))
        good = perr < 2.0 * FEW_SIDE_MM
        if not good.any():
            return Identification(none, None, reason="no_catalogue_match")
        hyp = hyp[good]
        need = len(idx) if len(idx) < 6 else len(idx) - 1
        ver = self._verified_counts(pts[idx], hyp)
        full = ver >= need
        if not full.any():
            return Identification(none, None, reason="no_consensus")
        hyp, ver = hyp[full], ver[full]
        best = int(np.argmax(ver))
        rivals = ~_agrees(hyp, hyp[best]) & (ver >= ver[best] - 1)
        ids = self.match_to_map(pts, hyp[best], self.verify_gate_mm)
        votes = int(np.sum(_agrees(hyp, hyp[best])))
        return self._unique(pts, Identification(ids, hyp[best], votes), hyp[rivals])

    def _near(self, q: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k, n) each: each of the points ``q`` (n, 2; body, mm) at each of the ``poses``
        (k, 3): its distance to the nearest lamp (inf beyond the verify gate) and that
        lamp (len(map) where none); one query for them all."""
        cs, sn = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        mapped = np.stack([poses[:, :1] + cs * q[:, 0] - sn * q[:, 1],
                           poses[:, 1:2] + sn * q[:, 0] + cs * q[:, 1]], axis=2)  # fmt: skip
        dist, j = self.map_tree.query(mapped.reshape(-1, 2),
                                      distance_upper_bound=self.verify_gate_mm)  # fmt: skip
        return dist.reshape(len(poses), len(q)), j.reshape(len(poses), len(q))

    def _verified_counts(self, q: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """(k,): how many of the points ``q`` each pose puts on a lamp, one point per lamp
        (`match_to_map`'s count: the lamps claimed, each once), for all poses at once."""
        _, j = self._near(q, poses)
        j = np.sort(j, axis=1)  # the misses (len(map)) last
        first = j[:, :1] < len(self.lamps)
        new = (np.diff(j, axis=1) != 0) & (j[:, 1:] < len(self.lamps))
        return first[:, 0].astype(int) + new.sum(axis=1)

    def _var(self) -> float:
        """A spot's variance on the ceiling per axis against its lamp (mm^2): the map's
        and the centroid's."""
        return self.rig.target.map_sigma_mm**2 + (CENTROID_PX * self.mm_per_px) ** 2

    def _chi2(self, pts: np.ndarray, pose: np.ndarray) -> tuple[float, np.ndarray, np.ndarray,
                                                                float]:  # fmt: skip
        """A pose's chi-square against the spots (RIVAL_CHI2's comment), the spots' lamp
        indices at it, the pose refitted to them and the identified spots' part of the
        chi-square."""
        ids = self.match_to_map(pts, pose, self.verify_gate_mm)
        m = ids >= 0
        n_fin = int(np.all(np.isfinite(pts), axis=1).sum())
        var = self._var()
        miss = (n_fin - int(m.sum())) * self.verify_gate_mm**2 / var
        if m.sum() < 2:
            return math.inf, ids, pose, math.inf
        src, dst = pts[m][None], self.lamps[ids[m], :2][None]
        fit, _ = _procrustes(src, dst)
        r = _to_map(pts[m], fit[0]) - dst[0]
        fitted = float(np.sum(r * r)) / var
        return fitted + miss, ids, fit[0], fitted

    def _unique(self, pts: np.ndarray, found: Identification,
                others: np.ndarray | None = None) -> Identification:  # fmt: skip
        """``found`` (a pose that explains the spots) kept when no other place fits them
        nearly as well (RIVAL_CHI2's comment): the places the lookup also found
        (``others``, poses (k, 3)) and those that put two identified spots far apart on
        any two lamps as far apart; the better place where one fits clearly better; else
        no fix (ambiguous)."""
        m = found.ids >= 0
        if m.sum() < 3:
            return found
        P = pts[m]
        # two identified spots far apart, and a third far from both
        d = np.linalg.norm(P[:, None] - P[None], axis=2)
        a, b = np.unravel_index(np.argmax(d), d.shape)
        c = int(np.argmax(np.minimum(d[a], d[b])))
        # a rival within RIVAL_CHI2 of the found pose puts each spot within
        # sqrt((its own chi-square + RIVAL_CHI2) var) of a lamp, and so the two spots'
        # distance within twice that of its two lamps' (at most RIVAL_SIDE_GATES gates)
        chi, ids, fit, fitted = self._chi2(pts, found.pose)
        scored = [(fit, chi, ids)]
        reach = math.sqrt((fitted + RIVAL_CHI2) * self._var())
        tol = min(2.0 * reach, RIVAL_SIDE_GATES * self.verify_gate_mm)
        li, lj, dist = self._pairs
        lo, hi = np.searchsorted(dist, [d[a, b] - tol, d[a, b] + tol])
        # each pair of lamps that far apart, both ways round: the pose that puts the two
        # spots on them
        i2 = np.concatenate([li[lo:hi], lj[lo:hi]])
        j2 = np.concatenate([lj[lo:hi], li[lo:hi]])
        vm = self.lamps[j2, :2] - self.lamps[i2, :2]
        vb = P[b] - P[a]
        psi = np.arctan2(vm[:, 1], vm[:, 0]) - math.atan2(vb[1], vb[0])
        cs, sn = np.cos(psi), np.sin(psi)
        pa = np.column_stack([cs * P[a, 0] - sn * P[a, 1], sn * P[a, 0] + cs * P[a, 1]])
        cands = np.column_stack([self.lamps[i2, :2] - pa, psi])
        if others is not None and len(others):
            cands = np.concatenate([others, cands])
        cands = cands[~_agrees(cands, found.pose)] if len(cands) else cands
        if not len(cands):
            return found
        # only those that put as many spots near lamps as the found pose (a spot left
        # unexplained costs a gate's chi-square, RIVAL_CHI2 many times over): tried first
        # on the third spot, then four more of the found pose's spots (a candidate may
        # miss no more of them than the spots the found pose leaves out), where a unique
        # map's candidates already fail, then on every spot
        fin = np.nonzero(np.all(np.isfinite(pts), axis=1))[0]
        ident = np.nonzero(m)[0]
        few = ident[~np.isin(ident, ident[[a, b, c]])][:4]
        slack = len(fin) - len(ident)
        third = ident[[c]]  # the pair's candidates have not placed it yet
        for part, need in ((third, 1 - slack), (few, len(few) - slack), (fin, len(ident))):
            if not len(cands):
                return found
            dist, _ = self._near(pts[part], cands)
            keep = np.isfinite(dist).sum(axis=1) >= need
            cands, dist = cands[keep], dist[keep]
        # one of each place (poses within a cluster's size alike), the likeliest first (the
        # spots' squared distances from their nearest lamps): a rival is then weighed
        # against the best place, not a worse one
        key = np.round(cands / [CLUSTER_MM, CLUSTER_MM, np.radians(CLUSTER_DEG)])
        first = np.unique(key, axis=0, return_index=True)[1]
        cands, dist = cands[first], dist[first]
        rough = np.minimum(dist, self.verify_gate_mm) ** 2
        cands = cands[np.argsort(rough.sum(axis=1), kind="stable")]
        for h in cands:
            chi, ids, fit, _ = self._chi2(pts, h)
            if any(_agrees(fit[None], q)[0] for q, _, _ in scored):
                continue  # the same place again
            scored.append((fit, chi, ids))
            fits = np.array([x[0] for x in scored])
            chis = np.array([x[1] for x in scored])
            best = int(np.argmin(chis))
            if np.any(~_agrees(fits, fits[best]) & (chis <= chis[best] + RIVAL_CHI2)):
                # two places the spots fit alike (one still better found later would
                # only make this a refusal it need not be: never a wrong fix)
                return Identification(np.full(len(pts), -1), None, found.votes, reason="ambiguous")
        best = int(np.argmin([x[1] for x in scored]))
        if best == 0:
            return found
        return Identification(scored[best][2], scored[best][0], found.votes)

    def _all_triangles(self):
        """Every map triangle whose sides all fit in the camera's view on the ceiling:
        lamp indices (T, 3) in the canonical order of :func:`_sides`, their sorted side
        lengths (T, 3) and a k-d tree over them (built on first need)."""
        if self._few_cat is None:
            xy = self.lamps[:, :2]
            cam = self.rig.camera
            reach = float(np.hypot(cam.width, cam.height)) * self.mm_per_px
            from scipy.spatial import cKDTree

            pairs = cKDTree(xy).query_pairs(reach, output_type="ndarray")
            nb: list[set] = [set() for _ in range(len(xy))]
            for i, j in pairs:
                nb[i].add(j)
                nb[j].add(i)
            tris = [(i, j, k) for i, j in pairs for k in nb[i] & nb[j] if k > max(i, j)]
            T = np.array(tris, int).reshape(-1, 3)
            feats, order = _sides(xy[T])
            T = np.take_along_axis(T, order, axis=1)
            self._few_cat = (T, feats, cKDTree(feats))
        return self._few_cat

    def uniqueness(self) -> TriangleUniqueness:
        """How unique the map's triangles are to the few-lamps lookup: among every map
        triangle that fits in the camera's view, the share with another within the
        lookup's FEW_SIDE_MM on every side (a frame whose three lit lamps form one is
        refused as ambiguous, and needs a fourth) and the smallest such separation."""
        _, feats, tree = self._all_triangles()
        if len(feats) < 2:
            return TriangleUniqueness(len(feats), 0.0, math.inf)
        d, _ = tree.query(feats, k=2, p=np.inf)
        sep = d[:, 1]
        return TriangleUniqueness(len(feats), float(np.mean(sep <= FEW_SIDE_MM)),
                                  float(sep.min()))  # fmt: skip

    def _lookup(
        self, pts: np.ndarray, tri: np.ndarray, catalog: Catalog, cat_perimeter: np.ndarray
    ) -> Identification:
        """Frame triangles ``tri`` (T, 3) of spots ``pts`` (body, mm) looked up in
        ``catalog``: hypotheses, votes, verification (see :meth:`lost_in_space`)."""
        none = np.full(len(pts), -1)
        if not len(tri):
            return Identification(none, None, reason="no_triangles")
        order, feats = triangle_features(pts[tri])
        tri = np.take_along_axis(tri, order, axis=1)
        usable = feats[:, 0] >= SLIVER_DEG
        tri, feats = tri[usable], feats[usable]
        if not len(tri):
            return Identification(none, None, reason="no_triangles")
        perim = _perimeter(pts[tri])
        # all frame triangles looked up at once (the k-d tree takes many points)
        near = catalog.tree.query_ball_point(feats, ANGLE_TOL_DEG * np.sqrt(2.0))
        pairs_t = np.repeat(np.arange(len(tri)), [len(c) for c in near])
        pairs_c = np.fromiter((c for cs in near for c in cs), dtype=int, count=len(pairs_t))
        if len(pairs_t):
            close = np.all(np.abs(catalog.features[pairs_c] - feats[pairs_t])
                           <= ANGLE_TOL_DEG, axis=1)  # fmt: skip
            size = np.abs(cat_perimeter[pairs_c] / perim[pairs_t] - 1.0) <= SIZE_TOL
            pairs_t, pairs_c = pairs_t[close & size], pairs_c[close & size]
        if not len(pairs_t):
            return Identification(none, None, reason="no_catalogue_match")
        pt, pc = pairs_t, pairs_c
        src = pts[tri[pt]]  # (m, 3, 2) body
        dst = self.lamps[catalog.triangles[pc], :2]  # (m, 3, 2) map
        hyp, err = _procrustes(src, dst)
        good = err < self.verify_gate_mm
        if not good.any():
            return Identification(none, None, reason="no_catalogue_match")
        hyp, pt = hyp[good], pt[good]
        votes = _votes(hyp, pt)
        best = int(np.argmax(votes))
        if votes[best] < MIN_VOTES:
            return Identification(none, None, votes=int(votes[best]), reason="no_consensus")
        ids = self.match_to_map(pts, hyp[best], self.verify_gate_mm)
        n_ver = int(np.sum(ids >= 0))
        if n_ver < max(MIN_VERIFIED, MIN_VERIFIED_SHARE * np.isfinite(pts).all(axis=1).sum()):
            return Identification(none, None, votes=int(votes[best]), reason="no_consensus")
        # the hypotheses that disagree with the winner with votes enough: each weighed
        # against it by how well the spots fit (_unique)
        rival = ~_agrees(hyp, hyp[best]) & (votes >= MIN_VOTES)
        return self._unique(pts, Identification(ids, hyp[best], int(votes[best])), hyp[rival])


def _lamp_pairs(xy: np.ndarray, tree, camera, mm_per_px: float):
    """Every pair of map lamps ``xy`` closer than the camera's view on the ceiling
    reaches: their indices (two arrays) and distances (mm), by distance."""
    reach = float(np.hypot(camera.width, camera.height)) * mm_per_px
    pairs = tree.query_pairs(reach, output_type="ndarray")
    dist = np.linalg.norm(xy[pairs[:, 0]] - xy[pairs[:, 1]], axis=1)
    order = np.argsort(dist)
    return pairs[order, 0], pairs[order, 1], dist[order]


def _sides(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (m, 3, 2): their side lengths sorted (m, 3), and the vertex order (m,
    3) that puts first the vertex opposite the shortest side, then the next."""
    opp = np.stack(
        [np.linalg.norm(p[:, 1] - p[:, 2], axis=1), np.linalg.norm(p[:, 2] - p[:, 0], axis=1),
         np.linalg.norm(p[:, 0] - p[:, 1], axis=1)], axis=1,
    )  # fmt: skip
    order = np.argsort(opp, axis=1)
    return np.take_along_axis(opp, order, axis=1), order


def _perimeter(p: np.ndarray) -> np.ndarray:
    return (
        np.linalg.norm(p[:, 0] - p[:, 1], axis=1)
        + np.linalg.norm(p[:, 1] - p[:, 2], axis=1)
        + np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    )


def _to_map(pts_b: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * pts_b[:, 0] - s * pts_b[:, 1], pose[1] + s * pts_b[:, 0] + c * pts_b[:, 1]]
    )


def _procrustes(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid 2-D fits map = p + Rz(psi) body of point sets (m, k, 2): poses (m, 3) and
    the largest point residual (m,)."""
    sc = src - src.mean(axis=1, keepdims=True)
    dc = dst - dst.mean(axis=1, keepdims=True)
    cross = np.sum(sc[..., 0] * dc[..., 1] - sc[..., 1] * dc[..., 0], axis=1)
    dot = np.sum(sc[..., 0] * dc[..., 0] + sc[..., 1] * dc[..., 1], axis=1)
    psi = np.arctan2(cross, dot)
    c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
    rx = c * src[..., 0] - s * src[..., 1]
    ry = s * src[..., 0] + c * src[..., 1]
    px = (dst[..., 0] - rx).mean(axis=1)
    py = (dst[..., 1] - ry).mean(axis=1)
    err = np.hypot(rx + px[:, None] - dst[..., 0], ry + py[:, None] - dst[..., 1]).max(axis=1)
    return np.column_stack([px, py, psi]), err


def _agrees(hyp: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Which hypotheses (m, 3) agree with h (3,) or, for h (k, 3), the (k, m) matrix."""
    h = np.atleast_2d(h)
    dpsi = np.abs((hyp[None, :, 2] - h[:, None, 2] + np.pi) % (2 * np.pi) - np.pi)
    d = np.hypot(hyp[None, :, 0] - h[:, None, 0], hyp[None, :, 1] - h[:, None, 1])
    out = (d < CLUSTER_MM) & (dpsi < np.radians(CLUSTER_DEG))
    return out[0] if out.shape[0] == 1 else out


def _votes(hyp: np.ndarray, tri_of: np.ndarray) -> np.ndarray:
    """For each hypothesis, the number of distinct frame triangles agreeing with it."""
    # counts as float32 products (BLAS; numpy's integer products are not): exact
    # for counts this small
    A = np.atleast_2d(_agrees(hyp, hyp)).astype(np.float32)  # (m, m)
    onehot = np.zeros((len(hyp), int(tri_of.max()) + 1), np.float32)
    onehot[np.arange(len(hyp)), tri_of] = 1.0
    return np.count_nonzero(A @ onehot, axis=1)
