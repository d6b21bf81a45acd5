"""The rig file (docs/reference.md, The rig file): one TOML file describing one setup.

:func:`load_rig` validates every key before any frame is read and raises
:class:`~visvec.errors.ConfigError` naming the file, the key and what was expected.
A calibration file has the same sections; the keys it names override the rig's.
"""

from __future__ import annotations

import difflib
import logging
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from visvec.camera import CameraModel
from visvec.errors import ConfigError
from visvec.lamps import LampMap, read_lamp_map
from visvec.tone import check_tone_curve

TARGET_KINDS = ("triangle", "markers", "lamps", "starfield")
REFINE_METHODS = ("lines", "pixels", "corners")

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Mount:
    """Camera pose: on the platform (t_B, R_BC) or in the lab (t_N, R_NC)."""

    on: str
    position_mm: np.ndarray
    rotation: np.ndarray


@dataclass(frozen=True)
class TriangleTarget:
    """A planar triangle on the ceiling; ``vertices_mm`` (3, 3) in N, most acute first.

    ``height_sigma_mm``: 1-sigma uncertainty of the vertices' height z as the file gives
    it (a tape-measured ceiling; it also covers a print's scale and a camera's tone
    curve, which change the triangle's apparent size alike). Each frame's fit then
    estimates the height with this prior (0: the height is taken as exact).
    """

    vertices_mm: np.ndarray
    kind: str = "triangle"
    height_sigma_mm: float = 20.0

    @property
    def centroid_mm(self) -> np.ndarray:
        return self.vertices_mm.mean(axis=0)


@dataclass(frozen=True)
class Pattern:
    """A rigid board of markers: origin ``position_mm`` (3,) and rotation R_B,board (3, 3)
    in B, and the markers' coordinates ``points_mm`` (K, 3) in the board frame."""

    position_mm: np.ndarray
    rotation: np.ndarray
    points_mm: np.ndarray

    @property
    def points_b(self) -> np.ndarray:
        """(K, 3) marker positions in B."""
        return self.points_mm @ self.rotation.T + self.position_mm


@dataclass(frozen=True)
class MarkerTarget:
    """Markers on the platform; ids run 0..M-1 in file order across patterns.

    reference_id : the id of a reference marker set apart from the others (the STASIS
        layout's identification aid), or None.
    placement_sigma_mm : 1-sigma error of each marker's position as the file gives it
        (hand-placed LEDs: a few hundredths of a mm). `calibrate system` estimates every
        marker's own offset with this as its prior; 0 takes the file's positions as exact.
    """

    patterns: tuple[Pattern, ...]
    reference_id: int | None = None
    placement_sigma_mm: float = 0.0
    kind: str = "markers"

    @cached_property
    def points_b(self) -> np.ndarray:
        """(M, 3) all marker positions in B."""
        return np.vstack([p.points_b for p in self.patterns])


@dataclass(frozen=True)
class StarfieldTarget:
    """The sky seen by a camera on the platform; only rates are measured.

    max_rate_dps : the largest angular rate to search for (deg/s); it sets how far a
        star may move between frames.
    """

    max_rate_dps: float = 6.0
    kind: str = "starfield"


@dataclass(frozen=True)
class LampTarget:
    """Lamps on a level ceiling: ``lamps`` (the map, positions in N) read from
    ``map_path``; ``ceiling_z_mm`` is their height above the body origin where the map
    has no z; ``map_sigma_mm`` how well the map's lamp positions are known (1-sigma per
    axis): lost in space tells two places the lamps fit apart by it."""

    lamps: LampMap
    map_path: Path
    ceiling_z_mm: float
    kind: str = "lamps"
    map_sigma_mm: float = 1.0


@dataclass(frozen=True)
class DetectSettings:
    """Detector settings (``[detect]``), all optional.

    brightness_band : (lo, hi) grey levels; outside it a frame gets a brightness warning.
    min_contrast : least grey-level step between board and triangle to accept.
    refine : "lines" (edge-line fits, default), "pixels" (the lines, then the blurred
        edges fitted to every pixel near them: at the Cramér-Rao bound, 1.33x the
        lines' time a frame at 640x480 with the fast extra) or "corners"
        (cv2.cornerSubPix).
    pixel_sigma_floor : px, least per-point noise assumed in the covariance.
    sigma_scale : triangle: factor on the vertices' 1-sigma (1 = the edge-noise model
        alone). `calibrate zero-tilt` measures it from the level frames' scatter and
        writes it when that is significantly wider than the model (compressed video).
    threshold : markers: grey level above which a pixel belongs to a spot (0 = automatic:
        background median + 6 robust sigmas, at least 20).
    centroid_sigma_px : markers and lamps: the prior of the centroid noise learned from
        the fits (visvec.noise); markers: also the identification's gates and the least
        noise a solution is refused by; starfield: the floor of a star's centroid noise.
    min_spot_px, max_spot_px : markers: accepted spot areas (pixels).
    """

    brightness_band: tuple[float, float] = (35.0, 220.0)
    min_contrast: float = 8.0
    refine: str = "lines"
    pixel_sigma_floor: float = 0.02
    sigma_scale: float = 1.0
    threshold: float = 0.0
    centroid_sigma_px: float = 0.1
    min_spot_px: int = 3
    max_spot_px: int = 400


