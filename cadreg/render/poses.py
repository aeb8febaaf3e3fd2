"""Camera poses as a person walking a room holds an RGB-D camera (z up, OpenCV camera axes).

A candidate position is uniform over the mesh's footprint at a height above the floor; it is kept when it is clear
of every surface, stands over floor (not over furniture), and is enclosed by the room (horizontal rays hit walls in
most directions). The orientation is any heading, pitched down, with a little roll.

A walk (`walk`) is the poses of one camera carried through the room, frame after frame: what a stream of a robot
or a phone sends, for tracking (`cadreg render --walk STEP_M`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

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


@dataclass(frozen=True)
class Placement:
    """Where a camera is and how it is held: position (3,) map frame (z up), height above the floor (m), heading,
    downward pitch and roll (degrees, `look_pose`'s)."""

    position: np.ndarray
    height_m: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float

    def pose(self) -> np.ndarray:
        """T_map_camera (4x4)."""
        return look_pose(self.position, self.yaw_deg, self.pitch_deg, self.roll_deg)


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
        placement = self.draw(rng, max_tries)
        return None if placement is None else placement.pose()

    def draw(self, rng: np.random.Generator, max_tries: int = 1000) -> Placement | None:
        """One camera placement (`sample`'s pose) or None when `max_tries` positions all fail."""
        cfg = self.config
        for _ in range(max_tries):
            xy = rng.uniform(self.xy_min, self.xy_max)
            h = rng.uniform(cfg.height_min_m, cfg.height_max_m)
            p = np.array([xy[0], xy[1], self.floor_z + h])
            if not self.position_ok(p, h):
                continue
            return Placement(p, float(h), float(rng.uniform(0.0, 360.0)),
                             float(rng.uniform(cfg.pitch_min_deg, cfg.pitch_max_deg)),
                             float(rng.uniform(-cfg.roll_max_deg, cfg.roll_max_deg)))
        return None


# A walk goes from place to place: it turns on the spot towards the next place by at most this much a frame (5
# degrees a frame is 50 a second at 10 frames a second, as a person turns), then walks there in a straight line.
WALK_SPIN_DEG = 5.0
# How far the hand's pitch and roll drift a frame (degrees, one standard deviation), within RenderConfig's ranges.
WALK_TILT_DEG = 0.5
# The next place is drawn as the sampler draws a camera position, and kept when every step of the straight way there
# stands where the sampler allows (clear of surfaces, over floor, inside the room) and its view shows a surface on
# at least this share of the depth camera's rays (`sees`): lower than a sampled view's (RenderConfig.
# min_valid_fraction, 0.5), since a scan's walls stop low (scene0470's at 1.37 m) and a camera at 1.2-1.75 m
# looking across the room sees over them. At most WALK_PLACE_TRIES draws a place, a place at least WALK_MIN_LEG_M
# away; of the first WALK_CHOICES places so found, the one it turns least to face (a person walks on rather than
# about).
WALK_MIN_VALID = 0.1
WALK_PLACE_TRIES = 200
WALK_MIN_LEG_M = 0.5
WALK_CHOICES = 4
# A walk's step: at least this (a finer one makes thousands of placements a way), at most WALK_MIN_LEG_M.
WALK_MIN_STEP_M = 0.005


def walk(sampler: PoseSampler, start: Placement, rng: np.random.Generator, n: int, *, step_m: float,
         sees: Callable[[np.ndarray], float] = lambda T: 1.0) -> list[Placement]:
    """`n` placements of one camera carried through the room from `start` (included), as a person films a room:
    it turns on the spot towards a next place (`WALK_SPIN_DEG` a frame) and walks there in a straight line,
    `step_m` a frame, looking the way it goes; pitch and roll drift a little (`WALK_TILT_DEG`) within the sampler's
    ranges. Every step stands where `PoseSampler.position_ok` allows, and every step and turn shows a surface on
    WALK_MIN_VALID of the view's rays (`sees(T_map_camera)`: the share, the caller's check). Where no next place is
    found (a pocket of furniture), it turns on the spot. step_m: WALK_MIN_STEP_M to WALK_MIN_LEG_M (every way to a
    next place holds a step). Deterministic for a given rng state."""
    cfg = sampler.config
    out: list[Placement] = [start]
    route: list[Placement] = []  # the placements still ahead on the way to the next place
    while len(out) < n:
        if not route:
            route = _route_to_next_place(sampler, out[-1], rng, step_m, sees)
        last = out[-1]
        pitch = float(np.clip(last.pitch_deg + rng.normal(0.0, WALK_TILT_DEG), cfg.pitch_min_deg, cfg.pitch_max_deg))
        roll = float(np.clip(last.roll_deg + rng.normal(0.0, WALK_TILT_DEG), -cfg.roll_max_deg, cfg.roll_max_deg))
        out.append(replace(route.pop(0), pitch_deg=pitch, roll_deg=roll))
    return out


def _route_to_next_place(sampler: PoseSampler, at: Placement, rng: np.random.Generator, step_m: float,
                         sees: Callable[[np.ndarray], float]) -> list[Placement]:
    """The placements from `at` to a next place (its pitch and roll as `at`'s): the turns on the spot towards it,
    then the steps there, each where the sampler allows and showing a surface on WALK_MIN_VALID of the view. None
    found: a quarter turn on the spot where it shows as much, else `at` again (its view was rendered)."""
    def shows(p: Placement) -> bool:
        return sees(p.pose()) >= WALK_MIN_VALID

    candidates: list[tuple[list[Placement], list[Placement]]] = []  # (turns, steps)
    for _ in range(WALK_PLACE_TRIES):
        xy = rng.uniform(sampler.xy_min, sampler.xy_max)
        way = np.array([xy[0], xy[1], at.position[2]]) - at.position
        length = float(np.linalg.norm(way))
        if length < WALK_MIN_LEG_M:
            continue
        yaw = float(np.degrees(np.arctan2(way[1], way[0])))
        steps = [replace(at, position=at.position + way * (k * step_m / length), yaw_deg=yaw % 360.0)
                 for k in range(1, int(length / step_m) + 1)]
        turns = _turns(at, yaw)
        if all(sampler.position_ok(p.position, p.height_m) for p in steps) and all(map(shows, turns + steps)):
            candidates.append((turns, steps))
            if len(candidates) == WALK_CHOICES:
                break
    if not candidates:
        turns = _turns(at, at.yaw_deg + 90.0)
        return turns if all(map(shows, turns)) else [at]
    turns, steps = min(candidates, key=lambda c: len(c[0]))
    return turns + steps


def _turns(at: Placement, yaw_deg: float) -> list[Placement]:
    """`at` turned on the spot towards heading yaw_deg, WALK_SPIN_DEG a frame (the last turn lands on it)."""
    delta = (yaw_deg - at.yaw_deg + 180.0) % 360.0 - 180.0
    count = int(np.ceil(abs(delta) / WALK_SPIN_DEG - 1e-9))
    return [replace(at, yaw_deg=(at.yaw_deg + delta * k / count) % 360.0) for k in range(1, count + 1)]
