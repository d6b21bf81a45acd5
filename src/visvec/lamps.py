"""Ceiling lamp maps and their Delaunay triangle catalogue.

After the ZARM LuVeX star camera (Keldysh Institute preprint 2011-24): the lamps on
the ceiling are alike and in no regular grid, so a frame's lamps are identified by the
shapes of the triangles they form. The catalogue is the Delaunay triangulation of all
lamps (scipy.spatial.Delaunay) with each triangle's smallest and largest angle as its
feature (both invariant to the camera's position, heading and distance); a frame's own
Delaunay triangles are looked up in it within a tolerance. The features are indexed by a
k-d tree (scipy.spatial.cKDTree) for fast lookup.

Each catalogue triangle lists its lamps in a canonical order: the vertex of the smallest
angle first, then counter-clockwise in the map's (x, y), so that a matched triangle
gives three lamp correspondences at once (a camera looking up sees the ceiling
mirrored: image triangles are put in the same order after flipping one image axis).
"""

from __future__ import annotations

import csv
import io
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# (scipy.spatial is imported where it is used: its import, 0.2 s, is then not in every
# command line's start, only in a lamps rig's)
from visvec.errors import ConfigError, InputFileError

MIN_SPACING_MM = 1.0  # two lamps closer than this are the same lamp listed twice
SLIVER_DEG = 3.0  # triangles with a smaller angle are too thin to identify by shape
CATALOG_VERSION = 1


@dataclass(frozen=True)
class LampMap:
    """Lamp positions ``xyz_mm`` (N, 3) in N (x, y on the ceiling, z its height above
    the body origin), read from ``path``."""

    xyz_mm: np.ndarray
    path: Path | None = None

    def __len__(self) -> int:
        return len(self.xyz_mm)


MAX_MAP_BYTES = 16 << 20


def read_lamp_map(path: str | Path, ceiling_z_mm: float) -> LampMap:
    """A lamp map CSV with columns x_mm, y_mm and optional z_mm (``ceiling_z_mm`` where
    it is missing or empty). Refuses a bad row, naming the line, and duplicate lamps;
    warns (and leaves out of the catalogue) lamps on a line with their neighbours.

    Raises
    ------
    ConfigError
        The file is missing, has no x_mm/y_mm columns, a row is not numbers, two lamps
        are at the same place, or fewer than 3 lamps are not on one line.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: the lamp map is not a file")
    if path.stat().st_size > MAX_MAP_BYTES:
        raise ConfigError(f"{path}: over {MAX_MAP_BYTES >> 20} MiB: not a lamp map")
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the lamp map ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file: not a lamp map") from None
    rows = []
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        cols = reader.fieldnames or []
    except csv.Error:
        cols = []
    if "x_mm" not in cols or "y_mm" not in cols:
        # the file may be anything the rig points at: its content is not echoed
        raise ConfigError(f"{path}: not a lamp map (a CSV with columns x_mm,y_mm[,z_mm])")
    try:
        parsed = list(enumerate(reader, start=2))
    except csv.Error as exc:
        raise ConfigError(f"{path}: not a lamp map ({exc})") from None
    for line, row in parsed:
        try:
            x, y = float(row["x_mm"]), float(row["y_mm"])
            z_raw = (row.get("z_mm") or "").strip()
            z = float(z_raw) if z_raw else ceiling_z_mm
        except (TypeError, ValueError):
            raise ConfigError(
                f"{path}: line {line}: expected numbers in x_mm,y_mm[,z_mm], got "
                f"{[row.get(k) for k in ('x_mm', 'y_mm', 'z_mm') if k in row]}"
            ) from None
        if not all(np.isfinite([x, y, z])):
            raise ConfigError(f"{path}: line {line}: coordinates must be finite")
        if z <= 0:
            raise ConfigError(
                f"{path}: line {line}: z_mm = {z}: expected the lamp above the camera"
            )
        rows.append((x, y, z))
    xyz = np.array(rows).reshape(-1, 3)
    if len(xyz) < 3:
        raise ConfigError(f"{path}: {len(xyz)} lamps; at least 3 are needed")
    from scipy.spatial import cKDTree

    tree = cKDTree(xyz[:, :2])
    pairs = sorted(tree.query_pairs(MIN_SPACING_MM))
    if pairs:
        i, j = pairs[0]
        raise ConfigError(
            f"{path}: lines {i + 2} and {j + 2}: the same lamp twice (closer than "
            f"{MIN_SPACING_MM} mm); {len(pairs)} such pair(s)"
        )
    centred = xyz[:, :2] - xyz[:, :2].mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1.0):
        raise ConfigError(f"{path}: all lamps lie on one line; a map needs two dimensions")
    return LampMap(xyz, path)


@dataclass(frozen=True)
class Catalog:
    """Delaunay triangles of a lamp map.

    lamps_mm : (N, 3) the map; triangles : (T, 3) lamp indices in canonical order
    (smallest angle first, then counter-clockwise in x, y); features : (T, 2) smallest
    and largest angle (deg); tree : k-d tree on the features.
    """

    lamps_mm: np.ndarray
    triangles: np.ndarray
    features: np.ndarray

    def __post_init__(self):
        from scipy.spatial import cKDTree

        object.__setattr__(self, "tree", cKDTree(self.features))

    def lookup(self, feature: np.ndarray, tol_deg: float) -> np.ndarray:
        """Indices of the catalogue triangles within ``tol_deg`` (both angles) of a
        feature (smallest, largest angle)."""
        idx = self.tree.query_ball_point(feature, tol_deg * np.sqrt(2.0))
        idx = np.asarray(idx, dtype=int)
        ok = np.all(np.abs(self.features[idx] - feature) <= tol_deg, axis=1)
        return idx[ok]

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            np.savez(
                fh,
                version=CATALOG_VERSION,
                lamps_mm=self.lamps_mm,
                triangles=self.triangles,
                features=self.features,
            )
        return path


def load_catalog(path: str | Path) -> Catalog:
    """A catalogue written by :meth:`Catalog.save` (`visvec catalog build`)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["version"]) != CATALOG_VERSION:
                raise InputFileError(
                    f"{path}: catalogue version {int(z['version'])}, expected {CATALOG_VERSION}"
                )
            return Catalog(z["lamps_mm"], z["triangles"], z["features"])
    except (OSError, KeyError, ValueError) as exc:
        raise InputFileError(f"{path}: not a visvec lamp catalogue ({exc})") from None


