"""Query views inside the rooms of a composed building, with the repeated-view oracle.

The building mesh is each room's labelled mesh copied into the building frame by its `T_building_room`, with the
faces of the room's dropped objects removed: a face goes when one of its vertices lies inside a dropped node's
oriented box grown by `compose.DROP_MARGIN_M` (the room bundle's node boxes, room frame) and is of the node's class
(the floor and the wall under and behind it stay); the rule compose applies to the map's points. Views are drawn as
follows: a room uniformly (seeded), a camera pose in it by `PoseSampler` on the room's own mesh (room frame, turned
level where that frame is not, the room's drops removed), then `T_building_camera = T_building_room · T_room_camera`
rendered on the whole building mesh (a neighbouring room can show over a low wall or through a gap) with the usual
noise, and judged by RenderConfig's valid-depth and visible-object thresholds.

**Oracle.** A view of room i is *repeated* in room j (j ≠ i, made from the same bundle) when the building rendered
at `T_building_room_j · T_room_camera` shows the same depth and labels as at `T_building_room_i · T_room_camera`:
both are cast noiselessly at a reduced resolution (OracleConfig, 160×120), and the agreement is the share of
pixels, among those valid (a surface within the sensor's range) in either cast, that are valid in both with depth
within `depth_tol_m` and the same label. The view is repeated in j when the agreement is ≥ `min_agreement`.
Copies with the same drops and the same surroundings agree to float rounding (≈ 1.0); a dropped chair or a
different neighbour over the wall takes several per cent of the pixels. Every other room of the same bundle is
cast (no pruning): the cost is (rooms of the bundle − 1) casts of 19 200 rays per view, depth and labels only
(~6–9 ms each on this machine at 10 rooms).

**Corridors.** A layout's corridors (`compose.CorridorEntry`) join the building mesh (`corridor_mesh`, the panels
compose samples into the map) and the places views are drawn in: a view's place is drawn uniformly among rooms and
corridors, and a corridor's view need not see an object. The oracle compares a corridor's view with the same
corridor-relative view in every other corridor of its size; what a bench makes of corridor views is its own
figure (`cadreg.bench`: a plain hallway shows nothing that places a view in it).

    OracleConfig                              resolution, depth tolerance, agreement threshold
    room_copy_mesh(mesh, dropped_nodes)       a room's mesh without its dropped objects (room frame)
    BuildingRoom, building_rooms(layout, ...) the layout's rooms (and corridors) with their meshes and transforms
    corridor_mesh(entry)                      a corridor's mesh (its frame)
    building_mesh(rooms)                      the whole building's LabelledMesh (building frame)
    RepeatOracle                              agreement / repeated_in of a room-relative view
    render_building_views(rooms, out_dir, n)  a recorded-frames folder of views + their BuildingView records
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field

from ..camera import CameraIntrinsics
from ..config import NoiseConfig, RenderConfig
from ..errors import ConfigError, InvalidFrame
from ..geometry import make_T, rotation_between, transform_points
from ..io.frames import FramesWriter
from ..labels import nyu40_label_map
from ..site.compose import CorridorEntry, Layout, copy_changes, inside_boxes
from ..site.corridor import corridor_panels, panel_grid
from ..site.graph import ObjectNode
from .mesh import LabelledMesh
from .noise import depth_range_m
from .poses import PoseSampler
from .raycast import MeshRenderer, camera_rig, pixel_rays
from .sequence import count_visible_objects, valid_share


# A corridor's mesh is a grid of cells this size (metres): flat panels need no finer, and the pose sampler reads
# the floor's height from its floor vertices.
CORRIDOR_MESH_STEP_M = 0.25


class OracleConfig(BaseModel):
    """The repeated-view oracle: a noiseless cast at width × height, depth tolerance (metres), agreement
    threshold (share of the pixels valid in either cast)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(160, gt=0)
    height: int = Field(120, gt=0)
    depth_tol_m: float = Field(0.02, gt=0)
    # Twins agree to float rounding (≥ 0.999 measured); the smallest thing that makes a view distinct, the bin
    # (0.43 × 0.36 m) seen whole from 2–3 m, covers ~1–3 % of the image: 0.97 calls views that differ by less
    # than about one small object "repeated".
    min_agreement: float = Field(0.97, gt=0, le=1)


