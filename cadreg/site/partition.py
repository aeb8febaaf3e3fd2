"""Regions for a building scanned in one piece: its rooms, found from its floor plan, each a region.

`site compose` makes a building of room bundles, and each room is a region (`regions.py`): the graph match and the
label-free search rank regions, a pose is refined and checked on its region's map, poses are compared along the
frame's rays through the building's stored distance field, and rooms that repeat one another are looked at for the
same view (`localize/twins.py`; DESIGN §1). A building scanned whole (one mesh of a floor, `site build --scan`) had
one region and took the one-room path at a building's size: the 10-room benchmark building (`/tmp/bldg/layout10.json`,
its composed clouds given as one region) answered its unique views 87.8 % right with labels and 75.7 % without (4
wrong `ok` answers), against 100 % and 98.6 % as ten rooms. Cut into a grid of tiles instead, it did well without labels (98.6 %, no
wrong `ok`) but not with them (5 wrong `ok`, each the same view in another room: tiles do not repeat as rooms do,
and the twin check had nothing to compare).

So the rooms are found, as a floor plan shows them (`rooms_of`): on a grid of PartitionConfig.cell_m seen from
above, the cells holding points between wall_from_m and wall_to_m above the floor are walls (above most furniture,
below door lintels); the other cells under the scan are free floor. Free floor wider than door_m (its distance to
the nearest wall or unscanned cell over door_m / 2) is the core of a room, cores split where a doorway narrows the
floor, cores smaller than min_room_m2 are dropped; each core is grown back over the free floor it reaches
(`_grown`), and every other cell (walls, furniture, unscanned gaps) goes to the room of the nearest free cell. A
room longer than tile_m along x or y (a corridor, a hall) is cut into equal tiles of at most tile_m a side, as
`site compose` cuts its corridors into segments.

Points go to the region of their cell (and tile), objects to that of their centroid's; the map's rows are put in
region order (a region is a slice of each cloud), and the building's distance field and the regions' grids are built
and stored as `site compose` does. A map no wider than above_m stays one region (one room, as before).

A scan of several storeys is cut by storey first (`storey_floors`, `StoreyPlans`): the floor of each storey above the
map's is the first height 2 m or more (STOREY_GAP_M) over the floor below at which surfaces facing up cover
min_storey_m2 of the plan; each storey's points (a point belongs to the highest storey whose floor lies under it) get
their own floor plan, measured from their own floor, and each of its regions states that floor (`Region.floor_m`):
the localizer's storeys (`regions.Storeys`) then keep a view on its own storey. A 30-room building of three storeys
(`/tmp/bldg/st30.json`) given as one scan and cut by rooms alone had 31 % of its unique views right with labels and 23
wrong `ok` answers (each region held three storeys); by storey, then rooms, 98.6 % and none, as composed (with its
corridors' tiles cut where the points end rather than on the plan's cells, one view down a corridor, which its other
half repeats, was answered `ok` at the other end: the halves, 3.85 and 3.71 m, were no copies of each other).

The floor plan is the map frame seen from above: only a map whose up is its z (within MAX_TILT_DEG) is cut, as a scan
mesh's is (a fused map's frame is its first camera's: it stays one region).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..config import PartitionConfig
from ..localize.gravity import map_floor_height, map_up_axis
from ..pointset import PointSet
from .bundle import Site
from .compose import store_search_structures
from .regions import BELOW_FLOOR_M, STOREY_GAP_M, region_from_points, to_manifest

log = logging.getLogger("cadreg.site")

# A map is cut into regions only when its up lies within this of its z (degrees).
MAX_TILT_DEG = 5.0
# The up and the floor of a map that states none are found from this many of its points (`map_up_axis`).
UP_SAMPLE = 200_000
# A surface whose normal's z is over this faces up (a floor, a table top); storeys' floors are sought among them in
# height bins of FLOOR_BIN_M (`storey_floors`).
FLOOR_NORMAL_Z = 0.9
FLOOR_BIN_M = 0.05
FLOOR_SAMPLE = 2_000_000


def partitioned(site: Site, config: PartitionConfig = PartitionConfig()) -> Site:
    """`site` (one region) cut by storey and room (and rooms too long into tiles) when its map is wider than
    config.above_m along x or y, its up is its z and its plan holds two regions or more; else `site` itself. The cut
    site states its up; its version is left to the caller (`Site.refresh_version`)."""
    if config.above_m <= 0 or len(site.regions) > 1:
        return site
    both = site.cloud("both")
    xyz = both.points.astype(np.float64)
    if not len(xyz) or np.all(np.ptp(xyz[:, :2], axis=0) <= config.above_m):
        return site
    up = site_up(site, both)
    if up is None:
        log.info("site %s: a map %.1f x %.1f m wide kept as one region: its up is not its z (a fused map's frame is "
                 "its first camera's)", site.site_id, *np.ptp(xyz[:, :2], axis=0))
        return site
    step = max(1, len(both) // UP_SAMPLE)
    floor_m = map_floor_height(xyz[::step], both.normals[::step].astype(np.float64), up)
    plans = StoreyPlans(xyz, both.normals, floor_m, config)
    map_region, raw_region = plans.region_at(site.map.points), plans.region_at(site.raw.points)
    nodes = site.graph.nodes
    node_region = plans.region_at(np.array([n.centroid for n in nodes]).reshape(-1, 3))
    site_map = site.map.take(np.argsort(map_region, kind="stable"))
    site_raw = site.raw.take(np.argsort(raw_region, kind="stable"))
    map_region, raw_region = np.sort(map_region), np.sort(raw_region)
    regions = []
    for k in np.union1d(map_region, raw_region):
        map_range = (int(np.searchsorted(map_region, k)), int(np.searchsorted(map_region, k, side="right")))
        raw_range = (int(np.searchsorted(raw_region, k)), int(np.searchsorted(raw_region, k, side="right")))
        points = [site_map.points[slice(*map_range)], site_raw.points[slice(*raw_range)]]
        regions.append(region_from_points(plans.names[k], points,
                                          [n.id for n, r in zip(nodes, node_region) if r == k], map_range, raw_range,
                                          floor_m=plans.region_floor_m[k]))
    if len(regions) < 2:
        return site
    manifest = dict(site.manifest) | {"regions": to_manifest(regions), "up": [float(x) for x in up]}
    out = Site(site_id=site.site_id, version="", manifest=manifest, map=site_map, raw=site_raw, graph=site.graph,
               classes=list(site.classes), label_maps=dict(site.label_maps))
    store_search_structures(out)
    return out


def site_up(site: Site, cloud: PointSet) -> np.ndarray | None:
    """(3,) the up a localizer takes for `site` (as it states it, else found from the surfaces of `cloud`, its map:
    `Site.cloud("both")`) when it lies within MAX_TILT_DEG of z; else None."""
    up = site.up
    if up is None:
        step = max(1, len(cloud) // UP_SAMPLE)
        up = map_up_axis(cloud.normals[::step].astype(np.float64), points=cloud.points[::step].astype(np.float64))
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return up if up[2] >= np.cos(np.radians(MAX_TILT_DEG)) else None


def storey_floors(xyz: np.ndarray, normals: np.ndarray, floor_m: float, config: PartitionConfig) -> np.ndarray:
    """(s,) ascending: the map's floor (floor_m, its lowest storey's) and the floor of each storey above it: the
    first height STOREY_GAP_M or more over the floor below at which surfaces facing up cover min_storey_m2 of the
    plan, or, within a metre above that, the height where they cover the most (the floor, not a landing under it).
    Table tops and seats lie within STOREY_GAP_M of their floor; a ceiling faces down.
    xyz, normals : (n, 3) the map's points and normals (map frame, z up; any float type)."""
    facing = np.flatnonzero(normals[:, 2] > FLOOR_NORMAL_Z)
    # A plan's cell holds tens of points: a sample of them finds the cells all the same.
    facing = facing[:: max(1, len(facing) // FLOOR_SAMPLE)]
    height = xyz[facing, 2] - floor_m
    level = np.floor(height / FLOOR_BIN_M).astype(np.int64)
    cell = np.floor(xyz[facing, :2] / config.cell_m).astype(np.int64)
    above = level >= 0
    height, level, cell = height[above], level[above], cell[above] - cell[above].min(axis=0, initial=0)
    # Each (bin, cell) once, as one integer. A bin's area counts the cells of the bins beside it too: a floor's points
    # straddle a bin's edge.
    span = cell.max(axis=0, initial=0) + 1
    flat = cell[:, 0] * span[1] + cell[:, 1]
    keys = np.unique(np.concatenate([(level + d + 1) * (span[0] * span[1]) + flat for d in (-1, 0, 1)]))
    levels, cells = np.unique(keys // (span[0] * span[1]) - 1, return_counts=True)
    area = cells * config.cell_m ** 2
    floors = [float(floor_m)]
    for b in levels[area >= config.min_storey_m2]:
        if (b + 0.5) * FLOOR_BIN_M < floors[-1] - floor_m + STOREY_GAP_M:
            continue
        near = (levels >= b) & (levels <= b + round(1.0 / FLOOR_BIN_M))
        best = levels[near][np.argmax(area[near])]
        floors.append(float(floor_m + np.median(height[np.abs(level - best) <= 1])))
    return np.array(floors)


class StoreyPlans:
    """The floor plans of a map's storeys (`storey_floors`): a point belongs to the highest storey whose floor lies
    under it (BELOW_FLOOR_M of slack, as `regions.Storeys` has it), and to the room of that storey's plan its cell
    lies in. names, region_floor_m : by region index; a building of several storeys names its regions
    s<storey>.room<k> and states each one's floor (`Region.floor_m`), one of one storey room<k> and leaves the
    floor to the localizer (the map's).
    xyz, normals : (n, 3) the map's points and normals (map frame, z up). floor_m : the map's floor."""

    def __init__(self, xyz: np.ndarray, normals: np.ndarray, floor_m: float, config: PartitionConfig) -> None:
        self.floors = storey_floors(xyz, normals, floor_m, config)
        storey = self.storey_of(xyz)
        self.plans = [FloorPlan(xyz[storey == s], f, config) for s, f in enumerate(self.floors)]
        several = len(self.plans) > 1
        self.names = [f"s{s}.{name}" if several else name
                      for s, plan in enumerate(self.plans) for name in plan.region_names()]
        self.region_floor_m = [float(f) if several else None
                               for f, plan in zip(self.floors, self.plans) for _ in plan.region_names()]
        self._first = np.cumsum([0] + [len(plan.region_names()) for plan in self.plans])

    def storey_of(self, xyz: np.ndarray) -> np.ndarray:
        """(n,) int: the storey of each point."""
        z = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)[:, 2]
        return np.maximum(np.searchsorted(self.floors, z + BELOW_FLOOR_M, side="right") - 1, 0)

    def region_at(self, xyz: np.ndarray) -> np.ndarray:
        """(n,) int: the region of each point (its storey's room, or tile of one)."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        storey = self.storey_of(xyz)
        out = np.zeros(len(xyz), dtype=np.int64)
        for s, plan in enumerate(self.plans):
            mine = storey == s
            out[mine] = self._first[s] + plan.region_at(xyz[mine])
        return out


@dataclass(frozen=True)
class Tiles:
    """The tiles of a floor plan's rooms, by room: first (r,) the region index of its first tile, lo (r, 2) the low
    corner of its tiles, size (r, 2) a tile's size, counts (r, 2) its tiles along x and y."""

    first: np.ndarray
    lo: np.ndarray
    size: np.ndarray
    counts: np.ndarray


class FloorPlan:
    """The rooms of a map seen from above (module docstring), each a region, or, a room longer than tile_m along x or
    y (a corridor, a hall), cut into equal tiles of at most tile_m over the extent of its points: a corridor's halves
    are then copies of each other, as `site compose` cuts its corridors, and a view down it repeated at its other end
    is found so (`localize/twins.py`).

    xyz : (n, 3) the map's points (map frame, z up). floor_m : the floor's height."""

    def __init__(self, xyz: np.ndarray, floor_m: float, config: PartitionConfig) -> None:
        self.config = config
        self.cell_m = config.cell_m
        self.lo = xyz[:, :2].min(axis=0) - config.cell_m
        self.shape = tuple(np.floor((xyz[:, :2].max(axis=0) - self.lo) / config.cell_m).astype(np.int64) + 2)
        height = xyz[:, 2] - floor_m
        # A hole in the scan inside its walls (floor no camera saw, under a table) is floor all the same.
        scanned = ndimage.binary_fill_holes(self._cells(xyz))
        walls = self._cells(xyz[(height >= config.wall_from_m) & (height <= config.wall_to_m)])
        self.room = rooms_of(scanned & ~walls, config) - 1  # 0 ..
        self._tiles = self._tiling(xyz)

    def _cells(self, xyz: np.ndarray) -> np.ndarray:
        """(shape) bool: the cells holding a point of xyz."""
        out = np.zeros(self.shape, dtype=bool)
        ij = self._index(xyz)
        out[ij[:, 0], ij[:, 1]] = True
        return out

    def _index(self, xyz: np.ndarray) -> np.ndarray:
        """(n, 2) int: the cell of each point (clamped to the grid)."""
        ij = np.floor((np.asarray(xyz, dtype=np.float64).reshape(-1, 3)[:, :2] - self.lo) / self.cell_m)
        return np.clip(ij.astype(np.int64), 0, np.array(self.shape) - 1)

    def room_at(self, xyz: np.ndarray) -> np.ndarray:
        """(n,) int: the room of each point's cell."""
        ij = self._index(xyz)
        return self.room[ij[:, 0], ij[:, 1]]

    def _tiling(self, xyz: np.ndarray) -> Tiles:
        """Each room's tiles, over the extent of its points: one for a room no longer than tile_m."""
        rooms = int(self.room.max()) + 1
        room = self.room_at(xyz)
        lo, hi = np.full((rooms, 2), np.inf), np.full((rooms, 2), -np.inf)
        np.minimum.at(lo, room, xyz[:, :2])
        np.maximum.at(hi, room, xyz[:, :2])
        seen = np.isfinite(lo[:, 0])
        lo[~seen], hi[~seen] = 0.0, 0.0
        counts = np.maximum(np.ceil((hi - lo) / self.config.tile_m), 1).astype(np.int64)
        first = np.concatenate([[0], np.cumsum(counts.prod(axis=1))[:-1]])
        return Tiles(first, lo, np.maximum((hi - lo) / counts, 1e-9), counts)

    def region_at(self, xyz: np.ndarray) -> np.ndarray:
        """(n,) int: the region of each point: its room's, or its room's tile it lies over."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        room = self.room_at(xyz)
        t = self._tiles
        ij = np.clip(np.floor((xyz[:, :2] - t.lo[room]) / t.size[room]).astype(np.int64), 0, t.counts[room] - 1)
        return t.first[room] + ij[:, 0] * t.counts[room, 1] + ij[:, 1]

    def region_names(self) -> list[str]:
        """Region ids by region index: room<k>, or room<k>.<i>.<j> for the tiles of a room longer than tile_m."""
        return [f"room{k}" if counts.prod() == 1 else f"room{k}.{i}.{j}"
                for k, counts in enumerate(self._tiles.counts)
                for i in range(counts[0]) for j in range(counts[1])]


def rooms_of(free: np.ndarray, config: PartitionConfig) -> np.ndarray:
    """Rooms on a floor plan: `free` (ny, nx) bool, the cells of free floor -> (ny, nx) int, every cell's room
    (1 ..): the cores (free floor wider than door_m, at least min_room_m2 each) grown over the free floor they
    reach, then the rest by the nearest free cell's room. One room when no core stands (a map of narrow floor)."""
    cell_m = config.cell_m
    clearance = ndimage.distance_transform_edt(free) * cell_m
    cores, count = ndimage.label(clearance > config.door_m / 2)
    area = ndimage.sum_labels(np.ones_like(cores), cores, index=np.arange(1, count + 1)) * cell_m ** 2
    keep = np.concatenate([[0], np.cumsum(area >= config.min_room_m2) * (area >= config.min_room_m2)])
    cores = keep[cores]
    if cores.max() == 0:
        return np.ones(free.shape, dtype=np.int64)
    rooms = _grown(cores, free)
    # walls, furniture and unscanned cells: the room of the nearest cell given one
    _, (i, j) = ndimage.distance_transform_edt(rooms == 0, return_indices=True)
    return rooms[i, j]


def _grown(cores: np.ndarray, free: np.ndarray) -> np.ndarray:
    """`cores` (int, 0 = none) grown a cell at a time (8-neighbours) over the `free` cells they reach, each cell
    taken by the first core to reach it (where two reach it at once, the larger label's): a doorway between two
    cores is split between them."""
    rooms = cores.copy()
    while True:
        reach = ndimage.grey_dilation(rooms, size=(3, 3))
        new = free & (rooms == 0) & (reach > 0)
        if not new.any():
            return rooms
        rooms[new] = reach[new]
