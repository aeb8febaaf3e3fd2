"""Generate a building layout (LAYOUT.json for `cadreg site compose`) from room bundles: a benchmark building.

Rooms r000, r001, ... fill a near-square grid (ceil(sqrt(N)) columns, row by row). Room k is a copy of source
bundle k mod len(sources) (cycled, so every source appears as evenly as the count allows), levelled (a bundle that
states an up other than +z, a fused room, is turned so that its up is +z), turned about z by a random multiple of
90° (with `any_turn`, by a random angle) about the centre of its footprint (the xy box of the bundle's levelled raw
points), and placed so that, after turning (a footprint turned by another angle counts by the box about it):

- within a row, each room's footprint starts exactly `gap_m` after its left neighbour's ends (x);
- each row's band (the tallest footprint of the row) starts exactly `gap_m` after the band of the row below (y);
  a room lower than its row's band sits at the band's bottom, so its gap to the row above is larger.

Footprints therefore never overlap and are at least `gap_m` apart. Each CAD-sourced object (graph node source ==
"cad") of each copy is dropped with probability `drop_prob`, and each one a copy keeps is moved with probability
`move_prob`: turned about the vertical through its box centre by up to `move_max_deg` and shifted horizontally by
up to `move_max_m`, redrawn (at most MOVE_TRIES times, else left) until its box stays inside the room's footprint.
One seeded generator draws, per room in order, the turn and then the drops (CAD node ids in sorted order),
then, for every room in order again, the moves: the same seed gives the same layout, and the same turns and drops
whatever `move_prob`.

With `storeys` > 1 the rooms are shared among that many storeys, the first ⌈N / storeys⌉ on the ground storey and
so on, each storey laid out as above on its own grid (of ⌈N / storeys⌉ rooms) and raised by `storey_height_m` plus
the spread of the sources' floor heights (each room keeps its own floor, and every floor of a storey then lies at
least `storey_height_m` above every floor of the storey below): seen from above, its rooms overlap those of the
storey below (a room turned as the one under it stands straight above it).

With `corridor_m` > 0 the rows pair up about corridors instead (`compose.CorridorEntry`, cadreg/site/corridor.py):
corridor c<k> runs along x between rows 2k and 2k + 1, its clear width `corridor_m` between walls CORRIDOR_WALL_M
thick standing against the footprints, from x = 0 to the far end of the longer row; the rooms of row 2k sit at the
top of their band and those of row 2k + 1 at the bottom of theirs, so every room backs onto a corridor, and the
seed's draws are those of the layout without corridors.

    RoomSource.from_site(name, bundle, site)   what the generator needs of a room bundle
    generate_layout(sources, config) -> Layout the layout (cadreg/site/compose.py's model)
    placed_footprint(source, T_building_room)  (2, 2) [min, max] xy of a placed room, building frame
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..errors import ConfigError
from ..geometry import rotation_between
from ..localize.gravity import map_floor_height
from .bundle import Site
from .compose import CorridorEntry, Layout, RoomEntry


# A moved object's draw is repeated at most this many times until its box stays inside the room's footprint.
MOVE_TRIES = 8
# A corridor's walls stand this far (metres) from the footprints of the rooms along it: a wall's thickness, so that
# its face is not in the plane of the room's own scanned wall.
CORRIDOR_WALL_M = 0.1


class LayoutConfig(BaseModel):
    """How the building is laid out: room count, gap between footprints (metres), drop and move probabilities and
    how far a move goes, seed."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    site_id: str = Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    rooms: int = Field(gt=0, le=10_000, description="number of rooms")
    gap_m: float = Field(0.6, ge=0, description="gap between neighbouring footprints, metres")
    drop_prob: float = Field(0.35, ge=0, le=1, description="probability that a CAD object of a copy is dropped")
    move_prob: float = Field(0.0, ge=0, le=1, description="probability that a CAD object a copy keeps is moved")
    move_max_m: float = Field(0.5, ge=0, description="largest horizontal shift of a moved object's box centre, metres")
    move_max_deg: float = Field(45.0, ge=0, le=180, description="largest turn of a moved object about the vertical, "
                                "degrees")
    corridor_m: float = Field(0.0, ge=0, le=10, description="clear width of a corridor between each pair of rows, "
                              "metres; 0: no corridors")
    corridor_height_m: float = Field(2.5, gt=0, le=10, description="height of the corridors' walls, metres")
    storeys: int = Field(1, ge=1, le=100, description="storeys the rooms are shared among, each laid out on its "
                         "own grid above the one below")
    storey_height_m: float = Field(3.0, ge=2.0, le=20, description="floor-to-floor height of a storey, metres "
                                   "(plus the spread of the rooms' own floor heights)")
    any_turn: bool = Field(False, description="turn each room by an angle drawn in [0°, 360°), not by a multiple of "
                           "90°: rooms that do not share their walls' directions")
    building_turn_deg: float = Field(0.0, ge=-360, le=360, description="turn the whole building about z (through "
                                     "the origin) by this, degrees: a building whose walls are not along x and y")
    seed: int = Field(0, ge=0)