def room_copy_mesh(mesh: LabelledMesh, dropped: list[ObjectNode],
                   moved: list[tuple[ObjectNode, np.ndarray]] = ()) -> LabelledMesh:
    """The room's mesh (room frame) as a copy of the room has it. An object's vertices are those of its node's class
    inside its box grown by `compose.DROP_MARGIN_M` (every vertex in the box for a mesh whose labels name no
    classes), the rule compose applies to the map's points. The faces touching a dropped object's vertices go; a
    moved object ((node, (4, 4) room frame) pairs) has its faces (those whose three vertices are its own) carried by
    its transform onto copies of their vertices, and the faces touching it go from where it stood. The floor and
    the wall the object stood on and against stay, as they would in a room without it there (cutting them out left
    a hole in the frames, no depth, that no sensor shows), and so do a door or a window the box reaches. Vertices
    are kept (unreferenced ones are harmless), so labels and instances keep their indices."""
    if not dropped and not moved:
        return mesh
    names = nyu40_label_map() if mesh.labels is not None and mesh.label_set == "nyu40" else None
    if names is None:
        vertex_class = None
    else:
        ids, inverse = np.unique(mesh.labels, return_inverse=True)
        vertex_class = np.array([names.get(int(i), "") for i in ids], dtype=object)[inverse.reshape(-1)]

    def object_vertices(node: ObjectNode) -> np.ndarray:
        inside = inside_boxes(mesh.vertices, [node])
        return inside if vertex_class is None else inside & (vertex_class == node.cls)

    gone = np.zeros(len(mesh.vertices), dtype=bool)
    for node in dropped:
        gone |= object_vertices(node)
    vertices, faces = [mesh.vertices], [mesh.faces[~np.any(gone[mesh.faces], axis=1)]]
    picks = []  # the source vertex of each appended one
    count = len(mesh.vertices)
    for node, T in moved:
        mine = object_vertices(node) & ~gone
        own = mesh.faces[np.all(mine[mesh.faces], axis=1)]
        used = np.unique(own)
        remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
        remap[used] = count + np.arange(len(used))
        vertices.append(transform_points(T, mesh.vertices[used]))
        faces.append(remap[own])
        picks.append(used)
        count += len(used)
        gone |= mine
        faces[0] = faces[0][~np.any(mine[faces[0]], axis=1)]
    src = np.concatenate([np.arange(len(mesh.vertices))] + picks)
    return LabelledMesh(np.concatenate(vertices), np.concatenate(faces), mesh.colors[src],
                        None if mesh.labels is None else mesh.labels[src], mesh.label_set,
                        None if mesh.instances is None else mesh.instances[src])


@dataclass
class BuildingRoom:
    """One room of the building: name, bundle (as in the layout), T_building_room (4, 4) room -> building,
    mesh : its copy's LabelledMesh in the room frame (dropped objects removed, moved ones moved). A corridor of the
    layout is one too (corridor True): its mesh is `corridor_mesh`'s in its own frame, its bundle names its size
    (corridors of one size are copies of each other, as rooms of one bundle are)."""

    name: str
    bundle: str
    T_building_room: np.ndarray
    mesh: LabelledMesh
    corridor: bool = False


def corridor_mesh(entry: CorridorEntry) -> LabelledMesh:
    """The corridor's panels (cadreg/site/corridor.py) as a labelled mesh, corridor frame: each a grid of
    CORRIDOR_MESH_STEP_M cells, its own vertices (a corner's label is its panel's), two triangles a cell."""
    vertices, faces, colors, labels = [], [], [], []
    count = 0
    for panel in corridor_panels(entry.length_m, entry.width_m, entry.height_m):
        grid, nu, nv = panel_grid(panel, CORRIDOR_MESH_STEP_M)
        index = count + np.arange(nu * nv).reshape(nu, nv)
        a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
        # two triangles a cell; their winding does not matter (the ray caster hits either side)
        faces.append(np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]))
        vertices.append(grid.reshape(-1, 3))
        colors.append(np.tile(np.array(panel.rgb, dtype=np.uint8), (nu * nv, 1)))
        labels.append(np.full(nu * nv, panel.label, dtype=np.uint16))
        count += nu * nv
    return LabelledMesh(np.concatenate(vertices), np.concatenate(faces), np.concatenate(colors),
                        np.concatenate(labels), "nyu40", np.full(count, -1, dtype=np.int32))


def corridor_bundle(entry: CorridorEntry) -> str:
    """What stands for a corridor's bundle: its size (the oracle compares a view with its copies in the corridors of
    the same size)."""
    return f"corridor {entry.length_m:.3f} x {entry.width_m:.3f} x {entry.height_m:.3f} m"


