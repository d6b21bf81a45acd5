"""Drawings of detections on frames, for a person to look at."""

from __future__ import annotations

import cv2
import numpy as np

from visvec.data import Status
from visvec.output import AttitudeRow, Row

_GREEN, _RED, _BLUE, _YELLOW, _GREY = (
    (60, 200, 60),
    (40, 40, 230),
    (230, 120, 30),
    (0, 220, 230),
    (160, 160, 160),
)


def draw_overlay(
    image: np.ndarray,
    det: object | None,
    row: Row,
    rig: object | None = None,
    scale: int | None = None,
) -> np.ndarray:
    """BGR picture of ``image`` with the detection drawn and the row's numbers.

    Triangle: the region outline, vertices (the acute one red), centroid, lab axes n1
    (toward the acute vertex, red) and n2 (blue). Markers: each spot circled, green with
    its marker id when identified, red when not; brightened so the dark frame shows.
    Lamps: the same, and the map's lamps projected at the fitted pose (blue crosses).
    With a ``rig`` whose lens model folds over inside the image (CameraModel.field_r2):
    the edge of its field, a grey ellipse, beyond which nothing is measured.
    """
    from visvec.pipeline import LampDetection, MarkerDetection, RateDetection

    if isinstance(det, MarkerDetection):
        return _text(_draw_field(_draw_markers(image, det, rig), rig), row)
    if isinstance(det, LampDetection):
        return _text(_draw_field(_draw_lamps(image, det, row, rig), rig), row)
    if isinstance(det, RateDetection):
        return _text(_draw_field(_draw_flow(image, det), rig), row)
    if scale is None:
        scale = max(1, int(round(800 / max(image.shape[1], 1))))
    big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    out = cv2.cvtColor(big, cv2.COLOR_GRAY2BGR)
    sh = 4

    def P(p: np.ndarray) -> tuple[int, int]:
        q = (np.asarray(p) + 0.5) * scale - 0.5
        return int(round(q[0] * (1 << sh))), int(round(q[1] * (1 << sh)))

    if det is not None and len(det.contour_px):
        pts = np.array([P(p) for p in det.contour_px], np.int32)
        cv2.polylines(out, [pts], True, _GREY, 1, cv2.LINE_AA, sh)
    if det is not None and np.all(np.isfinite(det.points_px)):
        v = det.points_px
        color = _GREEN if det.status is Status.OK else _YELLOW
        cv2.polylines(out, [np.array([P(p) for p in v], np.int32)], True, color, 1, cv2.LINE_AA, sh)
        c = v.mean(axis=0)
        cv2.arrowedLine(out, P(c), P(v[0]), _RED, 2, cv2.LINE_AA, sh, 0.08)
        n2 = v[1] - v[2]
        n2 = n2 / max(np.linalg.norm(n2), 1e-9) * np.linalg.norm(v[0] - c) * 0.6
        cv2.arrowedLine(out, P(c), P(c + n2), _BLUE, 2, cv2.LINE_AA, sh, 0.1)
        for k, p in enumerate(v):
            cv2.circle(out, P(p), 6 << sh, _RED if k == 0 else color, 1, cv2.LINE_AA, sh)
        cv2.drawMarker(
            out, tuple(int(x) >> sh for x in P(c)), _YELLOW, cv2.MARKER_CROSS, 14, 1, cv2.LINE_AA
        )
    return _text(_draw_field(out, rig, scale), row)


def _draw_field(out: np.ndarray, rig, scale: int = 1) -> np.ndarray:
    """The edge of the rig's lens-model field where it lies in view (see draw_overlay)."""
    cam = getattr(rig, "camera", None)
    if cam is None or not cam.field_radius_px < cam.corner_radius_px:
        return out
    f, sh = 0.5 * (cam.fx + cam.fy), 4
    centre = ((cam.cx + 0.5) * scale - 0.5, (cam.cy + 0.5) * scale - 0.5)
    axes = (cam.field_radius_px * cam.fx / f * scale, cam.field_radius_px * cam.fy / f * scale)
    cv2.ellipse(
        out,
        tuple(int(round(x * (1 << sh))) for x in centre),
        tuple(int(round(x * (1 << sh))) for x in axes),
        0.0, 0.0, 360.0, _GREY, 1, cv2.LINE_AA, sh,
    )  # fmt: skip
    return out


