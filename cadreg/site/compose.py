"""Compose a multi-room site from room bundles: a building made of rooms, each placed by its `T_building_room`.

A layout (LAYOUT.json) lists the rooms::

    {"site_id": "twin-rooms",
     "rooms": [{"name": "a", "bundle": "rooms/scene0470", "T_building_room": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
               {"name": "b", "bundle": "rooms/scene0470", "T_building_room": [[1,0,0,6],...],
                "drop_objects": ["cad-3"]}]}

Bundle paths are relative to the layout file. The same bundle may appear several times (repeated rooms). Each room's
map and raw points and graph nodes are moved into the building frame; node ids become "<name>/<id>"; `drop_objects`
removes objects of that room: their node, and their points in both clouds (inside the node's box grown by
DROP_MARGIN_M, of the node's class: the floor and wall under and behind it stay), as when a chair is missing from
one of two identical rooms. `move_objects` ({node id: 4x4 rigid transform, room frame}) moves objects of that room
the same way: the node and those points are carried by the transform (a chair pushed aside, a table turned), and the
floor and wall they stood on and against stay where they were. The graph's edges are rebuilt over all nodes with the
rooms' δ (rooms touching each other get edges across). Instance ids are offset per room so that they stay distinct.
Each room is a region of the site (`regions.py`): its name, box, nodes and its rows of the two clouds (rooms are
written one after the other). A layout may also list `corridors` (`CorridorEntry`: a name, `T_building_corridor`,
`length_m`, `width_m`, `height_m`): plain hallways made by `corridor.py`, their points written into both clouds after
the rooms', each cut into regions <name>.0, <name>.1, ... of at most CORRIDOR_SEGMENT_M, without objects. The
building's up is stated (the rooms'). The building's distance field and each region's grid of points (`RegionGrids`)
are built here and stored. The output is one ordinary bundle (cadreg/site/bundle.py), loaded and served as any other.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..config import LocalizeConfig
from ..errors import ConfigError, InvalidFileError
from ..geometry import is_rigid, transform_points
from ..localize.gravity import map_floor_height
from ..localize.regions import region_grids
from ..localize.bbs import building_pyramid
from ..localize.score import DistanceField, building_field
from ..pointset import PointSet
from .bundle import Site
from .corridor import corridor_cloud
from .graph import ObjectNode, build_graph
from .regions import region_from_points, to_manifest

# Points of a dropped object within this of its box go with it (CAD boxes are tight; scans bleed a little).
DROP_MARGIN_M = 0.03
# Instance ids of room k are offset by k times this (a room holds far fewer objects).
INSTANCE_STRIDE = 1_000_000
# A corridor is cut into regions of at most this length (metres): a region's map holds its box and a halo around it.
CORRIDOR_SEGMENT_M = 6.0
# A corridor's points are this far apart when the rooms' bundles do not state their sampling (enhance's default).
CORRIDOR_SPACING_M = 0.015


class RoomEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9._-]+$",
                      description="prefix of the room's node ids")
    bundle: str = Field(min_length=1, description="room bundle directory, relative to the layout file")
    T_building_room: list[list[float]] = Field(description="4x4 room -> building transform, metres")
    drop_objects: list[str] = Field(default_factory=list, description="node ids (of the room's graph) to remove")
    move_objects: dict[str, list[list[float]]] = Field(
        default_factory=dict, description="node id (of the room's graph) -> 4x4 rigid transform, room frame, that "
                                          "carries the object (its node and points) to where this copy has it")

    @field_validator("T_building_room")
    @classmethod
    def _rigid(cls, value: list[list[float]]) -> list[list[float]]:
        return _checked_rigid(value)

    @field_validator("move_objects")
    @classmethod
    def _rigid_moves(cls, value: dict[str, list[list[float]]]) -> dict[str, list[list[float]]]:
        for node_id, T in value.items():
            try:
                _checked_rigid(T)
            except ValueError as exc:
                raise ValueError(f"{node_id}: {exc}") from None
        return value

    @model_validator(mode="after")
    def _dropped_or_moved(self) -> "RoomEntry":
        both = sorted(set(self.drop_objects) & set(self.move_objects))
        if both:
            raise ValueError(f"objects {both} are both dropped and moved")
        return self

    def moves(self) -> dict[str, np.ndarray]:
        """`move_objects` as (4, 4) float64 arrays."""
        return {node_id: np.asarray(T, dtype=np.float64) for node_id, T in self.move_objects.items()}


def _checked_rigid(value: list[list[float]]) -> list[list[float]]:
    """`value` when it is a finite 4x4 rigid transform; ValueError saying what it is not otherwise."""
    T = np.asarray(value, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("must be a finite 4x4 matrix")
    if not is_rigid(T, tol=1e-6):
        raise ValueError("must be a rigid transform (rotation and translation)")
    return value


class CorridorEntry(BaseModel):
    """A plain corridor (cadreg/site/corridor.py): its frame has x along it from 0 to length_m, y across it (±width_m
    / 2), z up from its floor to the top of its walls (height_m); `T_building_corridor` places that frame."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9._-]+$",
                      description="prefix of the corridor's region ids (<name>.<k>, one per CORRIDOR_SEGMENT_M)")
    T_building_corridor: list[list[float]] = Field(description="4x4 corridor -> building transform, metres")
    length_m: float = Field(gt=0, le=1000, description="length along the corridor's x, metres")
    width_m: float = Field(gt=0, le=50, description="clear width between its side walls, metres")
    height_m: float = Field(2.5, gt=0, le=20, description="height of its walls above its floor, metres")

    @field_validator("T_building_corridor")
    @classmethod
    def _rigid(cls, value: list[list[float]]) -> list[list[float]]:
        return _checked_rigid(value)