def building_rooms(layout: Layout, meshes: dict[str, LabelledMesh],
                   nodes: dict[str, list[ObjectNode]]) -> list[BuildingRoom]:
    """The rooms of `layout`, then its corridors; `meshes` and `nodes` give, per bundle string of the layout, the
    room's labelled mesh and its graph nodes (room frame). ConfigError for a dropped or moved id the bundle's graph
    does not have."""
    rooms = []
    for entry in layout.rooms:
        mesh = room_copy_mesh(meshes[entry.bundle], *copy_changes(entry, nodes[entry.bundle]))
        rooms.append(BuildingRoom(entry.name, entry.bundle, np.asarray(entry.T_building_room, dtype=np.float64), mesh))
    for c in layout.corridors:
        rooms.append(BuildingRoom(c.name, corridor_bundle(c), np.asarray(c.T_building_corridor, dtype=np.float64),
                                  corridor_mesh(c), corridor=True))
    return rooms


def building_mesh(rooms: list[BuildingRoom]) -> LabelledMesh:
    """All rooms' meshes in the building frame as one LabelledMesh; instance ids offset per room so that they stay
    distinct (−1 stays −1). Rooms that carry labels must share a label set; a room without (a Replica mesh, a
    fused room) reads label 0, unlabelled, and no instance, in a building whose other rooms carry them."""
    labelled = [r for r in rooms if r.mesh.labels is not None]
    label_sets = {r.mesh.label_set for r in labelled} or {rooms[0].mesh.label_set}
    if len(label_sets) > 1:
        raise ConfigError(f"rooms of one building must share a label set, got {sorted(label_sets)}")
    vertices, faces, colors, labels, instances = [], [], [], [], []
    v_offset = i_offset = 0
    for r in rooms:
        m = r.mesh
        vertices.append(transform_points(r.T_building_room, m.vertices))
        faces.append(m.faces.astype(np.int64) + v_offset)
        colors.append(m.colors)
        if labelled:
            labels.append(m.labels if m.labels is not None else np.zeros(len(m.vertices), dtype=np.uint16))
        if m.instances is not None:
            instances.append(np.where(m.instances >= 0, m.instances + i_offset, -1))
            i_offset += m.n_instances
        elif labelled:
            instances.append(np.full(len(m.vertices), -1, dtype=np.int32))
        v_offset += len(m.vertices)
    return LabelledMesh(
        np.concatenate(vertices), np.concatenate(faces), np.concatenate(colors),
        np.concatenate(labels) if labels else None, label_sets.pop(),
        np.concatenate(instances) if len(instances) == len(rooms) else None,
    )


@dataclass
class OracleCast:
    """A noiseless cast for the oracle: depth_m (H, W) float32 z-depth in metres, inf on misses; labels (H, W)
    uint16 label of the hit face's nearest vertex (0 on misses), or None for a mesh without labels."""

    depth_m: np.ndarray
    labels: np.ndarray | None


def view_agreement(a: OracleCast, b: OracleCast, *, depth_tol_m: float, min_depth_m: float,
                   max_depth_m: float) -> float:
    """Share of the pixels valid in either view (a surface in [min_depth_m, max_depth_m]) that are valid in both
    with |depth difference| ≤ depth_tol_m and equal labels (labels ignored when the views carry none); 0 when no
    pixel is valid."""
    va = np.isfinite(a.depth_m) & (a.depth_m >= min_depth_m) & (a.depth_m <= max_depth_m)
    vb = np.isfinite(b.depth_m) & (b.depth_m >= min_depth_m) & (b.depth_m <= max_depth_m)
    either = va | vb
    if not either.any():
        return 0.0
    both = va & vb
    same = np.zeros_like(both)
    same[both] = np.abs(a.depth_m[both] - b.depth_m[both]) <= depth_tol_m
    if a.labels is not None and b.labels is not None:
        same &= a.labels == b.labels
    return float(same.sum() / either.sum())


