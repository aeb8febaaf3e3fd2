"""Ray-cast RGB-D(-L) views of a labelled mesh with Open3D's RaycastingScene.

Rays are built here rather than with `RaycastingScene.create_rays_pinhole`: Open3D puts its pinhole rays through
u + 0.5 (DESIGN §9), and building them from the pixel-centre convention (u - cx) / fx directly, with a camera-z
component of 1, makes the hit distance `t_hit` the depth z itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..camera import CameraIntrinsics
from ..config import NoiseConfig, RenderConfig
from ..errors import InvalidArgument
from ..frame import Frame
from ..geometry import make_T
from .mesh import LabelledMesh
from .noise import apply_color_noise, apply_depth_noise, depth_range_m

# ScanNet's colour camera (1296x968); other colour sizes are scaled from it.
SCANNET_COLOR = CameraIntrinsics(1296, 968, 1170.187988, 1170.187988, 647.750000, 483.750000)


def camera_rig(config: RenderConfig = RenderConfig()) -> tuple[CameraIntrinsics, CameraIntrinsics, np.ndarray]:
    """(depth intrinsics, colour intrinsics, T_color_depth) of the rendered sensor.

    The colour camera equals the depth camera unless `color_width/height` differ from the depth size; then its
    intrinsics are ScanNet's colour camera scaled to that size and it sits `baseline_m` along the depth camera's x.
    """
    depth = CameraIntrinsics(config.depth_width, config.depth_height, config.depth_fx, config.depth_fy,
                             config.depth_cx, config.depth_cy)
    cw = config.color_width or config.depth_width
    ch = config.color_height or config.depth_height
    if (cw, ch) == (depth.width, depth.height):
        return depth, depth, np.eye(4)
    color = SCANNET_COLOR if (cw, ch) == (SCANNET_COLOR.width, SCANNET_COLOR.height) else SCANNET_COLOR.scaled_to(cw, ch)
    # The colour centre is at +baseline along the depth camera's x: p_color = p_depth - (b, 0, 0).
    return depth, color, make_T(t=(-config.baseline_m, 0.0, 0.0))


def pixel_rays(intr: CameraIntrinsics) -> np.ndarray:
    """(H, W, 3) float32 camera-frame ray directions ((u - cx)/fx, (v - cy)/fy, 1) of every pixel."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    return np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1).astype(np.float32)


@dataclass
class View:
    """One noiseless ray-cast image.

    depth_m : (H, W) float32 z-depth in metres, inf where no surface; cos_incidence : (H, W) float32 |cos| of the
    angle between ray and surface normal (0 on misses); color : (H, W, 3) uint8; labels : (H, W) uint16 (0 on
    misses) or None; instances : (H, W) int32 object instance (-1 none) or None.
    """

    depth_m: np.ndarray
    cos_incidence: np.ndarray
    color: np.ndarray
    labels: np.ndarray | None
    instances: np.ndarray | None


