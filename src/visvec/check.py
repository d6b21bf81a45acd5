"""What a rig's geometry lets it see, and how well (`visvec check`).

Before a lab spends an afternoon calibrating, it wants to know whether the camera it
mounted keeps the target in view over the platform's attitudes, and what accuracy that
geometry gives. Both come from the rig file alone:

- the envelope (:func:`envelope`): at every yaw and tilt direction, the largest tilt up
  to which the whole target (the triangle's three vertices, or every LED) stays in the
  image, a margin inside its border and inside the lens model's field; and the share of
  attitudes at the rig's ``[platform] max_tilt_deg`` that keep it;
- the accuracy (:func:`simulated_accuracy`): frames rendered by the simulator at random
  attitudes within max_tilt_deg and run through the pipeline, cold (no tracking): ok
  share, RMS error, mean sigma.

A tilt here is the angle between b3 and n3 (what ``impossible_tilt`` bounds): the
attitude Rz(yaw) exp(t [cos d, sin d, 0]) tilts the platform by t about the horizontal
axis at angle d from its own b1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visvec.bench.triangle import Case, Outcome, evaluate
from visvec.detect.markers import VISIBLE_MARGIN_PX
from visvec.distribute import TaskPool
from visvec.rig import Rig
from visvec.rotations import matrix_to_euler
from visvec.sim.markers import SpotScene, render_markers
from visvec.sim.render import render_frame
from visvec.sim.scene import Scene

# how far inside the image border a point must be to count as in view, as the pipelines
# decide it: the triangle detector refuses a vertex within 1 px of the border (rendered
# frames tilting out of view: ok with the nearest vertex 1.0 px in, partly_out_of_view
# from 0.7 px), the markers pipeline expects a spot of an LED VISIBLE_MARGIN_PX in
VIEW_MARGIN_PX = {"triangle": 1.0, "markers": VISIBLE_MARGIN_PX}
# the envelope's grid: yaws and tilt directions every this many degrees, tilts every
# TILT_STEP_DEG up to the larger of TILT_SPAN x max_tilt_deg and MIN_TILT_SPAN_DEG
YAW_STEP_DEG = 5.0
DIRECTION_STEP_DEG = 15.0
TILT_STEP_DEG = 0.25
TILT_SPAN = 3.0
MIN_TILT_SPAN_DEG = 20.0
MAX_TILT_SPAN_DEG = 60.0
ATTITUDE_KINDS = ("triangle", "markers")


def tilted(yaw: np.ndarray, direction: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """(K, 3, 3) R_NB = Rz(yaw) exp(tilt [cos d, sin d, 0]) for K angles (rad) each."""
    yaw, d, t = np.broadcast_arrays(*(np.asarray(a, float) for a in (yaw, direction, tilt)))
    ax, ay = np.cos(d), np.sin(d)
    c, s = np.cos(t), np.sin(t)
    v = 1.0 - c
    # Rodrigues' formula about the horizontal unit axis (ax, ay, 0)
    T = np.empty(t.shape + (3, 3))
    T[..., 0, 0] = c + ax * ax * v
    T[..., 0, 1] = ax * ay * v
    T[..., 0, 2] = ay * s
    T[..., 1, 0] = ax * ay * v
    T[..., 1, 1] = c + ay * ay * v
    T[..., 1, 2] = -ax * s
    T[..., 2, 0] = -ay * s
    T[..., 2, 1] = ax * s
    T[..., 2, 2] = c
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.empty_like(T)
    R[..., 0, :] = cy[..., None] * T[..., 0, :] - sy[..., None] * T[..., 1, :]
    R[..., 1, :] = sy[..., None] * T[..., 0, :] + cy[..., None] * T[..., 1, :]
    R[..., 2, :] = T[..., 2, :]
    return R


def camera_points(rig: Rig, R_nb: np.ndarray) -> np.ndarray:
    """(K, P, 3) the target's points in the camera frame at K attitudes: the triangle's
    vertices for a camera on the platform, the LEDs for a camera fixed in the lab (see
    :mod:`visvec.geometry`)."""
    if rig.kind == "triangle":
        # P_C = R_BC^T (R_NB^T P_N - t_B)
        p_b = np.einsum("pi,kij->kpj", rig.target.vertices_mm, R_nb) - rig.t_b
        return p_b @ rig.R_bc
    if rig.kind == "markers":
        # P_C = R_NC^T (R_NB M_B - t_N)
        p_n = np.einsum("kij,pj->kpi", R_nb, rig.target.points_b) - rig.t_n
        return p_n @ rig.R_nc
    raise ValueError(f"target kind {rig.kind!r}: expected one of {ATTITUDE_KINDS}")


def in_view(rig: Rig, R_nb: np.ndarray, margin: float | None = None) -> np.ndarray:
    """(K, P) bool: each point of the target in the image, ``margin`` px inside its
    border (default: VIEW_MARGIN_PX of the rig's kind) and inside the lens model's field,
    at each of K attitudes."""
    margin = VIEW_MARGIN_PX[rig.kind] if margin is None else margin
    p_c = camera_points(rig, R_nb)
    k, p = p_c.shape[:2]
    uv = rig.camera.project(p_c.reshape(-1, 3))
    ok = np.all(np.isfinite(uv), axis=1) & rig.camera.in_image(uv, margin)
    return ok.reshape(k, p)


@dataclass(frozen=True)
class Envelope:
    """The tilts that keep the target in view (see :func:`envelope`).

    full_tilt_deg : largest tilt up to which the whole target is in view at every yaw
        and direction sampled (nan: not even level at every yaw)
    limit : (yaw, direction) in degrees of the first attitude found to lose it (None if
        none did within ``span_deg``)
    span_deg : largest tilt sampled
    share_at_max : share of (yaw, direction) at the rig's max_tilt_deg with the whole
        target in view
    level_share : the same, level (every yaw)
    fewest_at_max : fewest points in view at any attitude within max_tilt_deg
    n_points : the target's points (3 vertices, or the LEDs)
    """

    full_tilt_deg: float
    limit: tuple[float, float] | None
    span_deg: float
    share_at_max: float
    level_share: float
    fewest_at_max: int
    n_points: int


def envelope(rig: Rig, margin: float | None = None) -> Envelope:
    """The envelope of a triangle or markers rig over a grid of yaws (YAW_STEP_DEG),
    tilt directions (DIRECTION_STEP_DEG) and tilts (TILT_STEP_DEG)."""
    max_tilt = rig.max_tilt_deg
    span = min(max(TILT_SPAN * max_tilt, MIN_TILT_SPAN_DEG), MAX_TILT_SPAN_DEG)
    yaws = np.radians(np.arange(-180.0, 180.0, YAW_STEP_DEG))
    dirs = np.radians(np.arange(0.0, 360.0, DIRECTION_STEP_DEG))
    tilts_deg = np.arange(0.0, span + 0.5 * TILT_STEP_DEG, TILT_STEP_DEG)
    Y, D = np.meshgrid(yaws, dirs, indexing="ij")
    Y, D = Y.ravel(), D.ravel()
    whole = np.empty((len(Y), len(tilts_deg)), dtype=bool)
    count_at_max = np.full(len(Y), np.iinfo(np.int64).max)
    n_points = 0
    for j, t in enumerate(tilts_deg):
        seen = in_view(rig, tilted(Y, D, np.full(len(Y), math.radians(t))), margin)
        n_points = seen.shape[1]
        whole[:, j] = seen.all(axis=1)
        if t <= max_tilt:
            count_at_max = np.minimum(count_at_max, seen.sum(axis=1))
    # per (yaw, direction), the first tilt that loses the target: the envelope ends there
    # (a target hung off the axis can come back into view further out, see share_at_max)
    lost = ~whole
    first = np.where(lost.any(axis=1), lost.argmax(axis=1), len(tilts_deg))
    k = int(first.argmin())
    if first[k] == len(tilts_deg):
        full, limit = float(span), None
    else:
        full = float(tilts_deg[first[k] - 1]) if first[k] > 0 else math.nan
        limit = (float(np.degrees(Y[k])), float(np.degrees(D[k])))
    at_max = whole[:, int(np.searchsorted(tilts_deg, max_tilt, side="right")) - 1]
    return Envelope(
        full_tilt_deg=full,
        limit=limit,
        span_deg=float(span),
        share_at_max=float(at_max.mean()),
        level_share=float(whole[:, 0].mean()),
        fewest_at_max=int(count_at_max.min()),
        n_points=n_points,
    )


def random_attitudes_within(n: int, max_tilt_deg: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3, 3) attitudes with yaw uniform over the circle and the tilt uniform over the
    disc of ``max_tilt_deg`` (direction uniform, tilt max sqrt(u)): every one within the
    platform's range, unlike pitch and roll each drawn within it."""
    yaw = rng.uniform(-np.pi, np.pi, n)
    d = rng.uniform(0.0, 2.0 * np.pi, n)
    t = np.radians(max_tilt_deg) * np.sqrt(rng.uniform(0.0, 1.0, n))
    return tilted(yaw, d, t)


# check's simulated frames go out in tasks of this many (rendered and processed cold)
CHUNK_FRAMES = 10


def _accuracy_task(args) -> Outcome:
    """One task of :func:`simulated_accuracy`: render and process its frames."""
    rig, Rs, cases = args
    if rig.kind == "triangle":
        images = [render_frame(rig, R, c.scene, c.seed) for R, c in zip(Rs, cases, strict=True)]
    else:
        images = [render_markers(rig, R, SpotScene(), c.seed)
                  for R, c in zip(Rs, cases, strict=True)]  # fmt: skip
    return evaluate(rig, images, cases, "full")


def simulated_accuracy(
    rig: Rig, n: int, seed: int = 0, pool: TaskPool | None = None, progress=None
) -> Outcome:
    """Rows of ``n`` frames rendered at random attitudes within max_tilt_deg (the
    simulator's default scene), each processed cold, against their truth. The frames
    go out in tasks of CHUNK_FRAMES to ``pool`` (this process without one), so that the
    outcome is the same wherever they run; ``progress(k)`` after each task (2 per
    frame: rendered and processed)."""
    if rig.kind not in ATTITUDE_KINDS:
        raise ValueError(f"target kind {rig.kind!r}: expected one of {ATTITUDE_KINDS}")
    rng = np.random.default_rng(seed)
    Rs = random_attitudes_within(n, rig.max_tilt_deg, rng)
    euler = [np.array(matrix_to_euler(R)) for R in Rs]
    cases = [Case(e, Scene(), seed * 100003 + k) for k, e in enumerate(euler)]
    tasks = [(rig, Rs[k : k + CHUNK_FRAMES], cases[k : k + CHUNK_FRAMES])
             for k in range(0, n, CHUNK_FRAMES)]  # fmt: skip

    def done(i, _):
        if progress is not None:
            progress(2 * len(tasks[i][2]))

    parts = (pool or TaskPool(workers=1)).map(_accuracy_task, tasks, done)
    out = Outcome()
    for part in parts:
        out.extend(part)
    return out


def field_of_view_deg(rig: Rig) -> tuple[float, float, float] | None:
    """The camera's horizontal, vertical and diagonal field of view (deg), edge to edge
    through the principal point, from the lens model; None where the model's field ends
    inside the image."""
    cam = rig.camera
    w, h = cam.width - 0.5, cam.height - 0.5
    edges = np.array(
        [[-0.5, cam.cy], [w, cam.cy], [cam.cx, -0.5], [cam.cx, h], [-0.5, -0.5], [w, h]]
    )
    xy = cam.undistort(edges)
    if not np.all(np.isfinite(xy)):
        return None
    ang = np.arctan(np.hypot(xy[:, 0], xy[:, 1]))
    return tuple(float(np.degrees(ang[i] + ang[i + 1])) for i in (0, 2, 4))