@dataclass(frozen=True)
class ZeroTilt:
    """What `calibrate zero-tilt` found (``[zero_tilt]``): the zero-tilt centroid for the
    "paper" estimator, and how well it found the offsets it wrote into the rig:
    ``offsets_cov`` (4, 4), the covariance of the target's offset on the ceiling (dx,
    dy: mm) and the camera's tilt on its mount (about b1, b2: deg), and
    ``turn_sigma_deg``, the sigma of the camera's turn about b3 (nan: not calibrated).
    Their errors are the same in every row, so each row's sigma carries them
    (`cov_body`)."""

    centroid_px: np.ndarray | None = None
    offsets_cov: np.ndarray | None = None
    turn_sigma_deg: float = float("nan")

    def cov_body(self, R_nb: np.ndarray, target_mm: float, camera_mm: float) -> np.ndarray | None:
        """The calibration's covariance of a row's attitude about the body axes (rad^2)
        at attitude ``R_nb``, the target ``target_mm`` and the camera ``camera_mm``
        above the platform's pivot; None when nothing was calibrated.

        A camera tilted on its mount by (a, b) sees what a platform tilted by (a, b)
        about the camera would show; the triangle's attitude turns about the pivot, where
        the camera's own shift adds to the turn it sees, so it reads k (a, b, 0) about
        the body axes, k = (target_mm - camera_mm) / target_mm. A target shifted by (dx,
        dy) on the ceiling reads as the lab turned by theta = (-dy, dx, 0) / target_mm,
        an attitude error -R_nb^T theta about the body axes. A turn about b3 adds to the
        third. The geometry of calib.zero_tilt._model; checked against the triangle's
        own fit in tests/calib/test_zero_tilt.py."""
        if self.offsets_cov is None:
            return None
        k = (target_mm - camera_mm) / target_mm
        d = math.radians(1.0)
        J = np.zeros((3, 4))
        # columns dx, dy (mm): -R_nb^T theta, theta = (-dy, dx, 0) / target_mm
        J[:, 0] = -R_nb[1, :] / target_mm  # -R_nb^T (0, 1, 0) / target_mm
        J[:, 1] = R_nb[0, :] / target_mm  # -R_nb^T (-1, 0, 0) / target_mm
        J[0, 2] = J[1, 3] = k * d
        cov = J @ self.offsets_cov @ J.T
        if math.isfinite(self.turn_sigma_deg):
            cov[2, 2] += (self.turn_sigma_deg * d) ** 2
        return cov


@dataclass(frozen=True)
class CameraControls:
    """What a USB camera is set to at the start of a run (``[camera]`` keys; None: left
    as the camera has it). ``exposure``, ``gain`` and ``focus`` are in the driver's own
    units (V4L2: exposure in 100 us steps), as OpenCV's CAP_PROP_EXPOSURE, CAP_PROP_GAIN
    and CAP_PROP_FOCUS pass them on."""

    exposure: float | None = None
    gain: float | None = None
    auto_exposure: bool | None = None
    focus: float | None = None
    auto_focus: bool | None = None

    def any(self) -> bool:
        return any(v is not None for v in vars(self).values())


@dataclass(frozen=True)
class ImuSettings:
    """What the IMU's description says (``[imu]``, all optional): the gyro's range
    (deg/s, every axis), from its datasheet. A gyro's range is known, not guessed: without
    it, visvec learns one only from flat tops no gyro that turns can produce
    (visvec.fuse.saturation)."""

    gyro_range_dps: float | None = None