class RepeatOracle:
    """Which other rooms show a room-relative view as it is seen in its own room (module docstring)."""

    def __init__(self, renderer: MeshRenderer, rooms: list[BuildingRoom], depth_intr: CameraIntrinsics,
                 T_color_depth: np.ndarray, *, config: OracleConfig = OracleConfig(),
                 noise: NoiseConfig = NoiseConfig()) -> None:
        self.renderer = renderer
        self.rooms = rooms
        self.intr = depth_intr.scaled_to(config.width, config.height)
        self.T_color_depth = T_color_depth
        self.config = config
        self.noise = noise
        self._rays = pixel_rays(self.intr).reshape(-1, 3)

    def cast(self, room: int, T_room_camera: np.ndarray) -> OracleCast:
        """Noiseless low-resolution depth-camera cast of the building at room `room`'s copy of the view: depth and
        labels only (the renderer's full cast also shades colour and incidence, twice the time)."""
        T_building_depth = self.rooms[room].T_building_room @ T_room_camera @ self.T_color_depth
        dirs = self._rays @ T_building_depth[:3, :3].T.astype(np.float32)
        origin = np.broadcast_to(T_building_depth[:3, 3].astype(np.float32), dirs.shape)
        ans = self.renderer.scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, dirs], axis=1)))
        shape = (self.intr.height, self.intr.width)
        depth = ans["t_hit"].numpy()  # rays have camera-z 1: the hit distance is the depth
        mesh = self.renderer.mesh
        if mesh.labels is None:
            return OracleCast(depth.reshape(shape), None)
        hit = np.isfinite(depth)
        tri = mesh.faces[ans["primitive_ids"].numpy()[hit].astype(np.int64)]
        uv = ans["primitive_uvs"].numpy()[hit]
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        labels = np.zeros(len(depth), dtype=np.uint16)
        labels[hit] = mesh.labels[tri[np.arange(len(tri)), np.argmax(w, axis=1)]]
        return OracleCast(depth.reshape(shape), labels.reshape(shape))

    def agreements(self, room: int, T_room_camera: np.ndarray) -> dict[str, float]:
        """Agreement of the view with its copy in every other room of the same bundle, by room name."""
        reference = self.cast(room, T_room_camera)
        out = {}
        for j, other in enumerate(self.rooms):
            if j == room or other.bundle != self.rooms[room].bundle:
                continue
            out[other.name] = view_agreement(reference, self.cast(j, T_room_camera),
                                             depth_tol_m=self.config.depth_tol_m,
                                             min_depth_m=self.noise.min_depth_m, max_depth_m=self.noise.max_depth_m)
        return out

    def repeated_in(self, room: int, T_room_camera: np.ndarray) -> list[str]:
        """Names of the rooms that repeat the view (agreement ≥ min_agreement), in layout order."""
        return [name for name, a in self.agreements(room, T_room_camera).items() if a >= self.config.min_agreement]


@dataclass
class BuildingView:
    """One rendered view: index in the frames folder, room name, T_room_camera and T_building_camera (4, 4,
    colour camera -> room / building), repeated_in (rooms that repeat it), agreement (by room of the same bundle),
    corridor (the view was taken in a corridor: `room` names it, T_room_camera is in its frame)."""

    index: int
    room: str
    T_room_camera: np.ndarray
    T_building_camera: np.ndarray
    repeated_in: list[str]
    agreement: dict[str, float]
    corridor: bool = False

    def to_dict(self) -> dict:
        """The views.json record."""
        return {"index": self.index, "room": self.room, "corridor": self.corridor, "repeated": bool(self.repeated_in),
                "repeated_in": list(self.repeated_in), "T_room_camera": self.T_room_camera.tolist(),
                "agreement": {k: round(v, 4) for k, v in self.agreement.items()}}


class _RoomSamplers:
    """PoseSamplers on room meshes, built when first needed; the last few are kept (a renderer per room of a large
    building would hold every room's ray-casting structure). A room whose own frame is not level (a fused room: its
    frame is its first camera's, and its `T_building_room` levels it) is sampled on its mesh turned level, as
    `PoseSampler` takes z for up: `sample(room, rng)` gives T_room_camera either way."""

    def __init__(self, rooms: list[BuildingRoom], config: RenderConfig, keep: int = 8) -> None:
        self.rooms, self.config, self.keep = rooms, config, keep
        self._cache: OrderedDict[int, tuple[PoseSampler, np.ndarray]] = OrderedDict()

    def sample(self, room: int, rng: np.random.Generator) -> np.ndarray | None:
        """A T_room_camera drawn by the room's sampler (`PoseSampler.sample`), or None when it found no position."""
        sampler, T_room_level = self._sampler(room)
        T_level_camera = sampler.sample(rng)
        return None if T_level_camera is None else T_room_level @ T_level_camera

    def _sampler(self, room: int) -> tuple[PoseSampler, np.ndarray]:
        if room not in self._cache:
            entry = self.rooms[room]
            R_level = rotation_between(entry.T_building_room[:3, :3].T @ [0.0, 0.0, 1.0], np.array([0.0, 0.0, 1.0]))
            mesh = entry.mesh
            if not np.allclose(R_level, np.eye(3), atol=1e-9):
                mesh = dataclasses.replace(mesh, vertices=mesh.vertices @ R_level.T)
            self._cache[room] = (PoseSampler(MeshRenderer(mesh), self.config), make_T(R_level.T, np.zeros(3)))
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        self._cache.move_to_end(room)
        return self._cache[room]