def triangle_features(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical order and (smallest, largest) angle in degrees of triangles.

    p : (T, 3, 2) vertex coordinates. Returns order (T, 3) (indices into each
    triangle's vertices: smallest angle first, then counter-clockwise) and angles
    (T, 2).
    """
    a = np.linalg.norm(p[:, 1] - p[:, 2], axis=1)
    b = np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    c = np.linalg.norm(p[:, 0] - p[:, 1], axis=1)
    # law of cosines: the angle at vertex k faces the side opposite it
    A = np.degrees(np.arccos(np.clip((b**2 + c**2 - a**2) / (2 * b * c), -1, 1)))
    B = np.degrees(np.arccos(np.clip((a**2 + c**2 - b**2) / (2 * a * c), -1, 1)))
    C = 180.0 - A - B
    ang = np.column_stack([A, B, C])
    first = np.argmin(ang, axis=1)
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    step = np.where(cross > 0, 1, 2)  # counter-clockwise successor of each vertex
    order = np.column_stack([first, (first + step) % 3, (first + 2 * step) % 3])
    feats = np.column_stack([ang.min(axis=1), ang.max(axis=1)])
    return order, feats


def neighbour_triangles(xy: np.ndarray, k: int) -> np.ndarray:
    """(T, 3) index triples, each point with every pair of its ``k`` nearest neighbours
    (each triple once, sorted)."""
    n = len(xy)
    k = min(k, n - 1)
    if k < 2:
        return np.zeros((0, 3), dtype=int)
    from scipy.spatial import cKDTree

    _, nb = cKDTree(xy).query(xy, k + 1)
    nb = nb[:, 1:]
    a, b = np.triu_indices(k, 1)
    tri = np.column_stack([np.repeat(np.arange(n), len(a)), nb[:, a].ravel(), nb[:, b].ravel()])
    return np.unique(np.sort(tri, axis=1), axis=0)


def build_neighbour_catalog(lamps: LampMap, k: int) -> Catalog:
    """The catalogue of every lamp's triangles with pairs of its ``k`` nearest lamps,
    slivers left out: what a frame whose nearer lamps are dark still shows (the
    Delaunay triangles of the lamps left lit are not the map's)."""
    xy = lamps.xyz_mm[:, :2]
    tri = neighbour_triangles(xy, k)
    order, feats = triangle_features(xy[tri])
    tri = np.take_along_axis(tri, order, axis=1)
    keep = feats[:, 0] >= SLIVER_DEG
    return Catalog(lamps.xyz_mm, tri[keep], feats[keep])


def build_catalog(lamps: LampMap) -> Catalog:
    """The Delaunay catalogue of a lamp map; sliver triangles (an angle under 3 deg,
    three nearly collinear lamps) cannot be recognised by shape and are left out with
    a warning."""
    xy = lamps.xyz_mm[:, :2]
    from scipy.spatial import Delaunay

    dt = Delaunay(xy)
    tri = dt.simplices
    order, feats = triangle_features(xy[tri])
    tri = np.take_along_axis(tri, order, axis=1)
    sliver = feats[:, 0] < SLIVER_DEG
    # thin triangles with a side on the map's outline (the convex hull) are normal in a
    # Delaunay triangulation; inside it they mean lamps nearly on one line
    inner = sliver & np.all(dt.neighbors >= 0, axis=1)  # no side on the outline
    if inner.any():
        warnings.warn(
            f"{lamps.path or 'lamp map'}: {int(inner.sum())} triangle(s) of nearly "
            f"collinear lamps (an angle under {SLIVER_DEG} deg) inside the map, left out "
            "of the catalogue; lamps there are identified only through their other "
            "triangles",
            stacklevel=2,
        )
    return Catalog(lamps.xyz_mm, tri[~sliver], feats[~sliver])
