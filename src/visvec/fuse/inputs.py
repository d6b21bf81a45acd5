"""Inputs of `visvec fuse` (docs/reference.md, Output rows): an inertial CSV and a fixes CSV.

Inertial data: `time_s` and the columns it has of `gx_dps,gy_dps,gz_dps,ax_mps2,
ay_mps2,az_mps2` in body axes; a planar IMU has `gz_dps,ax_mps2,ay_mps2`. Fixes: visvec
output rows (attitude or planar pose) whose `time_s` is the exposure time; only `ok`
rows are used, and a fix becomes available at `time_s + latency_ms / 1000`.
"""

from __future__ import annotations

import csv
import functools
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.errors import InputFileError
from visvec.rotations import euler_rates_from_body, matrix_to_euler, quat_to_matrix

PLANAR_IMU = ("gz_dps", "ax_mps2", "ay_mps2")
ATTITUDE_IMU = ("gx_dps", "gy_dps", "gz_dps")
PLANAR_FIX = ("x_mm", "y_mm", "heading_deg")
ATTITUDE_FIX = ("qw", "qx", "qy", "qz")
STATUSES = ("ok", "no_target", "rejected", "not_converged", "read_error")
# an ok row with one of these warnings is no fix: its time is not its exposure's
# (read_late: a live frame read after it had waited, visvec.sources.reader)
UNTIMED = ("read_late",)


def untimed(row: dict) -> bool:
    """Whether an ok row's time is not known well enough for a fix (UNTIMED)."""
    return any(w in UNTIMED for w in (row.get("warnings") or "").split(";"))


GAP_PERIODS = 3.0  # a step longer than this many median periods is a gap


@dataclass(frozen=True)
class ImuData:
    """Samples of an inertial file: ``t`` (n,) s; ``gyro`` (n, 3) rad/s (a planar IMU
    fills only z); ``accel`` (n, 2) m/s^2 in x, y, or None; ``lines`` the file line of
    each sample; ``gaps`` the sample indices that start after a gap; ``gyro_range_dps``
    the gyro's range its header declares (``# gyro_range_dps = N``), if it does."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray | None
    lines: np.ndarray
    gaps: tuple[int, ...]
    period_s: float
    path: Path | None = None
    gyro_range_dps: float | None = None

    def __len__(self) -> int:
        return len(self.t)


def _number(row: dict, key: str, path: Path, line: int) -> float:
    raw = (row.get(key) or "").strip()
    try:
        x = float(raw)
    except ValueError:
        raise InputFileError(f"{path}: line {line}: {key} = {raw!r}: expected a number") from None
    if not math.isfinite(x):
        raise InputFileError(f"{path}: line {line}: {key} = {raw!r}: expected a finite number")
    return x


def _optional(row: dict, path: Path, line: int, key: str) -> float | None:
    """A column's number, None where it is empty or missing."""
    return _number(row, key, path, line) if (row.get(key) or "").strip() else None


