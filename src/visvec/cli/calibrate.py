"""`visvec calibrate zero-tilt`, `readout`, `camera` and `system`."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime
from pathlib import Path

import click
import numpy as np

from visvec.calib.camera import RECIPES, calibrate_camera, camera_section
from visvec.calib.readout import calibrate_readout, readout_sections, readout_trials
from visvec.calib.system import Observations, calibrate_system, initial_attitudes
from visvec.calib.system import calibration_sections as system_sections
from visvec.calib.tomlout import dumps
from visvec.calib.zero_tilt import (
    calibrate_zero_tilt,
    calibration_sections,
    level_detections,
    yaw_reference,
)
from visvec.camera import CameraModel
from visvec.cli.common import FiniteFloat, check_output, load, note_inputs, rig_options, write_whole
from visvec.cli.progress import Work
from visvec.detect.markers import MarkerIdentifier
from visvec.detect.spots import find_spots
from visvec.errors import InputFileError, SourceError
from visvec.sources import open_source
from visvec.sources.folder import IMAGE_SUFFIXES, natural_key


def calibration_out(what: str = ""):
    """The required --out of a calibration command (``what``: the keys it writes)."""
    return click.option(
        "--out",
        required=True,
        type=click.Path(dir_okay=False),
        help=f"Calibration file to write ({what}for later commands' --calibration).",
    )


def _runs_with(calibration: tuple[str, ...], out: str) -> str:
    """The options with which later commands apply a new calibration file ``out``: after
    those it was made on."""
    return " ".join(f"--calibration {c}" for c in (*calibration, out))


def _rig_named(rig_path: str, calibration: tuple[str, ...]) -> str:
    """The rig and the calibration files a new calibration was made on, for its header
    (a run applies them before it, in the same order)."""
    return f"rig {rig_path}" + (f" + calibration {', '.join(calibration)}" if calibration else "")


@click.group()
def calibrate():
    """Calibrate the rig: zero-tilt offsets, rolling-shutter readout, camera intrinsics,
    markers system."""


@calibrate.command("zero-tilt")
@click.argument("frames", nargs=-1, required=True, type=click.Path())
@rig_options
@calibration_out()
@click.option(
    "--yaw-deg",
    "yaws",
    multiple=True,
    metavar="DEG|-",
    help="The platform's known yaw (deg about n3 from n1, toward the triangle's most acute "
    "vertex) in each recording of FRAMES, in their order ('-' where not known): with two "
    "stops or more, the camera's turn about b3 on its mount is calibrated too, which "
    "level frames alone cannot tell from the yaw zero.",
)
@click.option(
    "--yaw-sigma-deg",
    type=FiniteFloat(min=0, min_open=True),
    default=0.05,
    show_default=True,
    help="How well the lab knows each stop's yaw (1-sigma, deg): a mark on the table, an "
    "encoder, a laser on a wall.",
)
def zero_tilt(frames, rig_path, calibration, out, yaws, yaw_sigma_deg):
    """Zero-tilt offsets from FRAMES (folders or videos: one recording, or one per yaw)
    taken with the platform level at several yaws: target offset from the rotation axis
    and camera mounting tilt (for --method full), zero-tilt centroid (for --method
    paper); with --yaw-deg per recording, the camera's turn about b3 (the yaw zero)."""
    rig = load(rig_path, calibration, "triangle", "zero-tilt calibration")
    note_inputs(*frames)
    check_output(out)
    known = _known_yaws(yaws, frames)
    # every source opened first: a missing one is refused before any work
    sources = [open_source(f, fps=rig.fps, retry_s=0.0) for f in frames]
    total = sum(len(s) for s in sources) if all(hasattr(s, "__len__") for s in sources) else None
    with Work("calibrate zero-tilt", total) as bar:
        level = level_detections(frames, sources, rig, lambda msg: click.echo(msg, err=True),
                                 lambda: bar.update(1))  # fmt: skip
    res = calibrate_zero_tilt(level.dets, rig)
    if not all(np.isnan(known)):
        res = yaw_reference(res, known[level.stop], level.stop, yaw_sigma_deg)
    not_level = res.converged and res.sigma_ratio > NOT_LEVEL_RATIO
    if res.converged and not res.camera_off and not not_level:
        # written before the report is printed: a reader that closes the pipe early
        # (`| head`) loses none of it
        n_used = len(level.dets) - int(res.outliers.sum())
        header = (
            f"visvec zero-tilt calibration, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC\n"
            f"{_rig_named(rig_path, calibration)}, frames {' '.join(frames)} ({n_used} used)"
        )
        sections = {**calibration_sections(res, rig), "made_for": made_for(rig)}
        write_whole(out, dumps(sections, header))
    click.echo(
        f"zero-tilt calibration from {len(level.dets) - int(res.outliers.sum())} frames "
        f"({level.bad} skipped, {int(res.outliers.sum())} left out)"
    )
    if not_level:
        click.echo(
            f"visvec: error: these frames do not fit a level platform at rest: the vertices "
            f"scatter {res.sigma_ratio:.0f}x their sigma over the fit (at most "
            f"{NOT_LEVEL_RATIO:g} for a level platform, whatever the camera or target "
            "offset). Level the platform and keep it still in every recording; nothing "
            "written",
            err=True,
        )
        raise SystemExit(1)
    _zero_tilt_report(res, rig, level.names)
    if not res.converged:
        click.echo("visvec: error: the calibration did not converge; nothing written", err=True)
        raise SystemExit(1)
    click.echo(f"wrote {out}; later runs take {_runs_with(calibration, out)}")