@dataclass(frozen=True)
class Rig:
    """One setup: camera, mount, target and settings (`load_rig` reads one).

    Attributes
    ----------
    camera : CameraModel
        Intrinsics (px) and distortion of the camera, its size (px).
    mount : Mount
        Where the camera sits on the platform and how it looks (mm, deg).
    target : TriangleTarget, MarkerTarget, StarfieldTarget or LampTarget
        The target kind (``kind``) and its geometry (mm).
    max_tilt_deg, max_rate_dps, max_tilt_rate_dps : float
        The platform's tilt (deg) and rates (deg/s) the checks allow.
    fps : float
        The frame rate (Hz) a source without times is timed by.
    readout_ms, readout_sigma_ms : float
        The rolling shutter's readout (ms) and its 1-sigma.
    tone_curve : str or float
        The camera's tone curve: "linear", "srgb" or a gamma (visvec.tone).
    detect, zero_tilt, controls, imu
        The [detect], [zero_tilt], camera controls and [imu] settings."""

    camera: CameraModel
    mount: Mount
    target: TriangleTarget | MarkerTarget | StarfieldTarget | LampTarget
    max_tilt_deg: float = 10.0
    # the platform's fastest yaw turn and tilting (deg/s): the sigma of a rolling-shutter
    # frame whose rate is not known yet covers them
    max_rate_dps: float = 10.0
    max_tilt_rate_dps: float = 2.0
    detect: DetectSettings = field(default_factory=DetectSettings)
    zero_tilt: ZeroTilt = field(default_factory=ZeroTilt)
    device: int | str | None = None
    fps: float = 30.0
    exposure_ms: float | None = None
    # rolling shutter: time from the first row's exposure to the last's (0: global;
    # negative: the last row is read first)
    readout_ms: float = 0.0
    # its 1-sigma (ms), as `calibrate readout` measured it: the rows' sigma carries it
    readout_sigma_ms: float = 0.0
    # the camera's tone curve ("linear", "srgb" or a gamma): the triangle's fits read
    # linear light through it (visvec.tone)
    tone_curve: str | float = "linear"
    controls: CameraControls = field(default_factory=CameraControls)
    imu: ImuSettings = field(default_factory=ImuSettings)
    # whether the rig file (or a calibration) gave [platform] max_tilt_deg, or the default
    max_tilt_given: bool = True
    path: Path | None = None

    @property
    def kind(self) -> str:
        return self.target.kind

    @property
    def t_b(self) -> np.ndarray:
        """(3,) camera optical centre in B, mm (camera on the platform)."""
        return self.mount.position_mm

    @property
    def R_bc(self) -> np.ndarray:
        """(3, 3) camera-to-body rotation (camera on the platform)."""
        return self.mount.rotation

    @property
    def t_n(self) -> np.ndarray:
        """(3,) camera optical centre in N, mm (camera fixed in the lab)."""
        return self.mount.position_mm

    @property
    def R_nc(self) -> np.ndarray:
        """(3, 3) camera-to-lab rotation (camera fixed in the lab)."""
        return self.mount.rotation


# --------------------------------------------------------------------------- parsing


class _Section:
    """Typed access to one TOML table that remembers which keys were read."""

    def __init__(
        self,
        path: str,
        name: str,
        table: Mapping[str, Any],
        origin: Mapping[str, str] | None = None,
    ):
        # origin: the file each key came from, when calibration files override the rig
        self.path, self.name, self.table = path, name, table
        self.origin = origin or {}
        self.used: set[str] = set()

    def _where(self, key: str) -> str:
        return f"{self.origin.get(key, self.path)}: [{self.name}] {key}"

    def has(self, key: str) -> bool:
        return key in self.table

    def get(self, key: str, default: Any = None, *, required: bool = False) -> Any:
        self.used.add(key)
        if key not in self.table:
            if required:
                # a misspelt key (fxx for fx) is named, not only the one that is missing
                # (a key that holds it or that it holds: fxx, f_x; not fy, a key of its own)
                cands = [str(k) for k in self.table if key in str(k) or str(k) in key
                         or str(k).replace("_", "") == key.replace("_", "")]  # fmt: skip
                near = difflib.get_close_matches(key, cands, 1, 0.6)
                hint = f"; the file has {near[0]!r}: misspelt?" if near else ""
                raise ConfigError(f"{self._where(key)}: missing (required){hint}")
            return default
        return self.table[key]

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        required: bool = False,
        positive: bool = False,
        lo: float | None = None,
        hi: float | None = None,
    ) -> float | None:
        v = self.get(key, default, required=required)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{self._where(key)} = {v!r}: expected a finite number")
        if positive and v <= 0:
            raise ConfigError(f"{self._where(key)} = {v!r}: expected a number > 0")
        if lo is not None and v < lo or hi is not None and v > hi:
            raise ConfigError(f"{self._where(key)} = {v!r}: expected a number in [{lo}, {hi}]")
        return float(v)

    def array(
        self, key: str, shape: tuple[int, ...], default: Any = None, *, required: bool = False
    ) -> np.ndarray | None:
        v = self.get(key, default, required=required)
        if v is None:
            return None
        try:
            a = np.array(v, dtype=float)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != shape or not np.all(np.isfinite(a)):
            want = " x ".join(str(n) for n in shape)
            raise ConfigError(
                f"{self._where(key)} = {v!r}: expected {want} finite numbers"
                + (" (rows of the matrix)" if len(shape) == 2 else "")
            )
        return a

    def choice(
        self,
        key: str,
        options: tuple[str, ...],
        default: str | None = None,
        *,
        required: bool = False,
    ) -> str | None:
        v = self.get(key, default, required=required)
        if v is None:
            return None
        if v not in options:
            raise ConfigError(f"{self._where(key)} = {v!r}: expected one of {list(options)}")
        return v

    def flag(self, key: str, default: bool | None = None) -> bool | None:
        v = self.get(key, default)
        if v is None:
            return None
        if not isinstance(v, bool):
            raise ConfigError(f"{self._where(key)} = {v!r}: expected true or false")
        return v

    def check_unknown(self) -> None:
        extra = sorted(set(self.table) - self.used)
        if extra:
            files = sorted({self.origin.get(k, self.path) for k in extra})
            raise ConfigError(
                f"{', '.join(files)}: [{self.name}] unknown key(s) {extra}; "
                f"known: {sorted(self.used)}"
            )


