"""Regions of a site: the rooms of a building (or the whole map of a one-room site), each a box of the map frame
with the objects and points inside it.

A building-scale site is searched region by region (DESIGN §1): the graph match ranks regions, the refinement's
search structures are per region, and a client may restrict a query to some of them (`SearchRegion`). Regions are
stored in site.json under "regions" (`to_manifest` / `from_manifest`)::

    {"id": "r003", "bounds": [[x0, y0, z0], [x1, y1, z1]], "nodes": ["r003/cad-1", ...],
     "map_range": [start, stop], "raw_range": [start, stop], "floor_m": z}

`map_range` / `raw_range` are the region's rows of map.ply / raw.ply: the composer writes each room's points
contiguously, so a region's points are a slice, read without touching the rest of the map.
A bundle without "regions" (built before regions existed, or by `site build` / `site fuse`) is one region holding
everything, named after the site.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidFileError, InvalidFrame

# A camera may stand in a doorway or a little outside the scanned walls of its room: the box test of a camera
# position against a region allows this much (metres, horizontally).
CAMERA_MARGIN_M = 0.5
# Rooms whose floors lie this far apart or more stand on different storeys (`Storeys`): a storey is 2.4 m or more
# from floor to floor, and a room a step above its neighbours (1 m in tests/test_building_floors.py) stands on theirs.
STOREY_GAP_M = 2.0
# A point up to this far under the lowest floor of a storey belongs to it, not to the storey below (a camera a
# little low, a region of interest's centre among the floor's points).
BELOW_FLOOR_M = 0.3


@dataclass(frozen=True)
class Region:
    """One region of a site.

    id : region name (a composed site's room name). bounds : (2, 3) float64, min and max corners of the axis-aligned
    box of its points, map frame, metres. nodes : graph node ids inside it. map_range, raw_range : [start, stop)
    rows of the site's map and raw clouds. floor_m : the height of its floor along the site's up (+z unless the
    site states another), metres, or None when the bundle does not say (one-room sites, buildings composed
    before it was stored): rooms of a building need not share a floor (storeys; scans with other floor heights).
    """

    id: str
    bounds: np.ndarray
    nodes: tuple[str, ...]
    map_range: tuple[int, int]
    raw_range: tuple[int, int]
    floor_m: float | None = None

    @property
    def points(self) -> int:
        return (self.map_range[1] - self.map_range[0]) + (self.raw_range[1] - self.raw_range[0])

    def contains_xy(self, xyz: np.ndarray, margin_m: float = CAMERA_MARGIN_M) -> np.ndarray:
        """xyz : (..., 3) float map frame -> (...) bool: inside the box (grown by margin_m) seen from above."""
        xyz = np.asarray(xyz, dtype=np.float64)
        lo, hi = self.bounds[0] - margin_m, self.bounds[1] + margin_m
        return np.all((xyz[..., :2] >= lo[:2]) & (xyz[..., :2] <= hi[:2]), axis=-1)

    def info(self) -> dict[str, Any]:
        """What `site info --json` and `GET /v1/sites/{id}` report of the region: {id, bounds, objects, points,
        floor_m}."""
        return {"id": self.id, "bounds": np.asarray(self.bounds, dtype=float).round(4).tolist(),
                "objects": len(self.nodes), "points": self.points,
                "floor_m": None if self.floor_m is None else round(float(self.floor_m), 4)}

    def to_dict(self) -> dict[str, Any]:
        out = {"id": self.id, "bounds": np.asarray(self.bounds, dtype=float).round(4).tolist(),
               "nodes": list(self.nodes), "points": self.points,
               "map_range": list(self.map_range), "raw_range": list(self.raw_range)}
        if self.floor_m is not None:
            out["floor_m"] = round(float(self.floor_m), 4)
        return out


@dataclass(frozen=True)
class Storeys:
    """The storeys of a building: its regions grouped by floor height, a storey starting wherever the next floor
    up lies STOREY_GAP_M or more above the one below it (a run of steps each under that stays one storey). Seen
    from above, the rooms of two storeys overlap: which room a point lies in is asked of the
    rooms on its own storey (`RegionMaps.indices_at`, `SearchRegion.allows`). Heights are z, the up of a composed
    building (`site compose` levels its rooms); a site of one region, or whose rooms share a storey, has one.

    region : (r,) int, the storey of each region (-1 where its floor is not known: it stands on every storey).
    base : (s,) float, the lowest floor of each storey, ascending (empty when no floor is known)."""

    region: np.ndarray
    base: np.ndarray

    @classmethod
    def of(cls, regions: list[Region]) -> "Storeys":
        floors = np.array([np.nan if r.floor_m is None else r.floor_m for r in regions], dtype=np.float64)
        known = np.isfinite(floors)
        heights = np.unique(floors[known])  # ascending
        first = np.concatenate([[True], np.diff(heights) >= STOREY_GAP_M]) if len(heights) else np.zeros(0, bool)
        base = heights[first]
        storey = np.searchsorted(base, np.where(known, floors, 0.0), side="right") - 1
        return cls(np.where(known, storey, -1), base)

    @property
    def several(self) -> bool:
        return len(self.base) > 1

    def at(self, z: np.ndarray) -> np.ndarray:
        """z : (n,) heights of points -> (n,) int: the storey of each, the highest whose lowest floor lies at most
        BELOW_FLOOR_M above it (the lowest for a point under every storey)."""
        return np.maximum(np.searchsorted(self.base, np.asarray(z, dtype=np.float64) + BELOW_FLOOR_M, side="right") - 1, 0)

    def elsewhere(self, z: np.ndarray) -> np.ndarray:
        """z : (n,) heights of points -> (n, r) bool: the region stands on another storey than the point (`at`)."""
        return (self.region[None, :] >= 0) & (self.region[None, :] != self.at(z)[:, None])


def region_from_points(region_id: str, xyz: list[np.ndarray], nodes: list[str], map_range: tuple[int, int],
                       raw_range: tuple[int, int], floor_m: float | None = None) -> Region:
    """A region whose bounds are those of the point arrays `xyz` ((n_i, 3) float, map frame; some may be empty)."""
    parts = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in xyz]
    every = np.concatenate(parts) if parts else np.zeros((0, 3))
    bounds = np.stack([every.min(axis=0), every.max(axis=0)]) if len(every) else np.zeros((2, 3))
    return Region(region_id, bounds, tuple(nodes), (int(map_range[0]), int(map_range[1])),
                  (int(raw_range[0]), int(raw_range[1])), None if floor_m is None else float(floor_m))


def to_manifest(regions: list[Region]) -> list[dict[str, Any]]:
    return [r.to_dict() for r in regions]


def from_manifest(entries: Any, *, map_points: int, raw_points: int, source: str = "site.json") -> list[Region]:
    """Regions from site.json's "regions", checked against the cloud sizes. Raises InvalidFileError naming
    `source` for a malformed entry, a range outside the clouds, or ids that repeat."""
    if not isinstance(entries, list) or not entries:
        raise InvalidFileError(source, "'regions' must be a non-empty list")
    out = []
    try:
        for e in entries:
            bounds = np.asarray(e["bounds"], dtype=np.float64)
            if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)):
                raise ValueError(f"region {e.get('id')!r}: bounds must be two finite 3-vectors")
            m0, m1 = (int(x) for x in e["map_range"])
            r0, r1 = (int(x) for x in e["raw_range"])
            if not (0 <= m0 <= m1 <= map_points and 0 <= r0 <= r1 <= raw_points):
                raise ValueError(f"region {e.get('id')!r}: point ranges outside the map")
            floor = e.get("floor_m")
            if floor is not None and not np.isfinite(float(floor)):
                raise ValueError(f"region {e.get('id')!r}: floor_m must be a finite number")
            out.append(Region(str(e["id"]), bounds, tuple(str(n) for n in e["nodes"]), (m0, m1), (r0, r1),
                              None if floor is None else float(floor)))
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidFileError(source, f"malformed regions: {exc}") from None
    ids = [r.id for r in out]
    if len(set(ids)) != len(ids):
        raise InvalidFileError(source, "region ids repeat")
    return out


@dataclass(frozen=True)
class SearchRegion:
    """Where a client says the camera is (DESIGN §6 `search_region`): within `radius_m` of `center` (map frame,
    metres), or inside one of the regions `region_ids`. Exactly one of the two forms."""

    center: np.ndarray | None = None
    radius_m: float | None = None
    region_ids: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        by_ball = self.center is not None or self.radius_m is not None
        if by_ball == bool(self.region_ids):
            raise InvalidFrame("search_region: give either center and radius_m, or region_ids")
        if by_ball:
            c = np.asarray(self.center, dtype=np.float64).reshape(-1) if self.center is not None else None
            if c is None or c.shape != (3,) or not np.all(np.isfinite(c)):
                raise InvalidFrame("search_region.center must be a finite 3-vector (map frame, metres)")
            r = self.radius_m
            if r is None or not np.isfinite(r) or r <= 0:
                raise InvalidFrame("search_region.radius_m must be a positive number of metres")
            object.__setattr__(self, "center", c)

    def resolve(self, regions: list[Region]) -> list[Region]:
        """The site's regions named by `region_ids` (InvalidArgument naming the unknown ones); [] for a ball."""
        if not self.region_ids:
            return []
        by_id = {r.id: r for r in regions}
        unknown = [i for i in self.region_ids if i not in by_id]
        if unknown:
            known = sorted(by_id)
            raise InvalidFrame(f"search_region: unknown region ids {unknown}; this site has {known[:20]}"
                                  + (f" and {len(known) - 20} more" if len(known) > 20 else ""),
                                  detail={"unknown": unknown})
        return [by_id[i] for i in self.region_ids]

    def allows(self, camera_xyz: np.ndarray, regions: list[Region]) -> np.ndarray:
        """camera_xyz : (h, 3) camera positions, map frame -> (h,) bool: inside the search region."""
        camera_xyz = np.asarray(camera_xyz, dtype=np.float64).reshape(-1, 3)
        if not self.region_ids:
            return np.linalg.norm(camera_xyz - self.center, axis=1) <= self.radius_m
        chosen = self.resolve(regions)
        storeys = Storeys.of(regions)
        # seen from above, a named room holds the cameras of the rooms above and below it too
        elsewhere = (storeys.elsewhere(camera_xyz[:, 2]) if storeys.several
                     else np.zeros((len(camera_xyz), len(regions)), dtype=bool))
        column = {r.id: k for k, r in enumerate(regions)}
        return np.any([r.contains_xy(camera_xyz) & ~elsewhere[:, column[r.id]] for r in chosen], axis=0)

    def to_dict(self) -> dict[str, Any]:
        if self.region_ids:
            return {"region_ids": list(self.region_ids)}
        return {"center": [float(x) for x in self.center], "radius_m": float(self.radius_m)}
