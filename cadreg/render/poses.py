"""Camera poses as a person walking a room holds an RGB-D camera (z up, OpenCV camera axes).

A candidate position is uniform over the mesh's footprint at a height above the floor; it is kept when it is clear
of every surface, stands over floor (not over furniture), and is enclosed by the room (horizontal rays hit walls in
most directions). The orientation is any heading, pitched down, with a little roll.
"""

from __future__ import annotations

import numpy as np

from ..config import RenderConfig
from ..geometry import make_T
from .raycast import MeshRenderer


def look_pose(position: np.ndarray, yaw_deg: float, pitch_down_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """T_map_camera (4x4) of a camera at `position` (map, z up) looking along heading `yaw_deg` (from +x towards
    +y), tilted `pitch_down_deg` below the horizon, rolled `roll_deg` about its optical axis."""
    yaw, pitch, roll = np.radians([yaw_deg, pitch_down_deg, roll_deg])
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward], axis=1)
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return make_T(R @ Rz, position)


def pose_height_pitch_roll(T_map_camera: np.ndarray, floor_z: float) -> tuple[float, float, float]:
    """(height above floor m, downward pitch deg, roll deg) of a camera pose; inverse of `look_pose`'s angles."""
    R = T_map_camera[:3, :3]
    forward, x_axis = R[:, 2], R[:, 0]
    pitch = float(np.degrees(np.arcsin(np.clip(-forward[2], -1, 1))))
    right0 = np.cross(forward, [0.0, 0.0, 1.0])
    right0 /= np.linalg.norm(right0)
    down0 = np.cross(forward, right0)
    roll = float(np.degrees(np.arctan2(np.dot(x_axis, down0), np.dot(x_axis, right0))))
    return float(T_map_camera[2, 3] - floor_z), pitch, roll


class PoseSampler:
    """Draws plausible hand-held camera poses inside the room of a mesh (z up)."""

    _N_WALL_RAYS = 12

    def __init__(self, renderer: MeshRenderer, config: RenderConfig = RenderConfig()) -> None:
        self.renderer = renderer
        self.config = config
        v = renderer.mesh.vertices
        self.floor_z = renderer.mesh.floor_height_m()
        self.xy_min = np.percentile(v[:, :2], 0.5, axis=0)
        self.xy_max = np.percentile(v[:, :2], 99.5, axis=0)
        a = np.linspace(0, 2 * np.pi, self._N_WALL_RAYS, endpoint=False)
        self._wall_dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)

    def position_ok(self, p: np.ndarray, height_m: float) -> bool:
        """Clear of surfaces, over floor, enclosed by walls."""
        cfg = self.config
        if self.renderer.distance_to_surface(p[None])[0] < cfg.min_clearance_m:
            return False
        t_down = self.renderer.cast_rays(p[None], np.array([[0.0, 0.0, -1.0]]))[0]
        if not (np.isfinite(t_down) and abs(t_down - height_m) < 0.1):
            return False
        # Rays at knee height: walls of ScanNet meshes can stop below the camera.
        o = np.tile([p[0], p[1], self.floor_z + 0.5], (self._N_WALL_RAYS, 1))
        t = self.renderer.cast_rays(o, self._wall_dirs)
        return int(np.isfinite(t).sum()) >= self._N_WALL_RAYS - 2

    def sample(self, rng: np.random.Generator, max_tries: int = 1000) -> np.ndarray | None:
        """One T_map_camera (colour camera -> map) or None when `max_tries` positions all fail."""
        cfg = self.config
        for _ in range(max_tries):
            xy = rng.uniform(self.xy_min, self.xy_max)
            h = rng.uniform(cfg.height_min_m, cfg.height_max_m)
            p = np.array([xy[0], xy[1], self.floor_z + h])
            if not self.position_ok(p, h):
                continue
            return look_pose(
                p,
                yaw_deg=rng.uniform(0.0, 360.0),
                pitch_down_deg=rng.uniform(cfg.pitch_min_deg, cfg.pitch_max_deg),
                roll_deg=rng.uniform(-cfg.roll_max_deg, cfg.roll_max_deg),
            )
        return None