def _zero_tilt_report(res, rig, names) -> None:
    """What the zero-tilt calibration found, for the operator."""
    _camera_check(res, rig)
    click.echo(
        f"  target offset from the axis: dx {res.target_offset_mm[0]:+.2f} +- "
        f"{res.sigma_target_offset_mm[0]:.2f} mm, dy {res.target_offset_mm[1]:+.2f} +- "
        f"{res.sigma_target_offset_mm[1]:.2f} mm"
    )
    click.echo(
        f"  target height against the rig file: {res.height_offset_mm:+.2f} +- "
        f"{res.sigma_height_offset_mm:.2f} mm (a ceiling measured wrong; a camera's tone "
        "curve and a print's scale also show here)"
    )
    click.echo(
        f"  camera mounting tilt: about b1 {res.camera_tilt_deg[0]:+.4f} +- "
        f"{res.sigma_camera_tilt_deg[0]:.4f} deg, about b2 {res.camera_tilt_deg[1]:+.4f}"
        f" +- {res.sigma_camera_tilt_deg[1]:.4f} deg"
    )
    _yaw_zero_lines(res)
    click.echo(
        f"  zero-tilt centroid (paper): u {res.centroid_px[0]:.3f} +- "
        f"{res.sigma_centroid_px[0]:.3f} px, v {res.centroid_px[1]:.3f} +- "
        f"{res.sigma_centroid_px[1]:.3f} px"
    )
    click.echo(
        f"  residual: rms {res.rms_px:.4f} px, worst frame {float(np.max(res.residual_px)):.4f} px"
    )
    lo, hi = res.sigma_ratio_95
    verdict = (
        f"wider than the edge-noise model (a lossy codec?): every row's sigma will be "
        f"scaled by {res.sigma_scale:.3f} ([detect] sigma_scale)"
        if res.sigma_scale > 1.0
        else "narrower than it: the sigma is on the safe side (sigma_scale 1)"
        if hi < 1.0
        else "consistent with it (sigma_scale 1)"
    )
    click.echo(
        f"  sigma check: the vertices scatter {res.sigma_ratio:.3f}x their sigma (95 % "
        f"interval {lo:.3f}-{hi:.3f}, {res.dof} degrees of freedom): {verdict}"
    )
    if hi / lo > 1.25:
        click.echo(
            "    (for a tighter check, record a few seconds at each yaw: every frame counts)"
        )
    n_out = int(res.outliers.sum())
    if n_out:
        click.echo(
            f"  {n_out} frame(s) left out, far outside their sigma (marked below: the "
            f"platform nudged, not at rest or not level, or a bad frame?)"
        )
    click.echo("  per frame (yaw found, rms vertex residual):")
    for name, yaw, r, out_ in zip(names, res.yaw_deg, res.residual_px, res.outliers, strict=True):
        flag = "  <- left out" if out_ else ""
        click.echo(f"    {name}: yaw {yaw:+9.3f} deg, {r:.4f} px{flag}")