def _open_csv(path: Path, what: str, comments: bool = False):
    """The file, its CSV reader and columns; with ``comments``, also the ``key = value``
    (or ``key: value``) lines starting with # before the header, and how many lines
    they take."""
    try:
        fh = open(path, newline="", encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read the {what} ({exc.strerror})") from None
    meta: dict[str, tuple[str, int]] = {}
    skipped = 0
    try:
        lines = iter(fh)
        first = next(lines, "")
        while comments and first.startswith("#"):
            skipped += 1
            key, sep, value = first[1:].replace(":", "=", 1).partition("=")
            if sep:
                meta[key.strip()] = (value.strip(), skipped)
            first = next(lines, "")
        reader = csv.DictReader(itertools.chain([first], lines) if first else lines)
        cols = list(reader.fieldnames or [])
    except (UnicodeDecodeError, csv.Error):
        fh.close()
        raise InputFileError(f"{path}: not a UTF-8 CSV file: expected the {what}") from None
    if comments:
        return fh, reader, cols, meta, skipped
    return fh, reader, cols


def _imu_header(meta: dict[str, tuple[str, int]], path: Path) -> float | None:
    """The gyro's range from the IMU file's header (# gyro_range_dps = N), if any: a
    positive finite number, else refused naming the line."""
    if "gyro_range_dps" not in meta:
        return None
    raw, line = meta["gyro_range_dps"]
    try:
        v = float(raw)
    except ValueError:
        v = math.nan
    if not math.isfinite(v) or v <= 0:
        raise InputFileError(f"{path}: line {line}: gyro_range_dps = {raw!r}: expected a "
                             "positive finite number (deg/s)")  # fmt: skip
    return v


def _rows(reader, path: Path, skipped: int = 0):
    """(line, row) of a CSV reader (``skipped`` comment lines before its header); a
    byte that is not UTF-8 or a broken CSV line is refused naming the file."""
    it = enumerate(reader, start=2 + skipped)
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except UnicodeDecodeError:
            raise InputFileError(f"{path}: not a UTF-8 text file") from None
        except csv.Error as exc:
            raise InputFileError(f"{path}: line {reader.line_num}: not CSV ({exc})") from None
        yield item


def read_imu(path: str | Path, planar: bool) -> ImuData:
    """Read an inertial CSV for planar (gz, ax, ay) or 3-D (gx, gy, gz) fusion.

    Parameters
    ----------
    path : str or Path
        CSV with ``time_s`` (any clock, increasing) and ``gz_dps, ax_mps2, ay_mps2``
        (planar) or ``gx_dps, gy_dps, gz_dps`` (3-D, deg/s about the body axes); a
        ``# gyro_range_dps = N`` line before the header declares the gyro's range.
    planar : bool
        Which columns to read.

    Returns
    -------
    ImuData
        ``t`` (n,) s, ``gyro`` (n, 3) rad/s, ``accel`` (n, 2) m/s^2 or None, the
        median ``period_s``, the indices of ``gaps`` (a step over three periods) and
        the declared ``gyro_range_dps`` (None if not).

    Raises
    ------
    InputFileError
        Missing columns, a bad number (naming the line and column), or a time that does
        not increase (naming both lines). Gaps are not errors: they are listed in
        ``gaps`` for the caller to report, and fusion restarts after each.
    """
    path = Path(path)
    need = ("time_s", *(PLANAR_IMU if planar else ATTITUDE_IMU))
    fh, reader, cols, meta, skipped = _open_csv(path, "inertial data", comments=True)
    with fh:
        gyro_range = _imu_header(meta, path)
        missing = [k for k in need if k not in cols]
        if missing:
            raise InputFileError(
                f"{path}: missing column(s) {', '.join(missing)}; a "
                f"{'planar' if planar else '3-D'} IMU file needs {','.join(need)} "
                f"(found {','.join(cols) or 'no header'})"
            )
        t, g, a, lines = [], [], [], []
        for line, row in _rows(reader, path, skipped):
            ti = _number(row, "time_s", path, line)
            if t and ti <= t[-1]:
                raise InputFileError(
                    f"{path}: line {line}: time_s = {ti} does not increase (line "
                    f"{lines[-1]} has {t[-1]}); inertial samples must be in time order"
                )
            t.append(ti)
            lines.append(line)
            if planar:
                g.append((0.0, 0.0, _number(row, "gz_dps", path, line)))
                a.append((_number(row, "ax_mps2", path, line), _number(row, "ay_mps2", path, line)))
            else:
                g.append(tuple(_number(row, k, path, line) for k in ATTITUDE_IMU))
    if len(t) < 2:
        raise InputFileError(f"{path}: {len(t)} inertial sample(s); at least 2 are needed")
    t_arr = np.array(t)
    dt = np.diff(t_arr)
    period = float(np.median(dt))
    gaps = tuple(int(i) + 1 for i in np.nonzero(dt > GAP_PERIODS * period)[0])
    return ImuData(
        t_arr,
        np.radians(np.array(g)),
        np.array(a) if planar else None,
        np.array(lines),
        gaps,
        period,
        path,
        gyro_range,
    )


@dataclass(frozen=True)
class Fix:
    """One ok fix: a camera's measurement for the fusion.

    Attributes
    ----------
    time_s : float
        The exposure's time (s), on the IMU's clock.
    available_s : float
        When it reached the fusion (s, the same clock): the exposure plus the camera's
        latency.
    value : ndarray
        Planar: (3,) x_mm, y_mm, heading (rad). Attitude: R_NB, (3, 3).
    cov : ndarray, shape (3, 3), or None
        Its covariance: mm^2, mm rad, rad^2 (planar); rad^2 about the body axes
        (attitude). None where the file has no sigma columns (the filter's fix sigma
        then).
    line : int
        Its line in the file it came from (0 for a row made in this process).
    shift : float
        How much earlier than its stated time the fusion applies it (s; its time
        offset as the fusion then knew it; ``time_s`` is then the stated time less
        ``shift``).
    """

    time_s: float
    available_s: float
    value: np.ndarray
    cov: np.ndarray | None
    line: int
    shift: float = 0.0


@dataclass(frozen=True)
class Fixes:
    """The ok fixes of a file, in file order; ``planar`` tells the kind."""

    fixes: tuple[Fix, ...]
    planar: bool
    n_rows: int
    path: Path | None = None


def read_fixes(path: str | Path) -> Fixes:
    """Read visvec output rows as fixes (planar pose or attitude, by the header).

    Parameters
    ----------
    path : str or Path
        A CSV or JSON-lines file of visvec rows (`track`, `batch` output): each ok row
        a fix at its ``time_s``, available ``latency_ms`` later; its covariance from
        the ``cov_*`` columns where the file has them (``--covariance``), else from
        its sigmas.

    Returns
    -------
    Fixes
        ``fixes`` (tuple of Fix), whether they are ``planar``, and how many rows the
        file held.

    Raises
    ------
    InputFileError
        Neither kind of columns, an unknown status, or an ok row with a missing or bad
        number (naming the line and the column).
    """
    path = Path(path)
    fh, reader, cols = _open_csv(path, "fixes")
    with fh:
        if "time_s" not in cols or "status" not in cols:
            raise InputFileError(
                f"{path}: fixes need the columns time_s and status of visvec output rows "
                f"(found {','.join(cols) or 'no header'})"
            )
        if all(k in cols for k in PLANAR_FIX):
            planar = True
        elif all(k in cols for k in ATTITUDE_FIX):
            planar = False
        else:
            raise InputFileError(
                f"{path}: fixes need planar pose columns ({','.join(PLANAR_FIX)}) or "
                f"attitude columns ({','.join(ATTITUDE_FIX)}); found {','.join(cols)}"
            )
        sig_cols = (
            ("sigma_x_mm", "sigma_y_mm", "sigma_heading_deg")
            if planar
            else ("sigma_yaw_deg", "sigma_pitch_deg", "sigma_roll_deg")
        )
        has_sigma = all(k in cols for k in sig_cols)
        has_cov = all(k in cols for k in cov_columns(planar))
        out, n = [], 0
        for line, row in _rows(reader, path):
            n += 1
            status = (row.get("status") or "").strip()
            if status not in STATUSES:
                raise InputFileError(
                    f"{path}: line {line}: status = {status!r}: expected one of {STATUSES}"
                )
            if status != "ok" or untimed(row):
                continue
            t = _number(row, "time_s", path, line)
            lat = _number(row, "latency_ms", path, line) if "latency_ms" in cols else 0.0
            if lat < 0:
                raise InputFileError(f"{path}: line {line}: latency_ms = {lat}: must be >= 0")
            if planar:
                x, y, h = (_number(row, k, path, line) for k in PLANAR_FIX)
                value = np.array([x, y, math.radians(h)])
            else:
                q = np.array([_number(row, k, path, line) for k in ATTITUDE_FIX])
                norm = float(np.linalg.norm(q))
                if abs(norm - 1.0) > 1e-3:
                    raise InputFileError(
                        f"{path}: line {line}: quaternion norm {norm:.6f}: expected 1"
                    )
                value = quat_to_matrix(q / norm)
            cov = None
            full = None
            if has_cov:
                try:
                    full = row_cov(functools.partial(_optional, row, path, line), planar)
                except ValueError as exc:
                    raise InputFileError(f"{path}: line {line}: {exc}") from None
            if full is not None:
                cov = fix_cov(full, value, planar)
            elif has_sigma:
                s = np.array([_number(row, k, path, line) for k in sig_cols])
                if np.any(s <= 0):
                    raise InputFileError(
                        f"{path}: line {line}: sigma columns must be positive, got {s.tolist()}"
                    )
                cov = _fix_cov(s, value, planar)
            out.append(Fix(t, t + lat / 1000.0, value, cov, line))
    return Fixes(tuple(out), planar, n, path)


def fix_cov(cov: np.ndarray, value: np.ndarray, planar: bool) -> np.ndarray:
    """A fix's covariance as the filters take it, from a row's covariance in its own
    units (planar: x mm, y mm, heading deg; attitude: yaw, pitch, roll deg): planar in
    mm and rad; attitude about the body axes (rad^2), d(euler) = J d(theta_body), so
    cov_theta = J^-1 cov_euler J^-T. Near the Euler angles' singularity (|cos pitch| <
    0.1) they say little: the largest variance on every axis."""
    cov = np.asarray(cov, float)
    if planar:
        d = np.array([1.0, 1.0, math.radians(1.0)])
        return cov * np.outer(d, d)
    c = np.radians(np.radians(cov))
    yaw, pitch, roll = matrix_to_euler(value)
    if abs(math.cos(pitch)) < 0.1:
        return np.eye(3) * float(np.linalg.eigvalsh(0.5 * (c + c.T)).max())
    Ji = np.linalg.inv(euler_rates_from_body(yaw, pitch, roll))
    return Ji @ c @ Ji.T


def _fix_cov(s: np.ndarray, value: np.ndarray, planar: bool) -> np.ndarray:
    """A fix's covariance from its row's three sigmas (fix_cov of their squares)."""
    return fix_cov(np.diag(np.asarray(s, float) ** 2), value, planar)


def cov_columns(planar: bool) -> tuple[str, ...]:
    """The covariance columns of a fix's row (``--covariance``: the upper triangle)."""
    from visvec.output import AttitudeRow, PoseRow

    return (PoseRow if planar else AttitudeRow).cov_columns()


def row_cov(get, planar: bool) -> np.ndarray | None:
    """The full covariance a row's ``cov_*`` columns give (``get(name)`` their numbers,
    None where a column is empty or missing), in the row's units; None unless all six
    are there. ValueError if it is not a covariance (not positive definite)."""
    vals = [get(k) for k in cov_columns(planar)]
    if any(v is None for v in vals):
        return None
    c = np.zeros((3, 3))
    k = 0
    for i in range(3):
        for j in range(i, 3):
            c[i, j] = c[j, i] = vals[k]
            k += 1
    if not np.all(np.isfinite(c)) or np.linalg.eigvalsh(c).min() <= 0.0:
        raise ValueError("the cov_* columns are not a covariance (positive definite)")
    return c


def fix_from_row(row, planar: bool) -> Fix | None:
    """An ok row of visvec's as a fix, in one process.

    Its full covariance is kept where it has one (the triangle's yaw-pitch
    correlation), its three sigmas where not; it is available at its exposure plus its
    ``latency_ms``.

    Parameters
    ----------
    row : visvec.output.Row
        A pipeline's row (AttitudeRow for attitude, PoseRow for planar).
    planar : bool
        True for a pose fix (x_mm, y_mm, heading), False for an attitude one.

    Returns
    -------
    Fix or None
        None for a row that is not ok, or whose time is not its exposure's (UNTIMED).

    Examples
    --------
    >>> fixes = [f for row in rows if (f := fix_from_row(row, planar=False))]
    """
    if not row.ok or any(w in UNTIMED for w in row.warnings):
        return None
    if planar:
        x, y, h = (float(v) for v in row.pose)
        value = np.array([x, y, math.radians(h)])
    else:
        q = np.asarray(row.q_nb, float)
        value = quat_to_matrix(q / np.linalg.norm(q))
    cov = None
    if row.cov is not None and np.all(np.isfinite(row.cov)):
        cov = fix_cov(row.cov, value, planar)
    elif np.all(np.isfinite(row.sigmas())) and np.all(row.sigmas() > 0):
        cov = _fix_cov(row.sigmas(), value, planar)
    t = float(row.time_s)
    return Fix(t, t + max(float(row.latency_ms), 0.0) / 1000.0, value, cov, 0)