@dataclass(frozen=True)
class RoomSource:
    """A room bundle to copy.

    name : the source's name (for reports); bundle : the path written into the layout (relative to the layout file
    or absolute); footprint_min, footprint_max : (2,) float64 xy box of the room's raw points, levelled room frame,
    metres; cad_ids : ids of the graph nodes with source "cad", sorted. R_level : (3, 3) rotation taking the
    room's up (`Site.up`: a fused room's frame is its first camera's) onto +z; identity for a z-up room.
    cad_corners : per CAD id, (8, 2) xy of its box's corners, levelled room frame (what a move must keep inside the
    footprint); empty when the source's objects are not to be moved. floor_z : height of its floor, levelled room
    frame (a corridor along it shares it).
    """

    name: str
    bundle: str
    footprint_min: np.ndarray
    footprint_max: np.ndarray
    cad_ids: tuple[str, ...]
    R_level: np.ndarray = field(default_factory=lambda: np.eye(3))
    cad_corners: tuple[np.ndarray, ...] = ()
    floor_z: float = 0.0

    @classmethod
    def from_site(cls, name: str, bundle: str, site: Site) -> "RoomSource":
        R_level = np.eye(3) if site.up is None else rotation_between(site.up, np.array([0.0, 0.0, 1.0]))
        xy = (site.raw.points.astype(np.float64) @ R_level.T)[:, :2]
        if len(xy) == 0:
            raise ConfigError(f"room bundle {bundle!r} has no raw points: no footprint to place")
        cad = sorted((n for n in site.graph.nodes if n.source == "cad"), key=lambda n: n.id)
        signs = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])
        corners = tuple(((n.box_center + (signs * n.box_extent) @ n.box_R.T) @ R_level.T)[:, :2] for n in cad)
        floor = map_floor_height(site.raw.points.astype(np.float64) @ R_level.T,
                                 site.raw.normals.astype(np.float64) @ R_level.T, np.array([0.0, 0.0, 1.0]))
        return cls(name, bundle, xy.min(axis=0), xy.max(axis=0), tuple(n.id for n in cad), R_level, corners, floor)

    @property
    def T_level(self) -> np.ndarray:
        """(4, 4) the levelling rotation as a transform (room frame -> levelled room frame)."""
        T = np.eye(4)
        T[:3, :3] = self.R_level
        return T

    @property
    def center(self) -> np.ndarray:
        """(2,) centre of the footprint, room frame."""
        return (self.footprint_min + self.footprint_max) / 2.0

    @property
    def size(self) -> np.ndarray:
        """(2,) width (x) and depth (y) of the footprint, metres."""
        return self.footprint_max - self.footprint_min


def grid_shape(n_rooms: int) -> tuple[int, int]:
    """(columns, rows) of the near-square grid of `n_rooms`: ceil(sqrt(n)) columns, as many rows as needed."""
    cols = max(1, math.ceil(math.sqrt(n_rooms)))
    return cols, math.ceil(n_rooms / cols)


