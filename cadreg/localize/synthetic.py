"""Seeded synthetic scenes for tests: a textured box room with box-shaped labelled objects, the real `Site` built
from it (map points sampled on its surfaces, one cluster node per object, the semantic graph), and frames rendered
from it at known poses (Open3D ray casting).

Labels follow NYU40 ids: 1 wall, 2 floor, 5 chair, 7 table, 39 otherfurniture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import CameraIntrinsics
from ..config import SiteBuildConfig
from ..frame import Frame
from ..geometry import invert_T, make_T
from ..pointset import PointSet
from ..site.bundle import Site
from ..site.graph import ObjectNode, build_graph

CLASSES = ["chair", "otherfurniture", "table"]
_LABEL_OF_CLASS = {"chair": 5, "otherfurniture": 39, "table": 7}


@dataclass
class SyntheticScene:
    """The room as triangles plus per-triangle label and colour; `site` is its map."""

    vertices: np.ndarray  # (v, 3) float64, map frame
    triangles: np.ndarray  # (t, 3) int32
    tri_label: np.ndarray  # (t,) int NYU40 label
    tri_color: np.ndarray  # (t, 3) float base colour in [0, 1]
    site: Site


def texture(points: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Procedural colour (n, 3) in [0, 1]: the base colour modulated by a 3-D checker of 0.25 m cells."""
    checker = (np.floor(points / 0.25).astype(np.int64).sum(axis=1) % 2).astype(float)
    return np.clip(base * (0.65 + 0.35 * checker[:, None]), 0.0, 1.0)