def _read_toml(path: Path, what: str) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_RIG_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, expected a {what} file (TOML)") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what} file ({exc.strerror})") from None
    if len(data) > MAX_RIG_FILE_BYTES:
        raise ConfigError(f"{path}: over {MAX_RIG_FILE_BYTES >> 20} MiB: not a {what} file")
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not a UTF-8 text file (byte {exc.start}): expected a {what} file (TOML)"
        ) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to be a {what} file") from None


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for name, table in over.items():
        if isinstance(table, dict) and isinstance(out.get(name), dict):
            out[name].update(table)
        else:
            out[name] = table
    return out


def _rotation(sec: _Section, key: str) -> np.ndarray:
    R = sec.array(key, (3, 3), required=True)
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(R) < 0:
        raise ConfigError(
            f"{sec._where(key)}: expected a proper rotation matrix (orthonormal rows, "
            f"det +1); got |R R^T - I| = {err:.2g}, det = {np.linalg.det(R):.3f}"
        )
    # Re-orthonormalise the few-digit matrices people type (nearest rotation, SVD).
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


_SECTIONS = (
    "camera",
    "mount",
    "target",
    "platform",
    "detect",
    "zero_tilt",
    "source",
    "report",
    "imu",
)
MADE_FOR_F_TOL = 0.02  # a calibration's camera: focal lengths within 2 % ...
MADE_FOR_C_TOL = 0.02  # ... and the principal point within 2 % of the width


def _check_made_for(made: Any, raw: Mapping[str, Any], cal_path: Path) -> None:
    """Refuse a calibration made with another camera than the one it is applied to
    (the rig's [camera] with the calibrations before it): its offsets are then wrong
    by more than their sigma."""
    if not isinstance(made, dict):
        raise ConfigError(f"{cal_path}: [made_for] must be a table")
    cam = raw.get("camera", {}) if isinstance(raw.get("camera"), dict) else {}
    for k in ("width", "height"):
        if k in made and k in cam and made[k] != cam[k]:
            raise ConfigError(
                f"{cal_path}: made for a {made.get('width')}x{made.get('height')} image; the "
                f"rig's camera is {cam.get('width')}x{cam.get('height')}: calibrate again at "
                "this size"
            )
    width = float(cam.get("width", 1) or 1)
    for k, tol in (("fx", MADE_FOR_F_TOL), ("fy", MADE_FOR_F_TOL), ("cx", MADE_FOR_C_TOL),
                   ("cy", MADE_FOR_C_TOL)):  # fmt: skip
        a, b = made.get(k), cam.get(k)
        if not isinstance(a, int | float) or not isinstance(b, int | float):
            continue
        off = abs(a - b) / (abs(b) if k in ("fx", "fy") else width)
        if off > tol:
            raise ConfigError(
                f"{cal_path}: made with [camera] {k} = {a}; the rig's is {b}: a calibration "
                "made with another camera model is wrong for this one; calibrate again with "
                "the camera as it is now"
            )


def load_rig(path: str | Path, calibration: str | Path | Sequence[str | Path] | None = None) -> Rig:
    """Read and validate a rig file, optionally overridden by calibration files: one, or
    several applied in order (each overrides the keys it names, so a later file wins:
    camera, then zero-tilt, then readout).

    Parameters
    ----------
    path : str or Path
        The rig file (TOML; configs/ has one per target kind; docs/reference.md lists
        its keys and units: mm and degrees).
    calibration : str or Path or sequence of them, optional
        Calibration files (`visvec calibrate ...` writes them), applied in order.

    Returns
    -------
    Rig
        The validated setup: camera, mount, target, settings.

    Raises
    ------
    ConfigError
        On any missing or wrong key; the message names file, key and expectation.
    """
    path = Path(path)
    raw = _read_toml(path, "rig")
    if calibration is None:
        calibration = ()
    elif isinstance(calibration, str | Path):
        calibration = (calibration,)
    # the file each key comes from, named in the errors: the last that sets it
    origins = {k: dict.fromkeys(t, str(path)) for k, t in raw.items() if isinstance(t, dict)}
    for cal_path in calibration:
        cal = _read_toml(Path(cal_path), "calibration")
        bad = sorted(set(cal) - set(_SECTIONS) - {"made_for"})
        if bad:
            raise ConfigError(f"{cal_path}: unknown section(s) {bad}")
        made = cal.pop("made_for", None)
        if made is not None:
            _check_made_for(made, raw, Path(cal_path))
        raw = _merge(raw, cal)
        for name, table in cal.items():
            if isinstance(table, dict):
                origins.setdefault(name, {}).update(dict.fromkeys(table, str(cal_path)))
    src = f"{path} (+ {', '.join(map(str, calibration))})" if calibration else str(path)
    return rig_from_dict(raw, src, base_dir=path.parent, origins=origins)