def _known_yaws(yaws: tuple[str, ...], frames: tuple[str, ...]) -> np.ndarray:
    """--yaw-deg per recording: (len(frames),) deg, nan where '-' or not given."""
    if not yaws:
        return np.full(len(frames), np.nan)
    if len(yaws) != len(frames):
        raise click.BadParameter(
            f"{len(yaws)} values for {len(frames)} recordings: give one per recording, in "
            "their order, '-' where the yaw is not known",
            param_hint="--yaw-deg",
        )
    out = []
    for y in yaws:
        if y.strip() in ("-", ""):
            out.append(np.nan)
            continue
        try:
            v = float(y)
        except ValueError:
            v = np.nan
        if not np.isfinite(v):
            raise click.BadParameter(
                f"{y!r}: expected a yaw in deg, or '-'", param_hint="--yaw-deg"
            )
        out.append(v)
    return np.array(out)


def _yaw_zero_lines(res) -> None:
    if not np.isfinite(res.camera_turn_deg):
        click.echo(
            "  yaw zero: not calibrated. Level frames cannot tell the camera's turn on its "
            "mount from where yaw zero is: every yaw carries that turn, and a tilt of t deg "
            "puts about t x turn (rad) of it into the other tilt axis. Set the platform at "
            "two known yaws or more and give them with --yaw-deg (the lab guide, Yaw zero)"
        )
        return
    text = (
        f"  camera turn about b3 (yaw zero): {res.camera_turn_deg:+.4f} +- "
        f"{res.sigma_camera_turn_deg:.4f} deg from {res.yaw_stops} stop(s) at known yaws"
    )
    if res.yaw_stops < 2:
        text += " (one stop: give two or more, so that a yaw given wrong shows)"
    elif res.yaw_stop_chi2_dof > 3.0:
        text += (
            f"; the stops disagree by {np.sqrt(res.yaw_stop_chi2_dof):.1f}x their sigma: a "
            "yaw given wrong, a stop that moved, or --yaw-sigma-deg too small?"
        )
    click.echo(text)


def made_for(rig) -> dict[str, object]:
    """The camera a calibration was made with ([made_for]: checked when it is applied,
    see rig.load_rig)."""
    c = rig.camera
    return {"width": c.width, "height": c.height, "fx": round(c.fx, 6), "fy": round(c.fy, 6),
            "cx": round(c.cx, 6), "cy": round(c.cy, 6)}  # fmt: skip


# a level, still platform leaves the vertices within a few times their sigma of the fit
# even with a camera model a little off (aspect 0.5 % off: 5.5, module doc of
# calib.zero_tilt); tilted frames leave hundreds
NOT_LEVEL_RATIO = 20.0


def _camera_check(res, rig) -> None:
    """The zero-tilt frames' check of the rig's camera model (aspect fy / fx, principal
    point); when they say it is wrong: what fits, and exit 1 (nothing was written)."""
    cam = rig.camera
    fy = cam.fy * (1.0 + res.aspect)
    (dcx, dcy), (scx, scy) = res.principal_point_px, res.sigma_principal_point_px
    verdict = "off" if res.camera_off else "consistent with the rig file"
    click.echo(
        f"  camera check: aspect fy / fx {fy / cam.fx:.5f} +- "
        f"{cam.fy * res.sigma_aspect / cam.fx:.5f} (rig file {cam.fy / cam.fx:.5f}), principal "
        f"point {dcx:+.2f} +- {scx:.2f}, {dcy:+.2f} +- {scy:.2f} px from the rig file's: {verdict}"
    )
    if res.camera_off:
        click.echo(
            f"visvec: error: the triangle's shape over these yaws says the rig's [camera] "
            f"is wrong: it fits with fy = {fy:.2f}, cx = {cam.cx + dcx:.2f}, cy = "
            f"{cam.cy + dcy:.2f} (fx {cam.fx:.2f}). Calibrate the camera (`visvec "
            f"calibrate camera`) or put these in the rig's [camera], and run this again; "
            f"nothing written",
            err=True,
        )
        raise SystemExit(1)