def render_building_views(
    rooms: list[BuildingRoom],
    out_dir: str | Path,
    n: int,
    *,
    seed: int = 0,
    config: RenderConfig = RenderConfig(),
    noise: NoiseConfig | None = NoiseConfig(),
    oracle: OracleConfig = OracleConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> list[BuildingView]:
    """Render `n` views inside the rooms into `out_dir` (DESIGN §4 layout, pose/<i>.txt = T_building_camera) and
    return their records (the caller writes views.json). Deterministic for a seed; noise None = noiseless."""
    if n <= 0:
        raise ConfigError(f"number of frames must be positive, got {n}")
    mesh = building_mesh(rooms)
    if config.min_visible_objects > 0 and mesh.labels is None:
        raise ConfigError("min_visible_objects > 0 needs room meshes with per-vertex labels (or set it to 0)")
    depth_intr, color_intr, T_color_depth = camera_rig(config)
    renderer = MeshRenderer(mesh)
    repeat = RepeatOracle(renderer, rooms, depth_intr, T_color_depth, config=oracle, noise=noise or NoiseConfig())
    samplers = _RoomSamplers(rooms, config)
    writer = FramesWriter(out_dir, depth_intr, color_intr, T_color_depth, depth_scale=1000.0,
                          label_set=mesh.label_set, color_format=config.color_format,
                          depth_range_m=depth_range_m(noise))
    rng = np.random.default_rng(seed)
    out: list[BuildingView] = []
    while len(out) < n:
        i = len(out)
        room = int(rng.integers(len(rooms)))
        T_room_camera, frame = _draw_view(samplers, room, renderer, rng, config, noise, i)
        T_building_camera = rooms[room].T_building_room @ T_room_camera
        writer.write(i, frame, T_building_camera)
        agreement = repeat.agreements(room, T_room_camera)
        repeated = [name for name, a in agreement.items() if a >= oracle.min_agreement]
        out.append(BuildingView(i, rooms[room].name, T_room_camera, T_building_camera, repeated, agreement,
                                rooms[room].corridor))
        if progress is not None:
            progress(len(out), n)
    return out


def _draw_view(samplers: _RoomSamplers, room_index: int, renderer: MeshRenderer, rng: np.random.Generator,
               config: RenderConfig, noise: NoiseConfig | None, index: int):
    """(T_room_camera, Frame) of the first pose sampled in room `room_index` whose building view passes the
    config's valid-depth and visible-object thresholds; ConfigError after `max_attempts_per_frame` failures."""
    room = samplers.rooms[room_index]
    depth_intr, color_intr, T_color_depth = camera_rig(config)  # cheap: a few dataclasses
    min_objects = 0 if room.corridor else config.min_visible_objects  # a corridor holds none
    min_z = noise.min_depth_m if noise is not None else 0.0
    max_z = noise.max_depth_m if noise is not None else np.inf
    for _ in range(config.max_attempts_per_frame):
        T_room_camera = samplers.sample(room_index, rng)
        if T_room_camera is None:
            raise ConfigError(f"no camera position inside room {room.name!r} passes the height/clearance checks")
        T_building_camera = room.T_building_room @ T_room_camera
        dview = renderer.cast(depth_intr, T_building_camera @ T_color_depth, with_color=True)
        z = dview.depth_m
        if (valid_share(z, min_z, max_z) < config.min_valid_fraction
                or count_visible_objects(dview, config.min_object_fraction) < min_objects):
            continue
        try:
            frame, _, _ = renderer.render_frame(T_building_camera, depth_intr, color_intr, T_color_depth, rng=rng,
                                                noise=noise, frame_id=str(index), depth_view=dview)
        except InvalidFrame:  # noise left no depth: draw again
            continue
        return T_room_camera, frame
    raise ConfigError(f"{config.max_attempts_per_frame} sampled views in room {room.name!r} failed (valid depth >= "
                      f"{config.min_valid_fraction}, >= {config.min_visible_objects} visible objects): relax the "
                      "render settings")