def rig_from_dict(
    raw: Mapping[str, Any],
    src: str = "<rig>",
    base_dir: Path | None = None,
    origins: Mapping[str, Mapping[str, str]] | None = None,
) -> Rig:
    """Build a :class:`Rig` from parsed TOML (see :func:`load_rig`); ``origins``: per
    section, the file each key came from (for the errors)."""
    origins = origins or {}
    unknown = sorted(set(raw) - set(_SECTIONS))
    if unknown:
        raise ConfigError(f"{src}: unknown section(s) {unknown}; expected {list(_SECTIONS[:5])}")
    for name in ("camera", "mount", "target"):
        if name not in raw:
            raise ConfigError(f"{src}: [{name}] section missing (required)")
        if not isinstance(raw[name], dict):
            raise ConfigError(f"{src}: {name} must be a [table]")

    def section(name: str) -> _Section:
        return _Section(src, name, raw.get(name, {}), origins.get(name, {}))

    fields = _camera_fields(section("camera"), src)
    mount = _mount(section("mount"))
    tgt = section("target")
    kind = tgt.choice("kind", TARGET_KINDS, required=True)
    if kind == "triangle":
        target = _triangle_target(tgt, mount, src)
    elif kind == "starfield":
        target = _starfield_target(tgt, mount, src)
    elif kind == "lamps":
        target = _lamp_target(tgt, mount, src, base_dir)
    else:
        target = _marker_target(tgt, mount, src)
    fields |= _platform_fields(section("platform"))
    imu = section("imu")
    fields["imu"] = ImuSettings(imu.number("gyro_range_dps", None, positive=True))
    imu.check_unknown()
    rig = Rig(
        mount=mount,
        target=target,
        detect=_detect_settings(section("detect"), src),
        zero_tilt=_zero_tilt(section("zero_tilt")),
        path=Path(src.split(" (+")[0]) if base_dir is not None else None,
        **fields,
    )
    _check_visible(rig, src)
    return rig


def _camera_fields(cam: _Section, src: str) -> dict[str, Any]:
    """The [camera] section's Rig fields: the lens model, the device and its timing
    (fps, exposure, rolling-shutter readout) and the controls visvec sets on it."""
    width = cam.number("width", required=True, positive=True)
    height = cam.number("height", required=True, positive=True)
    for k, v in (("width", width), ("height", height)):
        if v != int(v) or v > MAX_IMAGE_SIDE_PX:
            raise ConfigError(
                f"{src}: [camera] {k} = {v}: expected a whole number of pixels up to "
                f"{MAX_IMAGE_SIDE_PX}"
            )
    camera = CameraModel(
        width=int(width),
        height=int(height),
        fx=cam.number("fx", required=True, positive=True),
        fy=cam.number("fy", required=True, positive=True),
        cx=cam.number("cx", required=True),
        cy=cam.number("cy", required=True),
        dist=cam.array("dist", (5,), default=[0.0] * 5),
    )
    device = cam.get("device")
    if device is not None and not isinstance(device, int | str):
        raise ConfigError(f"{src}: [camera] device = {device!r}: expected an index or a path/URL")
    fps = cam.number("fps", 30.0, positive=True)
    exposure_ms = cam.number("exposure_ms", None, positive=True)
    if exposure_ms is not None and exposure_ms > 1000.0 / fps:
        raise ConfigError(
            f"{src}: [camera] exposure_ms = {exposure_ms}: longer than one frame "
            f"({1000.0 / fps:.1f} ms at fps = {fps})"
        )
    readout_ms = cam.number("readout_ms", 0.0, lo=-1000.0 / fps, hi=1000.0 / fps)
    readout_sigma_ms = cam.number("readout_sigma_ms", 0.0, lo=0.0, hi=1000.0 / fps)
    if readout_sigma_ms > 0 and readout_ms == 0:
        raise ConfigError(
            f"{cam._where('readout_sigma_ms')} = {readout_sigma_ms}: needs a readout_ms "
            "(0 declares a global shutter, whose readout has no uncertainty)"
        )
    try:
        tone_curve = check_tone_curve(cam.get("tone_curve", "linear"), cam._where("tone_curve"))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    controls = _camera_controls(cam)
    cam.check_unknown()
    _check_intrinsics(camera, cam)
    return {"camera": camera, "device": device, "fps": fps, "exposure_ms": exposure_ms,
            "readout_ms": readout_ms, "readout_sigma_ms": readout_sigma_ms,
            "tone_curve": tone_curve, "controls": controls}  # fmt: skip