@calibrate.command("readout")
@click.argument("frames", type=click.Path())
@rig_options
@calibration_out("[camera] readout_ms; ")
@click.option(
    "--max-frames",
    type=click.IntRange(min=10),
    default=300,
    show_default=True,
    help="Frames of FRAMES to use (each trial readout re-runs them all).",
)
@click.option(
    "--principal-point-sigma",
    type=FiniteFloat(min=0, min_open=True),
    default=None,
    help="How well the rig's principal point is known, 1-sigma px (`calibrate camera` "
    "prints it). [default: 0.8 % of the image width]",
)
def readout(frames, rig_path, calibration, out, max_frames, principal_point_sigma):
    """A rolling shutter's readout time ([camera] readout_ms) from FRAMES (a folder with
    its times.csv, from `track --save-frames`, or a video) of the platform turning at
    5-20 deg/s, best swinging out and back: the readout whose correction leaves the
    triangle rigid (least chi-square), the camera's principal point and aspect
    estimated beside it. Give it the zero-tilt calibration (--calibration): a camera
    mounted askew together with a target off the axis, left as the rig file has them,
    can pass for a shear."""
    rig = load(rig_path, calibration, "triangle", "readout calibration")
    note_inputs(frames)
    check_output(out)
    src = open_source(frames, fps=rig.fps, retry_s=0.0, max_frames=max_frames)
    if rig.zero_tilt.centroid_px is None:
        click.echo(
            "visvec: note: no zero-tilt calibration given: a camera askew and a target off "
            "the axis, as the rig file leaves them, can pass for a shear (`visvec calibrate "
            "zero-tilt` first, then its file as --calibration)",
            err=True,
        )
    frames_in = list(src)
    with Work("calibrate readout", readout_trials(rig), unit="trial") as bar:
        res = calibrate_readout(frames_in, rig, principal_point_sigma, progress=bar.update)
    if res.converged:
        sections = readout_sections(res)
        if abs(res.readout_ms) < 2.0 * res.sigma_ms:
            # no rolling shutter seen: a global shutter (the runs' own check of the
            # frames would find one at 5 sigma)
            sections["camera"] = {"readout_ms": 0.0}
        header = (
            f"visvec readout calibration, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC\n"
            f"{_rig_named(rig_path, calibration)}, frames {frames} ({res.n_used} used)"
        )
        sections["made_for"] = made_for(rig)
        write_whole(out, dumps(sections, header))  # before the report
    click.echo(
        f"readout calibration from {res.n_frames} frames (the platform turning at "
        f"{res.rate_dps:.1f} deg/s, median)"
    )
    if not res.converged:
        hint = " (--principal-point-sigma)" if res.poorly_determined else ""
        click.echo(f"visvec: error: {res.reason}{hint}; nothing written", err=True)
        raise SystemExit(1)
    click.echo(
        f"  readout (first to last row): {res.readout_ms:+.2f} +- {res.sigma_ms:.2f} ms"
        + ("  (negative: the last row is read first)" if res.readout_ms < 0 else "")
    )
    click.echo(
        f"    (the camera's principal point and aspect estimated beside it; taking them as "
        f"exact: {res.grid_ms:+.2f} +- {res.grid_sigma_ms:.2f} ms)"
    )
    click.echo(
        f"  chi-square per degree of freedom: {res.chi2_per_dof:.3f} corrected, "
        f"{res.chi2_per_dof_global:.3f} without the correction ({res.n_used} frames)"
    )
    if abs(res.readout_ms) < 2.0 * res.sigma_ms:
        click.echo("  no rolling shutter seen (within 2 sigma of 0): readout_ms = 0 written")
    keys = " and ".join(f"{k} = {v:g}" for k, v in sections["camera"].items())
    click.echo(
        f"wrote {out}: put {keys} in the rig's [camera] section, or give every later "
        f"command {_runs_with(calibration, out)}"
    )


