"""The one point-cloud type of a site's map, from site build to bundle to localizer.

A `PointSet` is six aligned per-point columns. The enhanced map, the raw scan and their union are all PointSets;
the bundle stores each as one PLY (`to_ply_bytes` / `from_ply_bytes`, columns below), and the localizer builds its
search structures straight from one.

    PLY column            PointSet attribute   dtype     meaning
    x y z                 points[:, 0..2]      float32   metres, map frame
    red green blue        colors[:, 0..2]      uint8     RGB
    nx ny nz              normals[:, 0..2]     float32   unit surface normal, map frame
    instance              instance             int32     object instance (CAD instance i is node "cad-<i>"), -1 none
    class                 class_index          int16     index into the site's classes, -1 none / structure
    source                source               uint8     SOURCE_RAW (0, scanned) or SOURCE_CAD (1, sampled on a CAD)
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from .errors import InvalidArgument, InvalidFileError
from .io.ply import map_vertices, parse_ply, ply_bytes, release_pages

SOURCE_RAW = 0
SOURCE_CAD = 1

# attribute -> (PLY columns, dtype); the order is the PLY's column order.
_COLUMNS: dict[str, tuple[tuple[str, ...], type]] = {
    "points": (("x", "y", "z"), np.float32),
    "colors": (("red", "green", "blue"), np.uint8),
    "normals": (("nx", "ny", "nz"), np.float32),
    "instance": (("instance",), np.int32),
    "class_index": (("class",), np.int16),
    "source": (("source",), np.uint8),
}


@dataclass(eq=False)  # arrays inside: == would be ambiguous
class PointSet:
    """Map points, all columns (N, ...) aligned (see the module docstring for dtypes, units and frames).

    points (N, 3) float32; colors (N, 3) uint8; normals (N, 3) float32; instance (N,) int32; class_index (N,) int16;
    source (N,) uint8. The constructor casts to those dtypes and checks the shapes.
    """

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    instance: np.ndarray
    class_index: np.ndarray
    source: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.points)
        for name, (cols, dtype) in _COLUMNS.items():
            value = np.asarray(getattr(self, name), dtype=dtype)
            want = (n, len(cols)) if len(cols) > 1 else (n,)
            if value.shape != want:
                raise InvalidArgument(f"PointSet.{name} must be {want}, got {value.shape}")
            setattr(self, name, value)

    @classmethod
    def scanned(cls, points: np.ndarray, colors: np.ndarray, normals: np.ndarray,
                class_index: np.ndarray | None = None) -> "PointSet":
        """Points of a scan as scanned: no instance, source raw; class -1 where `class_index` is None."""
        n = len(points)
        return cls(points, colors, normals, np.full(n, -1, np.int32),
                   np.full(n, -1, np.int16) if class_index is None else class_index, np.full(n, SOURCE_RAW, np.uint8))

    @classmethod
    def empty(cls) -> "PointSet":
        return cls.scanned(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))

    def __len__(self) -> int:
        return len(self.points)

    def take(self, index: np.ndarray) -> "PointSet":
        """The points at `index` (integer indices or a boolean mask), every column alike."""
        return PointSet(*(getattr(self, f.name)[index] for f in fields(self)))

    @staticmethod
    def concat(parts: list["PointSet"]) -> "PointSet":
        return PointSet(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(PointSet)))

    def rgb01(self) -> np.ndarray:
        """(N, 3) float64 colours in [0, 1]."""
        return self.colors.astype(np.float64) / 255.0

    # --- PLY ----------------------------------------------------------------------------------------------------

    def to_ply_bytes(self) -> bytearray:
        """Binary little-endian PLY with the columns of the module docstring (deterministic)."""
        vertex: dict[str, np.ndarray] = {}
        for name, (cols, _) in _COLUMNS.items():
            value = getattr(self, name)
            for j, col in enumerate(cols):
                vertex[col] = value[:, j] if len(cols) > 1 else value
        return ply_bytes(vertex)

    @classmethod
    def open_ply(cls, path: str | Path) -> tuple["PointSet", "MappedRows"]:
        """The PointSet of a PLY written by `to_ply_bytes`, memory-mapped: its columns are read-only views of the
        file, paged in as they are used (a building's map costs a worker only the rooms it touches), and the
        `MappedRows` hands pages back. Raises InvalidFileError naming `path` for another layout."""
        rec, mm, body_start = map_vertices(path)
        names = [c for cols, _ in _COLUMNS.values() for c in cols]
        if list(rec.dtype.names) != names or any(
                rec.dtype[c] != np.dtype(dtype).newbyteorder("<") for cols, dtype in _COLUMNS.values() for c in cols):
            raise InvalidFileError(path, f"vertex columns must be {names} with the dtypes of cadreg/pointset.py")
        values = {}
        for name, (cols, dtype) in _COLUMNS.items():
            first = rec[cols[0]]
            # Columns of one attribute lie side by side in each record: one strided (N, k) view, no copy.
            values[name] = (np.lib.stride_tricks.as_strided(first, shape=(len(rec), len(cols)),
                                                            strides=(rec.strides[0], first.itemsize), writeable=False)
                            if len(cols) > 1 else first)
        return cls(**values), MappedRows(mm, body_start, rec.itemsize)

    @classmethod
    def from_ply_bytes(cls, blob: bytes, path: str | Path = "<bytes>") -> "PointSet":
        """Parse a PLY written by `to_ply_bytes`. Raises InvalidFileError naming `path` for a malformed file or
        missing columns."""
        vertex = parse_ply(blob, path).vertex
        missing = [c for cols, _ in _COLUMNS.values() for c in cols if c not in vertex]
        if missing:
            raise InvalidFileError(path, f"missing vertex columns {missing}")
        values = {}
        for name, (cols, dtype) in _COLUMNS.items():
            stacked = np.stack([vertex[c] for c in cols], axis=1) if len(cols) > 1 else vertex[cols[0]]
            values[name] = stacked.astype(dtype)
        return cls(**values)


@dataclass(frozen=True)
class MappedRows:
    """Where a memory-mapped PointSet's rows lie in its file (`PointSet.open_ply`): `release(rows)` hands the
    pages of those rows back to the kernel once they have been copied (they leave the resident set, and are read
    again from the page cache when next used)."""

    mm: object
    offset: int
    itemsize: int

    def release(self, rows: slice) -> None:
        release_pages(self.mm, self.offset + rows.start * self.itemsize, self.offset + rows.stop * self.itemsize)
