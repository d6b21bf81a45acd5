"""The triangle's Cramér-Rao bound from the renderer's own intensity derivatives, beside
what visvec measures on the same scenes (issue 31).

For each scene (attitude, blur) the mean image is the renderer's noise-free frame,
``GaussianBlur(render_clean(...))``: what `render_frame` draws its noise around. Its
derivatives by each parameter are central differences of such renders:
- the attitude: yaw, pitch and roll (the Euler angles the rows report), each moved so
  that the triangle's edges move by about DERIV_PX;
- the nuisance of the scene, unknown to any estimator: the board level, the triangle's
  contrast, the lighting gradient (two components) and the blur sigma.
Only the triangle's edges count ("edges only"): the derivatives are those of the image
less the same image rendered without the triangle (the board's own edges and the ceiling
are left out), summed over the pixels within 3 blur widths + 1.75 px of the triangle's
boundary (the reach of visvec's profiles). With Gaussian read noise sigma and 8-bit
rounding (variance sigma^2 + 1/12 per pixel) the Fisher information is
F = J^T J / (sigma^2 + 1/12), J the (pixels, 8) derivatives; the bound on the attitude
is the (3, 3) block of F^-1 (the nuisance marginalised), and without the nuisance the
inverse of F's attitude block. A bound's RMS over the scenes is the square root of the
mean of its variances, compared with the RMS of visvec's errors on noisy frames of the
same scenes (cold, `full`; several noise draws of each scene), with the rig's default
edge lines and with `refine = "pixels"` (visvec.detect.photometric). The derivative step is
checked on the first STEP_CHECK scenes: the bounds with twice the step differ by at most
the reported share.

    python benchmarks/triangle_crb.py [--scenes 30] [--draws 4]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import cv2
import numpy as np

from visvec.bench.triangle import evaluate, random_cases, render_cases, with_refine
from visvec.rig import Rig, load_rig
from visvec.rotations import euler_to_matrix
from visvec.sim.render import render_clean
from visvec.sim.scene import Scene

from _common import CONFIGS, run_record, save_json

DERIV_PX = 0.1  # how far the edges move in an attitude difference step (px)
BLURS_PX = (0.6, 2.0)  # the clean scenes' blur and a defocused lens
AXES = ("yaw", "pitch", "roll")
STEP_CHECK = 6


def mean_image(rig: Rig, euler: np.ndarray, scene: Scene) -> np.ndarray:
    """The renderer's noise-free frame (float): render_frame without noise and rounding
    (tone gamma 1, exposure 1, as Scene's defaults)."""
    img = render_clean(rig, euler_to_matrix(*euler), scene)
    return cv2.GaussianBlur(img, (0, 0), scene.blur_sigma_px) if scene.blur_sigma_px > 0 else img


def _edge_part(rig, euler, scene) -> np.ndarray:
    """The triangle's share of the mean image: with it, less without it."""
    bare = replace(scene, show_triangle=False)
    return mean_image(rig, euler, scene) - mean_image(rig, euler, bare)


def _gradient(scene: Scene, dg: np.ndarray) -> Scene:
    g = scene.gradient_per_m * np.array(scene.gradient_dir) + dg
    n = float(np.hypot(*g))
    return replace(scene, gradient_per_m=n, gradient_dir=tuple(g / max(n, 1e-12)))


def derivatives(rig: Rig, euler: np.ndarray, scene: Scene, steps_px) -> tuple:
    """(pixels, 8) derivative images over the triangle's edge band, one for each
    attitude difference step in ``steps_px`` (px the edges move): yaw, pitch, roll (per
    rad), board level, contrast (per grey level), gradient x, y (per 1/m), blur (per
    px), the nuisance's columns shared; and the band's mask."""
    f = rig.camera.fx
    part = _edge_part(rig, euler, scene)
    inside = (np.abs(part) > 0.05 * scene.contrast).astype(np.uint8)
    w = np.hypot(scene.blur_sigma_px, np.sqrt(1.0 / 12.0))
    reach = int(np.ceil(3.0 * w + 1.75))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    band = (cv2.dilate(inside, k) - cv2.erode(inside, k)) > 0
    nuisance = []
    for name, d in (("board_level", 1.0), ("contrast", 1.0)):
        s1 = replace(scene, **{name: getattr(scene, name) + d})
        s0 = replace(scene, **{name: getattr(scene, name) - d})
        nuisance.append((mean_image(rig, euler, s1) - mean_image(rig, euler, s0)) / (2 * d))
    for i in range(2):
        dg = np.zeros(2)
        dg[i] = 0.01
        nuisance.append((mean_image(rig, euler, _gradient(scene, dg))
                         - mean_image(rig, euler, _gradient(scene, -dg))) / 0.02)  # fmt: skip
    clean = render_clean(rig, euler_to_matrix(*euler), scene)
    b, db = scene.blur_sigma_px, 0.02
    nuisance.append((cv2.GaussianBlur(clean, (0, 0), b + db)
                     - cv2.GaussianBlur(clean, (0, 0), b - db)) / (2 * db))  # fmt: skip
    nuisance = [c[band] for c in nuisance]
    # the triangle's size (px) sets the yaw step: its vertices move r d(yaw)
    ys, xs = np.nonzero(inside)
    r = max(float(np.hypot(xs - xs.mean(), ys - ys.mean()).max()), 10.0)
    out = []
    for step_px in steps_px:
        cols = []
        for i, d in enumerate((step_px / r, step_px / f, step_px / f)):
            e1, e0 = euler.copy(), euler.copy()
            e1[i] += d
            e0[i] -= d
            cols.append(((_edge_part(rig, e1, scene) - _edge_part(rig, e0, scene)) / (2 * d))[band])
        out.append(np.stack(cols + nuisance, axis=1))
    return out, band


def bound(args) -> dict:
    """One scene's bounds (deg^2 variances, per axis), with and without the nuisance, at
    the derivative step and (``check``) at twice it."""
    rig, euler, scene, check = args
    var_n = scene.noise_sigma**2 + 1.0 / 12.0
    tags = ("", "_2x")[: 2 if check else 1]
    Js, band = derivatives(rig, euler, scene, (DERIV_PX, 2 * DERIV_PX)[: len(tags)])
    out = {"pixels": int(band.sum())}
    for tag, J in zip(tags, Js, strict=True):
        F = J.T @ J / var_n
        cov = np.linalg.inv(F)[:3, :3]
        out["crb" + tag] = np.degrees(np.sqrt(np.diag(cov))) ** 2
        out["crb_known" + tag] = np.degrees(np.sqrt(np.diag(np.linalg.inv(F[:3, :3])))) ** 2
    return out


def _axes(v, digits: int = 6) -> dict:
    return dict(zip(AXES, np.round(v, digits).tolist(), strict=True))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=30)
    ap.add_argument("--draws", type=int, default=4, help="noise draws of each scene")
    args = ap.parse_args()
    res = {**run_record(), "deriv_px": DERIV_PX, "scenes": args.scenes, "draws": args.draws}
    for row, cfg in enumerate(("triangle-320.toml", "triangle.toml")):
        rig = load_rig(CONFIGS / cfg)
        name = f"{rig.camera.width}x{rig.camera.height}"
        for blur in BLURS_PX:
            scene = Scene(blur_sigma_px=blur)
            scenes = random_cases(args.scenes, scene, seed=71 + row)
            with ProcessPoolExecutor() as ex:
                bs = list(ex.map(bound, [(rig, c.euler, scene, i < STEP_CHECK)
                                         for i, c in enumerate(scenes)]))  # fmt: skip
            cases = [replace(c, seed=c.seed * 16 + d) for c in scenes for d in range(args.draws)]
            images = render_cases(rig, cases)
            checked = bs[:STEP_CHECK]
            step_share = np.max(np.abs(np.sqrt(np.mean([b["crb_2x"] for b in checked], axis=0)
                                               / np.mean([b["crb"] for b in checked], axis=0))
                                       - 1.0))  # fmt: skip
            entry = {
                "frames": len(cases),
                "step_check_share": round(float(step_share), 4),
                "band_pixels_median": int(np.median([b["pixels"] for b in bs])),
            }
            for refine in ("lines", "pixels"):
                out = evaluate(with_refine(rig, refine), images, cases, "full")
                ok = np.array([s == "ok" for s in out.status])
                # the bound over the same (ok) frames as the errors
                per_frame = [bs[i // args.draws] for i in np.nonzero(ok)[0]]
                crb = {k: np.sqrt(np.mean([b[k] for b in per_frame], axis=0))
                       for k in ("crb", "crb_known")}  # fmt: skip
                rms = out.rms()
                z = np.array(out.err_deg) / np.array(out.sigma_deg)
                entry["crb_deg"] = _axes(crb["crb"])
                entry["crb_nuisance_known_deg"] = _axes(crb["crb_known"])
                entry[refine] = {
                    "ok": int(ok.sum()),
                    "rms_deg": _axes(rms),
                    "ratio_to_crb": _axes(rms / crb["crb"], 3),
                    "error_over_sigma_rms": _axes(np.sqrt(np.mean(z * z, axis=0)), 3),
                    "beyond_3_sigma": int(np.sum(np.abs(z) > 3.0)),
                    "beyond_5_sigma": int(np.sum(np.abs(z) > 5.0)),
                }
            res[f"{name}_blur{blur}"] = entry
            print(name, blur, entry, flush=True)
    save_json("triangle_crb", res)


if __name__ == "__main__":
    main()