@calibrate.command("camera")
@click.argument("frames", type=click.Path(exists=False))
@click.option("--pattern", required=True, help="Inner corners, COLSxROWS (for example 9x6).")
@click.option(
    "--square-mm",
    required=True,
    type=FiniteFloat(min=0, min_open=True),
    help="Chessboard square size, mm.",
)
@click.option(
    "--recipe",
    type=click.Choice(list(RECIPES)),
    default="precise",
    show_default=True,
    help="Corner detection recipe.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the [camera] section to this file.",
)
def camera(frames, pattern, square_mm, recipe, out):
    """Intrinsics and distortion from chessboard photos (a folder or a glob)."""
    pat = parse_pattern(pattern)
    note_inputs(frames)
    check_output(out)
    p = Path(frames)
    if p.is_dir():
        files = [f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES]
    else:
        files = [f for f in p.parent.glob(p.name) if f.suffix.lower() in IMAGE_SUFFIXES]
    files.sort(key=lambda f: natural_key(f.name))
    if not files:
        raise SourceError(f"{frames}: no images found")
    with Work("calibrate camera", len(files), unit="photo") as bar:
        cal = calibrate_camera(files, pat, square_mm, recipe, progress=bar.update)
    text = dumps(
        {"camera": camera_section(cal)},
        f"visvec camera calibration ({recipe}), pattern {pattern}, "
        f"square {square_mm} mm, rms {cal.rms_px:.4f} px",
    )
    if out:
        write_whole(out, text)  # before the report (see zero-tilt)
    click.echo(
        f"camera calibration from {len(cal.files)} views "
        f"({len(cal.skipped)} without the pattern: {', '.join(cal.skipped) or '-'})"
    )
    intrinsics = cal.K[[0, 1, 0, 1], [0, 1, 2, 2]]
    values = zip(("fx", "fy", "cx", "cy"), intrinsics, cal.sigma_px, strict=True)
    click.echo("  " + "  ".join(f"{k} {v:.3f} +- {s:.3f}" for k, v, s in values) + " px")
    click.echo("  dist " + " ".join(f"{x:+.6f}" for x in cal.dist))
    click.echo(f"  rms reprojection error {cal.rms_px:.4f} px")
    for name, e in zip(cal.files, cal.per_view_px, strict=True):
        flag = "  <- outlier" if name in cal.outliers else ""
        click.echo(f"    {name}: {e:.4f} px{flag}")
    click.echo(_coverage(cal.camera, cal.reach_px))
    if out:
        click.echo(
            f"wrote {out}: its [camera] section into the rig file, or --calibration {out} "
            "first in every later command"
        )
    else:
        click.echo(text)


def _coverage(
    cam: CameraModel,
    reach_px: float,
    seen: str = "the photos' corners",
    advice: str = "Add photos with the chessboard in the corners",
) -> str:
    """How far the calibration's points (``seen``) and the lens model reach, against
    the image's corners; a warning with ``advice`` when the model folds over short of
    them (see CameraModel.field_r2)."""
    corner, fold = cam.corner_radius_px, cam.field_radius_px
    line = (
        f"  {seen} reach {reach_px:.0f} px from the principal point, "
        f"the image's corners {corner:.0f} px"
    )
    if fold >= corner:
        return line + "; the lens model holds to the image's corners"
    return (
        f"{line}\n  warning: the lens model folds over {fold:.0f} px out, short of the "
        f"image's corners: nothing beyond is measured. {advice}"
    )


CAL_GATE_PX = 10.0