def _text(out: np.ndarray, row: Row) -> np.ndarray:
    text = [f"frame {row.frame}  {row.status}"]
    if isinstance(row, AttitudeRow) and row.ok:
        y, p, r = row.euler_deg
        sy, sp, sr = row.sigma_deg
        text.append(f"yaw {y:8.3f} +- {sy:.3f}")
        text.append(f"pitch {p:6.3f} +- {sp:.3f}   roll {r:6.3f} +- {sr:.3f}")
    elif row.ok:
        for k, v, s in zip(row.value_columns, row.values(), row.sigmas(), strict=True):
            text.append(f"{k} {v:9.4f} +- {s:.4f}")
    if row.warnings:
        text.append(" ".join(row.warnings))
    # white text on a darkened box: a thick black outline under thin white text does not
    # line up (OpenCV 5 spaces thick glyphs wider), which made the lines unreadable
    # (and the text grows with the image: a 2048 px frame is looked at scaled down)
    k = max(1.0, out.shape[1] / 800.0)
    font, scale, thick, step = cv2.FONT_HERSHEY_SIMPLEX, 0.55 * k, max(1, round(k)), 20 * k
    width = max(cv2.getTextSize(t, font, scale, thick)[0][0] for t in text)
    box = out[: int(12 * k + step * len(text)), : int(16 * k) + width]
    box[:] = box // 3
    for i, t in enumerate(text):
        org = (int(8 * k), int(22 * k + step * i))
        cv2.putText(out, t, org, font, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return out


def _draw_markers(image: np.ndarray, det, rig, size: float = 1.0) -> np.ndarray:
    bright = cv2.convertScaleAbs(image, alpha=4.0)
    out = cv2.cvtColor(bright, cv2.COLOR_GRAY2BGR)
    r = int(round(14 * size))
    for (u, v), k in zip(det.spots.centroids_px, det.ids, strict=True):
        c = (int(round(u)), int(round(v)))
        color = _GREEN if k >= 0 else _RED
        cv2.circle(out, c, r, color, 2 if size >= 1 else 1, cv2.LINE_AA)
        if k >= 0:
            cv2.putText(
                out,
                str(int(k)),
                (c[0] + r + 2, c[1] - r + 4),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.9 * size,
                color,
                2 if size >= 1 else 1,
                cv2.LINE_AA,
            )
    return out


def _draw_lamps(image: np.ndarray, det, row: Row, rig) -> np.ndarray:
    from visvec.estimate.planar import lamps_to_camera

    out = _draw_markers(image, det, rig, size=0.6)
    if row.ok and rig is not None:
        x, y, h = row.values()
        p = lamps_to_camera(rig, np.array([x, y, np.radians(h)]), rig.target.lamps.xyz_mm)
        uv = rig.camera.project(p[p[:, 2] > 0])
        for u, v in uv[rig.camera.in_image(uv)]:
            c = (int(round(u)), int(round(v)))
            cv2.drawMarker(out, c, _BLUE, cv2.MARKER_CROSS, 7, 1, cv2.LINE_AA)
    return out


FLOW_GAIN = 5.0  # arrows are drawn this many times longer than the motion


def _draw_flow(image: np.ndarray, det) -> np.ndarray:
    """Stars circled (yellow), and the motion from the previous frame as arrows, 5x
    magnified: green for stars used, red for outliers."""
    bright = cv2.convertScaleAbs(image, alpha=4.0)
    out = cv2.cvtColor(bright, cv2.COLOR_GRAY2BGR)
    for u, v in det.stars.centroids_px:
        cv2.circle(out, (int(round(u)), int(round(v))), 9, _YELLOW, 1, cv2.LINE_AA)
    m = det.matches
    if m is not None and len(m):
        inl = det.inliers if det.inliers is not None else np.ones(len(m), bool)
        for a, b, ok in zip(m.uv1, m.uv2, inl, strict=True):
            tip = a + FLOW_GAIN * (b - a)
            p0 = (int(round(a[0])), int(round(a[1])))
            p1 = (int(round(tip[0])), int(round(tip[1])))
            cv2.arrowedLine(out, p0, p1, _GREEN if ok else _RED, 2, cv2.LINE_AA, 0, 0.2)
    return out