def quarter_turn(k: int) -> np.ndarray:
    """(3, 3) rotation about z by k·90°, with exact 0 / ±1 entries (integers in, so no -0.0 reaches a layout)."""
    return _about_z(*[(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4])


def turn_about_z(rad: float) -> np.ndarray:
    """(3, 3) rotation about z by `rad` radians."""
    return _about_z(math.cos(rad), math.sin(rad))


def _about_z(c: float, s: float) -> np.ndarray:
    """(3, 3) rotation about z with cosine c and sine s."""
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def turned_size(source: RoomSource, R: np.ndarray) -> np.ndarray:
    """(2,) size of the box about the footprint turned by R ((3, 3) about z): width and depth swap, exactly, on odd
    quarter turns."""
    return np.abs(R[:2, :2]) @ source.size


def place_room(source: RoomSource, R: np.ndarray, corner_xy: np.ndarray) -> np.ndarray:
    """(4, 4) T_building_room levelling the room (its up onto +z), turning it by R ((3, 3) about z) about its
    footprint centre and putting the turned footprint's box's min corner at `corner_xy` (building frame, metres)."""
    half = turned_size(source, R) / 2.0
    T = np.eye(4)
    T[:3, :3] = R
    # p_building = R (p_level - c) + corner + half: the footprint centre c lands on the turned box's centre.
    T[:2, 3] = corner_xy + half - R[:2, :2] @ source.center
    return T @ source.T_level


def placed_footprint(source: RoomSource, T_building_room: np.ndarray) -> np.ndarray:
    """(2, 2) [[xmin, ymin], [xmax, ymax]] of the room's footprint corners mapped into the building frame."""
    lo, hi = source.footprint_min, source.footprint_max
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]])
    T_place = T_building_room @ source.T_level.T  # the footprint lies in the levelled room frame
    xy = corners @ T_place[:2, :2].T + T_place[:2, 3]
    return np.stack([xy.min(axis=0), xy.max(axis=0)])


def draw_room(source: RoomSource, rng: np.random.Generator, drop_prob: float,
              any_turn: bool = False) -> tuple[np.ndarray, list[str]]:
    """(turn (3, 3) about z, dropped CAD node ids) of one copy, drawn in that order from `rng`: a quarter turn, or
    with `any_turn` an angle in [0, 2π)."""
    R = turn_about_z(float(rng.uniform(0.0, 2.0 * math.pi))) if any_turn else quarter_turn(int(rng.integers(4)))
    draws = rng.random(len(source.cad_ids))
    return R, [nid for nid, u in zip(source.cad_ids, draws) if u < drop_prob]


def draw_moves(source: RoomSource, kept: list[str], rng: np.random.Generator,
               config: LayoutConfig) -> dict[str, list[list[float]]]:
    """The moves of one copy's kept CAD objects (`kept`, in the order of `source.cad_ids`), drawn from `rng`: each
    with probability config.move_prob, a turn about the vertical through its box centre and a horizontal shift, drawn
    again until its box's corners stay inside the footprint (at most MOVE_TRIES draws, else it stays). Returns
    {node id: 4x4 room-frame transform} (`RoomEntry.move_objects`)."""
    if config.move_prob <= 0 or not kept:
        return {}
    if len(source.cad_corners) != len(source.cad_ids):
        raise ConfigError(f"room source {source.name!r} gives no object boxes to move")
    corners = dict(zip(source.cad_ids, source.cad_corners))
    moves = {}
    for node_id in kept:
        if rng.random() >= config.move_prob:
            continue
        xy = corners[node_id]
        centre = (xy.min(axis=0) + xy.max(axis=0)) / 2.0
        for _ in range(MOVE_TRIES):
            yaw = np.radians(rng.uniform(-config.move_max_deg, config.move_max_deg))
            reach, heading = config.move_max_m * np.sqrt(rng.random()), rng.uniform(0.0, 2.0 * np.pi)
            shift = reach * np.array([np.cos(heading), np.sin(heading)])  # uniform over the disc
            R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            moved = (xy - centre) @ R.T + centre + shift
            if np.all(moved >= source.footprint_min) and np.all(moved <= source.footprint_max):
                M = np.eye(4)  # levelled room frame: about the vertical through the box centre, then shifted
                M[:2, :2], M[:2, 3] = R, centre + shift - R @ centre
                moves[node_id] = (source.T_level.T @ M @ source.T_level).tolist()
                break
    return moves


def grid_corners(sizes: list[np.ndarray], cols: int, gap_m: float,
                 corridor_gap_m: float | None = None) -> list[np.ndarray]:
    """(2,) min corner of each turned footprint of `sizes` ((2,) each), row by row, `cols` per row. With
    `corridor_gap_m`, rows pair up about a corridor: an odd row's band starts corridor_gap_m after the band below,
    and the rooms of an even row sit at the top of their band (both rows touch the corridor's walls)."""
    corners: list[np.ndarray] = []
    y = 0.0
    for row, row_start in enumerate(range(0, len(sizes), cols)):
        members = sizes[row_start:row_start + cols]
        band = max(float(s[1]) for s in members)
        if corridor_gap_m is not None and row % 2 == 1:
            y += corridor_gap_m - gap_m
        top = corridor_gap_m is not None and row % 2 == 0
        x = 0.0
        for size in members:
            corners.append(np.array([x, y + band - float(size[1]) if top else y]))
            x += float(size[0]) + gap_m
        y += band + gap_m
    return corners