def _camera_controls(cam: _Section) -> CameraControls:
    """The exposure, gain and focus the rig asks the camera to keep."""
    controls = CameraControls(
        exposure=cam.number("exposure", None, lo=0.0),
        gain=cam.number("gain", None, lo=0.0),
        auto_exposure=cam.flag("auto_exposure"),
        focus=cam.number("focus", None, lo=0.0),
        auto_focus=cam.flag("auto_focus"),
    )
    if controls.exposure is not None and controls.auto_exposure:
        raise ConfigError(
            f"{cam._where('exposure')} = {controls.exposure:g} with auto_exposure = true: the "
            "camera would not keep it; set auto_exposure = false (or drop exposure)"
        )
    if controls.focus is not None and controls.auto_focus:
        raise ConfigError(
            f"{cam._where('focus')} = {controls.focus:g} with auto_focus = true: the camera "
            "would not keep it; set auto_focus = false (or drop focus)"
        )
    return controls


def _check_intrinsics(camera: CameraModel, cam: _Section) -> None:
    """Refuse a focal length, principal point or distortion no lens has."""
    for k, v, lo, hi in (("fx", camera.fx, 0.0, 100.0 * camera.width),
                         ("fy", camera.fy, 0.0, 100.0 * camera.height),
                         ("cx", camera.cx, 0.0, camera.width),
                         ("cy", camera.cy, 0.0, camera.height)):  # fmt: skip
        if not lo <= v <= hi:
            raise ConfigError(
                f"{cam._where(k)} = {v}: expected {lo:g} to {hi:g} px for a "
                f"{camera.width}x{camera.height} image (the principal point lies in the "
                "image; a focal length beyond 100 image widths is no lens)"
            )
    if np.any(np.abs(camera.dist) > MAX_DISTORTION):
        raise ConfigError(
            f"{cam._where('dist')} = {[float(x) for x in camera.dist]}: expected "
            f"coefficients within +-{MAX_DISTORTION:g} (k1 k2 p1 p2 k3, as `visvec "
            "calibrate camera` writes them)"
        )
    _check_lens(camera, cam._where("dist"))


def _mount(mnt: _Section) -> Mount:
    mount = Mount(
        on=mnt.choice("on", ("platform", "lab"), required=True),
        position_mm=mnt.array("position_mm", (3,), required=True),
        rotation=_rotation(mnt, "rotation"),
    )
    mnt.check_unknown()
    return mount


def _platform_fields(plat: _Section) -> dict[str, Any]:
    """The [platform] section's Rig fields: the tilt and rates the platform reaches."""
    fields = {
        "max_tilt_given": plat.has("max_tilt_deg"),
        "max_tilt_deg": plat.number("max_tilt_deg", 10.0, positive=True, hi=60.0),
        "max_rate_dps": plat.number("max_rate_dps", 10.0, positive=True, hi=360.0),
        "max_tilt_rate_dps": plat.number("max_tilt_rate_dps", 2.0, positive=True, hi=360.0),
    }
    plat.check_unknown()
    return fields


def _detect_settings(det: _Section, src: str) -> DetectSettings:
    band = det.array("brightness_band", (2,), default=[35.0, 220.0])
    if not 0 <= band[0] < band[1] <= 255:
        raise ConfigError(
            f"{src}: [detect] brightness_band = {band.tolist()}: expected "
            "[lo, hi] with 0 <= lo < hi <= 255"
        )
    detect = DetectSettings(
        brightness_band=(float(band[0]), float(band[1])),
        min_contrast=det.number("min_contrast", 8.0, positive=True),
        refine=det.choice("refine", REFINE_METHODS, "lines"),
        pixel_sigma_floor=det.number("pixel_sigma_floor", 0.02, lo=0.0, hi=5.0),
        sigma_scale=det.number("sigma_scale", 1.0, positive=True, hi=10.0),
        threshold=det.number("threshold", 0.0, lo=0.0, hi=65535.0),
        centroid_sigma_px=det.number("centroid_sigma_px", 0.1, positive=True, hi=10.0),
        min_spot_px=int(det.number("min_spot_px", 3, positive=True)),
        max_spot_px=int(det.number("max_spot_px", 400, positive=True)),
    )
    det.check_unknown()
    return detect


def _zero_tilt(zt: _Section) -> ZeroTilt:
    cov = zt.array("offsets_cov", (4, 4))
    if cov is not None and (not np.allclose(cov, cov.T) or np.linalg.eigvalsh(cov).min() < 0):
        raise ConfigError(
            f"{zt._where('offsets_cov')}: expected a covariance (symmetric, positive "
            "semi-definite), as `calibrate zero-tilt` writes it"
        )
    turn = zt.number("turn_sigma_deg", None, lo=0.0)
    zero = ZeroTilt(centroid_px=zt.array("centroid_px", (2,)), offsets_cov=cov,
                    turn_sigma_deg=math.nan if turn is None else turn)  # fmt: skip
    zt.get("residual_px")  # written by `calibrate zero-tilt`, for the reader
    zt.check_unknown()
    return zero