def make_scene(seed: int = 0, *, size_m: tuple[float, float, float] = (5.0, 4.0, 2.6), n_objects: int = 7,
               map_points: int = 120_000) -> SyntheticScene:
    """A room (floor, four walls) with `n_objects` boxes of random class, size, position and yaw."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    W, D, H = size_m
    meshes: list[tuple[o3d.geometry.TriangleMesh, int, np.ndarray, int]] = []  # mesh, label, colour, object

    def box(w, d, h, T, label, colour, instance=-1):
        m = o3d.geometry.TriangleMesh.create_box(w, d, h)
        m.translate((-w / 2, -d / 2, -h / 2))
        m.transform(T)
        meshes.append((m, label, np.asarray(colour, float), instance))

    # Thin slabs make a closed room whose inner faces are the walls.
    box(W, D, 0.1, make_T(t=[W / 2, D / 2, -0.05]), 2, [0.55, 0.5, 0.45])
    box(W, 0.1, H, make_T(t=[W / 2, -0.05, H / 2]), 1, [0.8, 0.8, 0.75])
    box(W, 0.1, H, make_T(t=[W / 2, D + 0.05, H / 2]), 1, [0.75, 0.8, 0.85])
    box(0.1, D, H, make_T(t=[-0.05, D / 2, H / 2]), 1, [0.85, 0.75, 0.7])
    box(0.1, D, H, make_T(t=[W + 0.05, D / 2, H / 2]), 1, [0.7, 0.85, 0.7])
    objects: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []  # class, centre, extent, R
    placed: list[np.ndarray] = []
    while len(objects) < n_objects:
        cls = CLASSES[int(rng.integers(len(CLASSES)))]
        w, d = rng.uniform(0.4, 0.9, size=2)
        h = {"chair": rng.uniform(0.8, 1.0), "table": rng.uniform(0.7, 0.8), "otherfurniture": rng.uniform(0.3, 1.2)}[cls]
        c = np.array([rng.uniform(0.6, W - 0.6), rng.uniform(0.6, D - 0.6), h / 2])
        if any(np.linalg.norm(c[:2] - p[:2]) < 1.0 for p in placed):
            continue
        yaw = rng.uniform(0, np.pi)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        box(w, d, h, make_T(R, c), _LABEL_OF_CLASS[cls], rng.uniform(0.15, 0.9, size=3), len(objects))
        placed.append(c)
        objects.append((cls, c, np.array([w, d, h]), R))
    verts, tris, tri_label, tri_color, tri_object = [], [], [], [], []
    offset = 0
    for m, label, colour, instance in meshes:
        v = np.asarray(m.vertices)
        t = np.asarray(m.triangles) + offset
        verts.append(v); tris.append(t)
        tri_label.append(np.full(len(t), label)); tri_color.append(np.tile(colour, (len(t), 1)))
        tri_object.append(np.full(len(t), instance))
        offset += len(v)
    V, T = np.vstack(verts), np.vstack(tris).astype(np.int32)
    tri_label_a, tri_color_a, tri_object_a = np.concatenate(tri_label), np.vstack(tri_color), np.concatenate(tri_object)
    # Map points: uniform surface samples with the triangle's label and the procedural colour.
    areas = 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1)
    tri = rng.choice(len(T), size=map_points, p=areas / areas.sum())
    a, b = rng.random(map_points), rng.random(map_points)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    P = V[T[tri, 0]] + a[:, None] * (V[T[tri, 1]] - V[T[tri, 0]]) + b[:, None] * (V[T[tri, 2]] - V[T[tri, 0]])
    N = np.cross(V[T[tri, 1]] - V[T[tri, 0]], V[T[tri, 2]] - V[T[tri, 0]])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    col = (texture(P, tri_color_a[tri]) * 255).astype(np.uint8)
    lut = {v: CLASSES.index(k) for k, v in _LABEL_OF_CLASS.items()}
    cls_idx = np.array([lut.get(int(l), -1) for l in tri_label_a[tri]], dtype=np.int16)
    instance = tri_object_a[tri].astype(np.int32)
    cloud = PointSet(P, col, N, instance, cls_idx, np.zeros(map_points, np.uint8))
    nodes = [ObjectNode(f"obj-{i}", cls, c.copy(), c.copy(), ext, R, source="cluster", cad_id=None,
                        points=int((instance == i).sum()))
             for i, (cls, c, ext, R) in enumerate(objects)]
    build = SiteBuildConfig()
    site = Site(site_id=f"synthetic-{seed}", version="", manifest={"build_config": build.model_dump(mode="json")},
                map=cloud, raw=cloud, graph=build_graph(nodes, build.graph.edge_max_m), classes=list(CLASSES),
                label_maps={"nyu40": {v: k for k, v in _LABEL_OF_CLASS.items()}})
    site.refresh_version()
    return SyntheticScene(V, T, tri_label_a, tri_color_a, site)


def look_pose(position: np.ndarray, yaw_rad: float, pitch_down_rad: float) -> np.ndarray:
    """T_map_camera of an OpenCV camera at `position` (z up map) looking along yaw, pitched down, no roll."""
    f = np.array([np.cos(yaw_rad) * np.cos(pitch_down_rad), np.sin(yaw_rad) * np.cos(pitch_down_rad), -np.sin(pitch_down_rad)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    return make_T(np.stack([right, down, f], axis=1), position)


def render_frame(scene: SyntheticScene, T_map_camera: np.ndarray, *, intrinsics: CameraIntrinsics | None = None,
                 color_intrinsics: CameraIntrinsics | None = None, T_color_depth: np.ndarray | None = None,
                 depth_noise_m: float = 0.0, labels: bool = True, seed: int = 0) -> Frame:
    """Ray-cast depth (depth camera), colour and labels (colour camera) at T_map_camera (colour camera -> map)."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    Kd = intrinsics or CameraIntrinsics(160, 120, 140.0, 140.0, 79.5, 59.5)
    Kc = color_intrinsics or Kd
    T_cd = np.eye(4) if T_color_depth is None else np.asarray(T_color_depth, float)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(scene.vertices.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(scene.triangles)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)

    def cast(K: CameraIntrinsics, T_map_cam: np.ndarray):
        u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
        d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        dw = d @ T_map_cam[:3, :3].T
        rays = np.hstack([np.broadcast_to(T_map_cam[:3, 3], dw.shape), dw]).astype(np.float32)
        return rc.cast_rays(o3d.core.Tensor(rays)), dw

    hit, _ = cast(Kd, T_map_camera @ T_cd)
    t = hit["t_hit"].numpy()
    z = np.where(np.isfinite(t), t, 0.0).reshape(Kd.height, Kd.width)
    if depth_noise_m > 0:
        z = z + (z > 0) * rng.normal(0.0, depth_noise_m, z.shape) * z ** 2
    depth = np.clip(np.rint(z * 1000.0), 0, 65535).astype(np.uint16)
    hit_c, dirs = cast(Kc, T_map_camera)
    tc = hit_c["t_hit"].numpy()
    prim = hit_c["primitive_ids"].numpy().astype(np.int64)
    ok = np.isfinite(tc)
    prim = np.where(ok, prim, 0)
    P = T_map_camera[:3, 3] + dirs * np.where(ok, tc, 0.0)[:, None]
    col = np.where(ok[:, None], texture(P, scene.tri_color[prim]), 0.0)
    color = (col * 255).astype(np.uint8).reshape(Kc.height, Kc.width, 3)
    lab = np.where(ok, scene.tri_label[prim], 0).astype(np.uint16).reshape(Kc.height, Kc.width)
    return Frame(depth=depth, color=color, labels=lab if labels else None, depth_intrinsics=Kd, color_intrinsics=Kc,
                 T_color_depth=T_cd, frame_id="synthetic")


__all__ = ["SyntheticScene", "invert_T", "look_pose", "make_scene", "render_frame"]