class MeshRenderer:
    """Renders depth, colour and labels of a LabelledMesh; build once, render many views."""

    def __init__(self, mesh: LabelledMesh) -> None:
        self.mesh = mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        tmesh = o3d.t.geometry.TriangleMesh()
        tmesh.vertex.positions = o3d.core.Tensor(mesh.vertices.astype(np.float32))
        tmesh.triangle.indices = o3d.core.Tensor(mesh.faces.astype(np.uint32))
        self.scene.add_triangles(tmesh)
        self._rays_cache: dict[CameraIntrinsics, tuple[np.ndarray, np.ndarray]] = {}
        self._colors = mesh.colors.astype(np.float32)

    def _rays(self, intr: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) camera-frame rays of every pixel and their (n,) inverse lengths (rotation keeps lengths)."""
        if intr not in self._rays_cache:
            rays = pixel_rays(intr).reshape(-1, 3)
            self._rays_cache[intr] = (rays, (1.0 / np.linalg.norm(rays, axis=1)).astype(np.float32))
        return self._rays_cache[intr]

    def cast(self, intr: CameraIntrinsics, T_map_cam: np.ndarray, *, with_color: bool = True) -> View:
        """Ray-cast one camera at pose T_map_cam (camera -> map, 4x4)."""
        dirs_cam, inv_len = self._rays(intr)
        R = T_map_cam[:3, :3].astype(np.float32)
        dirs = dirs_cam @ R.T
        origin = np.broadcast_to(T_map_cam[:3, 3].astype(np.float32), dirs.shape)
        rays = np.concatenate([origin, dirs], axis=1)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = ans["t_hit"].numpy()
        hit = np.isfinite(t_hit)
        shape = (intr.height, intr.width)
        normals = ans["primitive_normals"].numpy()
        # |cos| between the unit ray and the face normal.
        cos = np.abs(np.einsum("ij,ij->i", normals, dirs)) * inv_len
        cos[~hit] = 0.0
        color = np.zeros((len(t_hit), 3), dtype=np.uint8)
        labels = instances = None
        if with_color:
            prim = ans["primitive_ids"].numpy()[hit].astype(np.int64)
            uv = ans["primitive_uvs"].numpy()[hit]
            tri = self.mesh.faces[prim]
            w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1).astype(np.float32)
            rgb = np.einsum("ik,ikc->ic", w, self._colors[tri])
            color[hit] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
            nearest = tri[np.arange(len(tri)), np.argmax(w, axis=1)]
            if self.mesh.labels is not None:
                labels = np.zeros(len(t_hit), dtype=np.uint16)
                labels[hit] = self.mesh.labels[nearest]
                labels = labels.reshape(shape)
            if self.mesh.instances is not None:
                instances = np.full(len(t_hit), -1, dtype=np.int32)
                instances[hit] = self.mesh.instances[nearest]
                instances = instances.reshape(shape)
        return View(
            depth_m=t_hit.reshape(shape), cos_incidence=cos.reshape(shape).astype(np.float32),
            color=color.reshape(shape + (3,)), labels=labels, instances=instances,
        )

    def render_frame(
        self,
        T_map_camera: np.ndarray,
        depth_intr: CameraIntrinsics,
        color_intr: CameraIntrinsics,
        T_color_depth: np.ndarray,
        *,
        rng: np.random.Generator | None = None,
        noise: NoiseConfig | None = NoiseConfig(),
        depth_scale: float = 1000.0,
        frame_id: str | None = None,
        depth_view: View | None = None,
    ) -> tuple[Frame, View, View]:
        """Render a Frame whose colour camera is at T_map_camera (colour -> map).

        The depth camera sits at T_map_depth = T_map_camera @ T_color_depth. noise None = noiseless depth and
        colour (still quantised to the depth unit); with noise the frame's `depth_range_m` is the noise model's
        cut-off. `depth_view`: the depth camera's cast at this pose when the caller already has it (with colour when
        the cameras coincide). Returns (frame, depth view, colour view).
        """
        T_map_depth = T_map_camera @ T_color_depth
        same = depth_intr == color_intr and np.allclose(T_color_depth, np.eye(4))
        dview = depth_view if depth_view is not None else self.cast(depth_intr, T_map_depth, with_color=same)
        cview = dview if same else self.cast(color_intr, T_map_camera)
        z = np.where(np.isfinite(dview.depth_m), dview.depth_m, 0.0)
        color = cview.color
        if noise is not None:
            if rng is None:
                raise InvalidArgument("noise needs a seeded numpy Generator")
            z = apply_depth_noise(z, dview.cos_incidence, rng, noise)
            color = apply_color_noise(color, rng, noise.color_sigma)
        depth = np.clip(np.rint(z * depth_scale), 0, 65535).astype(np.uint16)
        frame = Frame(
            depth=depth, color=color, labels=cview.labels,
            depth_intrinsics=depth_intr, color_intrinsics=color_intr, T_color_depth=T_color_depth,
            depth_scale=depth_scale, label_set=self.mesh.label_set, frame_id=frame_id,
            depth_range_m=depth_range_m(noise),
        )
        return frame, dview, cview

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """(n,) float32 unsigned distance (metres) from map points (n, 3) to the mesh."""
        return self.scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()

    def cast_rays(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(n,) float32 hit distance along each ray (directions need not be unit: t is in their units); inf = miss."""
        rays = np.concatenate([np.asarray(origins, np.float32), np.asarray(directions, np.float32)], axis=1)
        return self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