APEX_MARGIN_DEG = 10.0
MAX_IMAGE_SIDE_PX = 20000
MAX_DISTORTION = 50.0  # |k1|, |k2|, |p1|, |p2|, |k3| of any lens this model fits
MAX_RIG_FILE_BYTES = 1 << 20


def _check_triangle(v: np.ndarray, src: str) -> None:
    """Refuse a triangle that is degenerate, not level, or whose first vertex is not the
    most acute."""
    e = [np.linalg.norm(v[(i + 1) % 3] - v[(i + 2) % 3]) for i in range(3)]
    area = 0.5 * np.linalg.norm(np.cross(v[1] - v[0], v[2] - v[0]))
    if area < 1e-3 * max(e) ** 2:
        raise ConfigError(
            f"{src}: [target] vertices_mm: the three vertices are (nearly) "
            "collinear; expected a triangle"
        )
    if np.ptp(v[:, 2]) > 1e-6 * max(e) + 1e-9 and np.ptp(v[:, 2]) > 1.0:
        raise ConfigError(
            f"{src}: [target] vertices_mm: the vertices must lie on a level "
            f"ceiling (equal z); z spans {np.ptp(v[:, 2]):.1f} mm"
        )
    if v[0, 2] <= 0:
        raise ConfigError(
            f"{src}: [target] vertices_mm: z = {v[0, 2]} mm; expected the "
            "target above the centre of rotation (z > 0)"
        )
    # the side opposite the most acute vertex is the shortest
    if not (e[0] < e[1] and e[0] < e[2]):
        raise ConfigError(
            f"{src}: [target] vertices_mm: the first vertex must be the most acute one "
            f"(opposite the shortest side); side lengths are {[round(x, 1) for x in e]} mm"
        )
    # ... and clearly so: the detector tells the vertices apart by their angles, which
    # perspective and noise move by a few degrees (an equilateral target gives any of
    # three attitudes 120 deg apart)
    a, b, c = e
    ang = np.degrees(
        np.arccos(
            np.clip(
                [(b * b + c * c - a * a) / (2 * b * c), (a * a + c * c - b * b) / (2 * a * c)],
                -1,
                1,
            )
        )
    )
    angles = [float(ang[0]), float(ang[1]), 180.0 - float(ang[0] + ang[1])]
    if min(angles[1:]) - angles[0] < APEX_MARGIN_DEG:
        raise ConfigError(
            f"{src}: [target] vertices_mm: the angles are "
            f"{[round(x, 1) for x in angles]} deg; the first (acute) vertex's angle must be "
            f"at least {APEX_MARGIN_DEG:g} deg smaller than the other two, so that the "
            "camera can tell it apart (an acute isosceles triangle, such as 38/71/71)"
        )


def _triangle_target(tgt: _Section, mount: Mount, src: str) -> TriangleTarget:
    if mount.on != "platform":
        raise ConfigError(
            f"{src}: [mount] on = {mount.on!r}: a triangle target needs the camera "
            'on the platform (on = "platform")'
        )
    verts = tgt.array("vertices_mm", (3, 3), required=True)
    height_sigma = tgt.number("height_sigma_mm", 20.0, lo=0.0, hi=500.0)
    tgt.check_unknown()
    _check_triangle(verts, src)
    return TriangleTarget(vertices_mm=verts, height_sigma_mm=height_sigma)


def _lamp_target(tgt: _Section, mount: Mount, src: str, base_dir: Path | None) -> LampTarget:
    if mount.on != "platform":
        raise ConfigError(
            f"{src}: [mount] on = {mount.on!r}: a lamps camera rides on the mock-up "
            '(on = "platform")'
        )
    name = tgt.get("map", required=True)
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{src}: [target] map = {name!r}: expected the lamp map's CSV path")
    ceiling = tgt.number("ceiling_z_mm", required=True, positive=True)
    map_sigma = tgt.number("map_sigma_mm", 1.0, positive=True, hi=100.0)
    tgt.check_unknown()
    path = Path(name)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    try:
        lamps = read_lamp_map(path, ceiling)
    except ConfigError as exc:
        raise ConfigError(f"{src}: [target] map: {exc}") from None
    return LampTarget(lamps, path, ceiling, map_sigma_mm=map_sigma)


def _starfield_target(tgt: _Section, mount: Mount, src: str) -> StarfieldTarget:
    if mount.on != "platform":
        raise ConfigError(
            f"{src}: [mount] on = {mount.on!r}: a starfield camera rides on the platform "
            '(on = "platform")'
        )
    rate = tgt.number("max_rate_dps", 6.0, positive=True, hi=180.0)
    tgt.check_unknown()
    return StarfieldTarget(max_rate_dps=rate)