class Layout(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    site_id: str = Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    rooms: list[RoomEntry] = Field(min_length=1)
    corridors: list[CorridorEntry] = Field(default_factory=list)

    @model_validator(mode="after")
    def _distinct_places(self) -> "Layout":
        names = [r.name for r in self.rooms] + [c.name for c in self.corridors]
        if len(set(names)) != len(names):
            raise ValueError(f"room and corridor names must be distinct, got {names}")
        return self


def read_layout(path: str | Path) -> Layout:
    """The checked layout at `path`; InvalidFileError naming it for bad JSON, ConfigError for bad fields."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InvalidFileError(path, "no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidFileError(path, f"not a JSON layout: {exc}") from None
    try:
        return Layout.model_validate(doc)
    except ValidationError as exc:
        why = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"bad layout {path}: {why}") from None


# Rooms of one building must share their up within this (degrees): a fused room placed without levelling would
# otherwise be searched on its side.
MAX_UP_SPREAD_DEG = 5.0


@dataclass
class _Room:
    entry: RoomEntry
    site: Site
    T: np.ndarray


def _moved(cloud: PointSet, T: np.ndarray, instance_offset: int) -> PointSet:
    """`cloud` in the building frame, its object instances offset (−1 stays −1)."""
    instance = cloud.instance.astype(np.int64)
    instance = np.where(instance >= 0, instance + instance_offset, -1)
    normals = cloud.normals.astype(np.float64) @ T[:3, :3].T
    return replace(cloud, points=transform_points(T, cloud.points.astype(np.float64)), normals=normals,
                   instance=instance)


def inside_boxes(xyz: np.ndarray, nodes: list[ObjectNode], margin_m: float = DROP_MARGIN_M) -> np.ndarray:
    """(n,) bool: points (n, 3, room frame) inside any node's oriented box grown by `margin_m`."""
    inside = np.zeros(len(xyz), dtype=bool)
    for node in nodes:
        local = (xyz - node.box_center) @ node.box_R
        inside |= np.all(np.abs(local) <= node.box_extent / 2 + margin_m, axis=1)
    return inside


def _object_points(cloud: PointSet, node: ObjectNode, classes: list[str]) -> np.ndarray:
    """(n,) bool: the points of `cloud` (room frame) that are `node`'s object: of its class, inside its oriented
    box grown by DROP_MARGIN_M (`classes`: the room site's class names). The floor and wall under and behind the
    object are not."""
    k = classes.index(node.cls) if node.cls in classes else -2
    return inside_boxes(cloud.points.astype(np.float64), [node]) & (cloud.class_index == k)


def room_copy_cloud(cloud: PointSet, dropped: list[ObjectNode], moved: list[tuple[ObjectNode, np.ndarray]],
                    classes: list[str]) -> PointSet:
    """`cloud` (room frame) as a copy of the room has it: the `dropped` objects' points gone, each moved object's
    points carried by its transform ((node, (4, 4) room frame) pairs); the floor and wall under and behind both
    stay, as in a room where the object never stood there."""
    gone = np.zeros(len(cloud), dtype=bool)
    for node in dropped:
        gone |= _object_points(cloud, node, classes)
    if moved:
        points, normals = cloud.points.astype(np.float64), cloud.normals.astype(np.float64)
        for node, T in moved:
            mine = _object_points(cloud, node, classes) & ~gone
            points[mine] = transform_points(T, points[mine])
            normals[mine] = normals[mine] @ T[:3, :3].T
        cloud = replace(cloud, points=points, normals=normals)
    return cloud.take(~gone) if gone.any() else cloud


def _moved_node(node: ObjectNode, T: np.ndarray, name: str | None = None) -> ObjectNode:
    """`node` carried by the rigid transform T, its id prefixed by `name/` when given."""
    R, t = T[:3, :3], T[:3, 3]
    return replace(node, id=node.id if name is None else f"{name}/{node.id}", centroid=R @ node.centroid + t,
                   box_center=R @ node.box_center + t, box_R=R @ node.box_R)


def _floor_height(up: np.ndarray, *clouds: PointSet) -> float:
    """A room's floor height along the building's up (building frame), from its points and normals
    (`map_floor_height`)."""
    both = PointSet.concat([c for c in clouds if len(c)])
    return map_floor_height(both.points.astype(np.float64), both.normals.astype(np.float64), up)


def _building_up(rooms: list["_Room"]) -> np.ndarray:
    """(3,) the up all rooms share in the building frame: each room's own (`Site.up`; +z for a scan mesh that
    states none) turned by its T_building_room. ConfigError naming a room whose up lies more than MAX_UP_SPREAD_DEG
    from the others' mean: a fused room (its frame is its first camera's) placed without levelling."""
    z = np.array([0.0, 0.0, 1.0])
    ups = np.array([r.T[:3, :3] @ (z if r.site.up is None else r.site.up) for r in rooms])
    up = ups.mean(axis=0)
    up /= np.linalg.norm(up)
    off = np.degrees(np.arccos(np.clip(ups @ up, -1.0, 1.0)))
    k = int(np.argmax(off))
    if off[k] > MAX_UP_SPREAD_DEG:
        r = rooms[k]
        raise ConfigError(f"room {r.entry.name!r} ({r.entry.bundle}): its up lies {off[k]:.0f} degrees from the "
                          "building's; level it with its T_building_room (`cadreg site layout` does)")
    return up


def copy_changes(entry: RoomEntry,
                 nodes: list[ObjectNode]) -> tuple[list[ObjectNode], list[tuple[ObjectNode, np.ndarray]]]:
    """The room's nodes its copy `entry` drops, and those it moves with their transforms; ConfigError naming an id
    the room's graph (`nodes`) does not have."""
    by_id = {n.id: n for n in nodes}
    for what, ids in (("drop", entry.drop_objects), ("move", list(entry.move_objects))):
        unknown = sorted(set(ids) - set(by_id))
        if unknown:
            raise ConfigError(f"room {entry.name!r}: no object {unknown} to {what} in {entry.bundle} "
                              f"(has {sorted(by_id)})")
    return [by_id[i] for i in entry.drop_objects], [(by_id[i], T) for i, T in entry.moves().items()]


def corridor_segments(entry: CorridorEntry, up: np.ndarray, spacing_m: float) -> list[tuple[str, PointSet]]:
    """(region id, points in the building frame) of each segment of the corridor `entry`: its length cut into equal
    segments of at most CORRIDOR_SEGMENT_M, named <name>.0, <name>.1, ... (a long corridor as one region would give
    its region map every room along it). ConfigError when its up is not the building's `up`."""
    T = np.asarray(entry.T_building_corridor, dtype=np.float64)
    off = float(np.degrees(np.arccos(np.clip(T[:3, 2] @ up, -1.0, 1.0))))
    if off > MAX_UP_SPREAD_DEG:
        raise ConfigError(f"corridor {entry.name!r}: its up (z) lies {off:.0f} degrees from the building's")
    local = corridor_cloud(entry.length_m, entry.width_m, entry.height_m, spacing_m)
    n = max(1, math.ceil(entry.length_m / CORRIDOR_SEGMENT_M))
    segment = np.minimum((local.points[:, 0] / (entry.length_m / n)).astype(np.int64), n - 1)
    cloud = _moved(local, T, 0)
    return [(f"{entry.name}.{k}", cloud.take(segment == k)) for k in range(n)]


def compose_site(layout: Layout, root: str | Path, *, versioned: bool = True) -> Site:
    """The building site of `layout` (bundle paths relative to `root`). Rooms must share their classes and label
    maps (the same label set and class names): ConfigError otherwise, and for a dropped or moved id a room does not
    have. versioned False: its version and manifest are left for `Site.save` to make, for a caller that saves it at
    once (`site compose`: encoding and hashing a 100-room building's files took 1.7 s of its 33 s, and `save` does
    it)."""
    root = Path(root)
    # Each bundle read once, however many rooms copy it (the 100-room benchmark held 100 reads of one, 0.9 GB).
    bundles: dict[Path, Site] = {}
    rooms = []
    for e in layout.rooms:
        key = (root / e.bundle).resolve()
        if key not in bundles:
            bundles[key] = Site.load(root / e.bundle)  # (errors name the bundle as the layout does)
        rooms.append(_Room(e, bundles[key], np.asarray(e.T_building_room, dtype=np.float64)))
    first = rooms[0].site
    for r in rooms[1:]:
        if r.site.classes != first.classes or r.site.label_maps != first.label_maps:
            raise ConfigError(f"room {r.entry.name!r} ({r.entry.bundle}) has other classes or label maps than "
                              f"room {rooms[0].entry.name!r}: rooms of one site must share them")
    up = _building_up(rooms)
    maps, raws, nodes, regions = [], [], [], []

    def add_region(region_id: str, site_map: PointSet, site_raw: PointSet, node_ids: list[str]) -> None:
        """A region's points appended to each cloud after the regions before it, so the region is a slice of each
        (a corridor segment's one cloud goes into both)."""
        map_at, raw_at = sum(map(len, maps)), sum(map(len, raws))
        maps.append(site_map)
        raws.append(site_raw)
        clouds = [site_map] if site_raw is site_map else [site_map, site_raw]
        regions.append(region_from_points(region_id, [c.points for c in clouds], node_ids,
                                          (map_at, map_at + len(site_map)), (raw_at, raw_at + len(site_raw)),
                                          floor_m=_floor_height(up, *clouds)))

    for k, r in enumerate(rooms):
        dropped, moved = copy_changes(r.entry, r.site.graph.nodes)
        classes = list(r.site.classes)
        site_map = room_copy_cloud(r.site.map, dropped, moved, classes)
        site_raw = room_copy_cloud(r.site.raw, dropped, moved, classes)
        moves = r.entry.moves()
        room_nodes = [_moved_node(_moved_node(n, moves[n.id]) if n.id in moves else n, r.T, r.entry.name)
                      for n in r.site.graph.nodes if n.id not in r.entry.drop_objects]
        nodes += room_nodes
        add_region(r.entry.name, _moved(site_map, r.T, k * INSTANCE_STRIDE), _moved(site_raw, r.T, k * INSTANCE_STRIDE),
                   [n.id for n in room_nodes])
    # Corridors: their points in both clouds (a made surface is what the scan and the enhanced map would both hold),
    # one region per segment, no objects.
    spacing = float(first.manifest.get("build_config", {}).get("enhance", {}).get("sample_spacing_m",
                                                                                  CORRIDOR_SPACING_M))
    for entry in layout.corridors:
        for region_id, cloud in corridor_segments(entry, up, spacing):
            add_region(region_id, cloud, cloud, [])
    ids = [r.id for r in regions]
    if len(set(ids)) != len(ids):
        raise ConfigError(f"region ids repeat: {sorted({i for i in ids if ids.count(i) > 1})} (a room named as a "
                          "corridor's segment <name>.<k>)")
    manifest: dict[str, Any] = {
        key: first.manifest[key] for key in ("build_config",) if key in first.manifest
    }
    manifest["regions"] = to_manifest(regions)
    # The building states its up, the rooms' (+z for scan meshes that state none): estimated from the map's normals
    # (`gravity.map_up_axis`), a building's long corridor walls outnumber its floors, and its up came out as the
    # corridors' cross axis: every frame was searched on its side.
    manifest["up"] = [float(x) for x in up]
    manifest["inputs"] = {"composed": [{"name": r.entry.name, "bundle": r.entry.bundle, "site_id": r.site.site_id,
                                        "version": r.site.version, "T_building_room": r.entry.T_building_room,
                                        "drop_objects": list(r.entry.drop_objects)}
                                       | ({"move_objects": dict(r.entry.move_objects)} if r.entry.move_objects else {})
                                       for r in rooms]}
    if layout.corridors:
        manifest["inputs"]["corridors"] = [c.model_dump() for c in layout.corridors]
    site = Site(site_id=layout.site_id, version="", manifest=manifest, map=PointSet.concat(maps),
                raw=PointSet.concat(raws), graph=build_graph(nodes, first.edge_max_m), classes=list(first.classes),
                label_maps=dict(first.label_maps))
    maps.clear()  # the rooms' copies, now in the building's clouds (0.8 GB at 100 rooms)
    raws.clear()
    store_search_structures(site)
    if versioned:
        site.refresh_version()
    return site


def store_search_structures(site: Site) -> None:
    """Build a building's search structures from its regions and keep them with it, to be stored in its bundle
    (`site compose`, and `site build` of a building scanned in one piece: `partition.py`):
    - the distance field, built region by region (`building_field`): a worker maps it instead of rebuilding it
      over the whole building at every start;
    - with several regions, each one's grid of the points its localizer's region map holds (itself and a halo of
      its neighbours), with the default localizer settings: a worker reads a region's rows instead of gathering and
      gridding them (a one-room site's localizer builds its one map at start, from the whole cloud);
    - with several regions, the label-free search's pyramid over the field, with the default settings: a worker
      maps it instead of building its own (2 s and 95 MB each for 100 rooms)."""
    site.field_grid = building_field([np.concatenate([site.map.points[slice(*r.map_range)],
                                                      site.raw.points[slice(*r.raw_range)]]) for r in site.regions])
    site.pyramid = None
    if len(site.regions) > 1:
        lc = LocalizeConfig()
        site.region_grids = region_grids(site, site.regions, cloud=lc.refine.map_points, halo_m=lc.regions.halo_m)
        if site.up is not None:  # (a building states its up: `compose`, `partition.py`)
            field = DistanceField.from_grid(site.field_grid)
            site.pyramid = building_pyramid(field, site.up, lc.label_free).to_stored()