@calibrate.command("system")
@click.argument("frames", type=click.Path())
@rig_options
@calibration_out()
@click.option("--max-iterations", type=click.IntRange(min=1), default=30, show_default=True)
def system(frames, rig_path, calibration, out, max_iterations):
    """Self-calibrate a markers rig from FRAMES (a folder or video of the platform moved
    through many attitudes): intrinsics, camera position, pattern poses (STASIS
    Sec. 2.5). Prints a report like the paper's Table 2."""
    rig = load(rig_path, calibration, "markers", "system calibration")
    note_inputs(frames)
    check_output(out)
    # the rig is only roughly known yet: identify with a free translation (which absorbs
    # errors of the camera distance and focal length) and a wide final gate (markers are
    # about 100 px apart, so 10 px cannot confuse two of them)
    ident = MarkerIdentifier(
        rig, rig.detect.centroid_sigma_px, final_gate_px=CAL_GATE_PX, six_dof=True
    )
    d = rig.detect
    fr, mk, uv = [], [], []
    n_used = 0
    seen: dict[bytes, int] = {}  # image digest -> the frame it came first in
    src = open_source(frames, fps=rig.fps, retry_s=0.0)
    bar = Work("calibrate system", len(src) if hasattr(src, "__len__") else None)
    for frame in src:
        bar.update(1)
        if frame.image is None or frame.image.shape != (rig.camera.height, rig.camera.width):
            click.echo(f"frame {frame.index}: skipped (unreadable or wrong size)", err=True)
            continue
        # the same image twice is one measurement, not two: counted twice it would
        # shrink every sigma the calibration reports
        digest = hashlib.sha1(frame.image.tobytes()).digest()
        if digest in seen:
            click.echo(
                f"frame {frame.index}: skipped (the same image as frame {seen[digest]})",
                err=True,
            )
            continue
        seen[digest] = frame.index
        spots = find_spots(frame.image, d.threshold, d.min_spot_px, d.max_spot_px)
        res = ident.identify(
            rig.camera.undistort(spots.centroids_px) if len(spots) else np.zeros((0, 2))
        )
        sel = res.ids >= 0
        if res.R_nb is None or sel.sum() < 6:
            click.echo(f"frame {frame.index}: skipped (markers not identified)", err=True)
            continue
        fr += [n_used] * int(sel.sum())
        mk += res.ids[sel].tolist()
        uv.append(spots.centroids_px[sel])
        n_used += 1
    bar.close()
    if n_used == 0:
        raise InputFileError(f"{frames}: no frame with identified markers")
    fr_a, mk_a, uv_a = np.array(fr), np.array(mk), np.vstack(uv)
    obs = Observations(fr_a, mk_a, uv_a, initial_attitudes(rig, fr_a, mk_a, uv_a))
    res = calibrate_system(rig, obs, max_iterations)
    if res.converged:
        header = (
            f"visvec system calibration, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC\n"
            f"{_rig_named(rig_path, calibration)}, frames {frames} ({n_used} used)\n"
            f"residual std {res.residual_std_px:.4f} px; B's orientation 1-sigma (a bias "
            f"shared by every attitude) about b1, b2, b3: "
            + ", ".join(f"{v:.1f}" for v in res.b_orientation_sigma_arcsec)
            + " arcsec"
        )
        sections = {**system_sections(res), "made_for": made_for(rig)}
        write_whole(out, dumps(sections, header))  # before the report
    click.echo(f"system calibration from {n_used} frames, {len(mk_a)} marker positions")
    for line in res.report():
        click.echo(line)
    if res.converged:
        cam = res.rig.camera
        reach = float(np.hypot(uv_a[:, 0] - cam.cx, uv_a[:, 1] - cam.cy).max())
        tilt = "recordings tilting the platform further, so that the LEDs reach them"
        click.echo(_coverage(cam, reach, "the LEDs seen", f"Calibrate again from {tilt}"))
    if not res.converged:
        click.echo(
            f"visvec: error: the calibration did not converge ({res.message}); "
            f"residual rms {res.rms_px:.3f} px; nothing written",
            err=True,
        )
        raise SystemExit(1)
    click.echo(f"wrote {out}; later runs take {_runs_with(calibration, out)}")


def parse_pattern(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) inner corners."""
    try:
        a, b = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputFileError(
            f"--pattern {text!r}: expected inner corners as COLSxROWS, for example 9x6"
        ) from None
    if a < 3 or b < 3:
        # OpenCV's chessboard finder needs more than 2 inner corners each way
        raise InputFileError(f"--pattern {text!r}: expected at least 3x3 inner corners")
    return a, b