def _marker_target(tgt: _Section, mount: Mount, src: str) -> MarkerTarget:
    if mount.on != "lab":
        raise ConfigError(
            f"{src}: [mount] on = {mount.on!r}: a markers target needs the camera fixed "
            'in the lab (on = "lab")'
        )
    pats = tgt.get("patterns", required=True)
    if not isinstance(pats, list) or not pats or not all(isinstance(p, dict) for p in pats):
        raise ConfigError(
            f"{src}: [target] patterns: expected one or more [[target.patterns]] tables"
        )
    patterns = []
    for i, raw in enumerate(pats):
        sec = _Section(src, f"target.patterns[{i}]", raw)
        pts = sec.get("points_mm", required=True)
        try:
            arr = np.array(pts, dtype=float)
        except (TypeError, ValueError):
            arr = None
        if (
            arr is None
            or arr.ndim != 2
            or arr.shape[1] != 3
            or len(arr) == 0
            or not np.all(np.isfinite(arr))
        ):
            raise ConfigError(
                f"{src}: [target.patterns[{i}]] points_mm = {pts!r}: expected "
                "a list of [x, y, z] marker positions (mm)"
            )
        patterns.append(
            Pattern(
                sec.array("position_mm", (3,), default=[0.0, 0.0, 0.0]),
                _rotation(sec, "rotation") if sec.has("rotation") else np.eye(3),
                arr,
            )
        )
        sec.get("rotation")
        sec.check_unknown()
    n = sum(len(p.points_mm) for p in patterns)
    ref = tgt.get("reference_id")
    if ref is not None and (isinstance(ref, bool) or not isinstance(ref, int) or not 0 <= ref < n):
        raise ConfigError(
            f"{src}: [target] reference_id = {ref!r}: expected a marker id 0..{n - 1}"
        )
    placement = tgt.number("placement_sigma_mm", 0.0, lo=0.0, hi=10.0)
    tgt.check_unknown()
    target = MarkerTarget(tuple(patterns), ref, placement)
    pts = target.points_b
    if n < 4:
        raise ConfigError(f"{src}: [target] patterns: {n} markers; at least 4 are needed")
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(n) * 1e9
    if d.min() < 1e-6:
        i, j = np.unravel_index(np.argmin(d), d.shape)
        raise ConfigError(f"{src}: [target] patterns: markers {i} and {j} are at the same place")
    return target


def _check_lens(camera: CameraModel, where: str) -> None:
    """Refuse distortion whose polynomial folds over (see CameraModel.field_r2) inside
    the image's inscribed circle: no lens does that, a mistyped coefficient does; warn
    when it folds short of the corners (a calibration extrapolated past its photos)."""
    r, corner = camera.field_radius_px, camera.corner_radius_px
    if r >= corner:
        return
    dist = [float(k) for k in camera.dist]
    inscribed = min(
        camera.cx + 0.5, camera.width - 0.5 - camera.cx, camera.cy + 0.5,
        camera.height - 0.5 - camera.cy,
    )  # fmt: skip
    if r < inscribed:
        raise ConfigError(
            f"{where} = {dist}: the lens model folds over {r:.0f} px from the principal "
            f"point, well inside the image ({inscribed:.0f} px to its nearest edge): not "
            "a lens; expected the coefficients `visvec calibrate camera` wrote (k1 k2 p1 p2 "
            "k3, in that order)"
        )
    _log.warning(
        "%s = %s: the lens model folds over %.0f px from the principal point, short of "
        "the image's corners (%.0f px): nothing beyond is measured. The calibration "
        "photos left the corners out; calibrate again with the chessboard in them",
        where, dist, r, corner,
    )  # fmt: skip


def _check_visible(rig: Rig, src: str) -> None:
    """The target must be in front of the camera at zero attitude."""
    if rig.kind in ("starfield", "lamps"):
        if rig.R_bc[2, 2] <= 0:
            raise ConfigError(
                f"{src}: [mount] rotation: the camera looks down; a {rig.kind} camera looks "
                "up (third column of R_BC with a positive z)"
            )
        return
    if rig.kind == "markers":
        p_c = (rig.target.points_b - rig.t_n) @ rig.R_nc
        if np.any(p_c[:, 2] <= 0):
            raise ConfigError(
                f"{src}: [mount] rotation: markers are behind the camera at zero attitude; "
                "expected the boresight (third column of R_NC) to point at the platform"
            )
        return
    p_c = (rig.target.vertices_mm - rig.t_b) @ rig.R_bc
    if np.any(p_c[:, 2] <= 0):
        raise ConfigError(
            f"{src}: [mount] rotation: the target is behind the camera at zero "
            "attitude; expected the boresight (third column) to point at it"
        )
    if not np.all(np.isfinite(rig.camera.project(p_c))):
        raise ConfigError(
            f"{src}: [target] vertices_mm: at zero attitude the triangle lies beyond the "
            f"lens model's field ({rig.camera.field_radius_px:.0f} px from the principal "
            "point, see [camera] dist); expected it in view of the camera"
        )