def grid_corridors(sources: list[RoomSource], sizes: list[np.ndarray], corners: list[np.ndarray], cols: int,
                   config: LayoutConfig) -> list[CorridorEntry]:
    """The corridors of a grid laid out by `grid_corners` with corridors: corridor k runs along x between rows 2k
    and 2k + 1 (the last one alone when the row count is odd), from x = 0 to the far end of the longer row, its
    clear width config.corridor_m inside walls CORRIDOR_WALL_M thick, its floor at the median floor height of
    those rooms."""
    out = []
    for k, row_start in enumerate(range(0, len(sizes), 2 * cols)):
        lower = range(row_start, min(row_start + cols, len(sizes)))
        both = range(row_start, min(row_start + 2 * cols, len(sizes)))
        y0 = max(float(corners[i][1] + sizes[i][1]) for i in lower) + CORRIDOR_WALL_M
        length = max(float(corners[i][0] + sizes[i][0]) for i in both)
        floor = float(np.median([sources[i].floor_z for i in both]))
        T = np.eye(4)
        T[:3, 3] = [0.0, y0 + config.corridor_m / 2.0, floor]
        out.append(CorridorEntry(name=f"c{k:02d}", T_building_corridor=T.tolist(), length_m=length,
                                 width_m=config.corridor_m, height_m=config.corridor_height_m))
    return out


def generate_layout(sources: list[RoomSource], config: LayoutConfig) -> Layout:
    """The layout of `config.rooms` copies of `sources` (cycled) on a grid, or on one grid a storey (the first
    ⌈rooms / storeys⌉ rooms on the ground storey, and so on, each storey raised by storey_height_m and the spread of
    the rooms' floors; seen from above, its rooms overlap those of the storey below), the whole turned by
    building_turn_deg; deterministic per `config.seed` (the turns, drops and moves are those of the layout on one
    storey)."""
    if not sources:
        raise ConfigError("a layout needs at least one room bundle")
    rng = np.random.default_rng(config.seed)
    picked = [sources[k % len(sources)] for k in range(config.rooms)]
    draws = [draw_room(s, rng, config.drop_prob, config.any_turn) for s in picked]
    # after every room's turn and drops: the same seed turns and drops the same whatever move_prob
    moves = [draw_moves(s, [i for i in s.cad_ids if i not in dropped], rng, config)
             for s, (_, dropped) in zip(picked, draws)]
    sizes = [turned_size(s, R) for s, (R, _) in zip(picked, draws)]
    corridor_gap = config.corridor_m + 2.0 * CORRIDOR_WALL_M if config.corridor_m > 0 else None
    per_storey = math.ceil(config.rooms / config.storeys)
    cols, _ = grid_shape(per_storey)
    # Rooms keep their floors (a Replica office's lies 1.19 m under scene0470's): raised by the storey height alone,
    # a storey's lowest floor lay under the storey below's camera heights, and its rooms counted as one storey with
    # those below (`regions.Storeys`: floors 1.19, 1.81 and 1.19 m apart, each a step).
    floors = [s.floor_z for s in picked]
    storey_rise = config.storey_height_m + max(floors) - min(floors)
    rooms, corridors = [], []
    for storey, first in enumerate(range(0, config.rooms, per_storey)):
        members = range(first, min(first + per_storey, config.rooms))
        corners = grid_corners([sizes[k] for k in members], cols, config.gap_m, corridor_gap)
        raise_T = np.eye(4)
        raise_T[2, 3] = storey * storey_rise
        if config.building_turn_deg:
            raise_T[:3, :3] = turn_about_z(math.radians(config.building_turn_deg))
        for k, corner in zip(members, corners):
            (R, dropped), s = draws[k], picked[k]
            rooms.append(RoomEntry(name=f"r{k:03d}", bundle=s.bundle,
                                   T_building_room=(raise_T @ place_room(s, R, corner)).tolist(),
                                   drop_objects=dropped, move_objects=moves[k]))
        if corridor_gap is not None:
            for c in grid_corridors([picked[k] for k in members], [sizes[k] for k in members], corners, cols, config):
                name = c.name if config.storeys == 1 else f"s{storey}{c.name}"
                T = (raise_T @ np.array(c.T_building_corridor)).tolist()
                corridors.append(c.model_copy(update={"name": name, "T_building_corridor": T}))
    return Layout(site_id=config.site_id, rooms=rooms, corridors=corridors)
