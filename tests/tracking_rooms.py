"""Helpers of the repeated-rooms tests (no tests here): two copies of the real scene0470 room side by side, the
second missing a chair and the bin (`cadreg site compose`), and a camera that starts on a view both rooms share and
turns towards what only the first room holds, rendered from the real scene0470 mesh (which is room "a"); and
`near`, the tests' 5 cm / 5° check of a pose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

ROOM_B_OFFSET_M = 6.0  # room "b" is room "a" moved along x (the room is 3.5 m wide)
DROPPED = ["cad-4", "cad-0"]  # the chair at (3.03, 0.62) and the bin at (3.26, 1.50): only room "a" has them
CAMERA_M = np.array([1.7, 2.3, 1.4])
# looked-at points: from the table's corner (a view both rooms share) to the chair and bin only room "a" holds
LOOK_FROM_M = np.array([0.7, 0.6, 0.4])
LOOK_TO_M = np.array([3.2, 0.9, 0.4])


def near(T: np.ndarray, T_true: np.ndarray) -> bool:
    """Whether pose T lies within 5 cm and 5° of T_true (both (4, 4))."""
    from cadreg.geometry import pose_errors

    t_err, r_err = pose_errors(np.asarray(T, float), T_true)
    return t_err < 0.05 and r_err < 5.0


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) T_map_camera of an OpenCV camera (x right, y down, z forward) at `position` looking at `target`,
    z up."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = position
    return T


def turning_poses(n: int) -> list[np.ndarray]:
    return [look_at(CAMERA_M, LOOK_FROM_M + (LOOK_TO_M - LOOK_FROM_M) * k / (n - 1)) for k in range(n)]


def write_layout(room_dir: Path, out: Path, dropped: list[str] = DROPPED) -> Path:
    """The LAYOUT.json of the two rooms (room "b" moved by ROOM_B_OFFSET_M along x, without `dropped`)."""
    layout = out / "LAYOUT.json"
    layout.parent.mkdir(parents=True, exist_ok=True)
    eye = np.eye(4)
    moved = np.eye(4)
    moved[0, 3] = ROOM_B_OFFSET_M
    layout.write_text(json.dumps({"site_id": "twin-rooms", "rooms": [
        {"name": "a", "bundle": str(room_dir), "T_building_room": eye.tolist()},
        {"name": "b", "bundle": str(room_dir), "T_building_room": moved.tolist(), "drop_objects": dropped},
    ]}))
    return layout


def twin_site(room_dir: Path, out: Path, dropped: list[str] = DROPPED) -> Path:
    """Compose and save the two-room site (site id "twin-rooms", room "b" without `dropped`; its LAYOUT.json in
    `out`); returns its bundle directory."""
    from cadreg.site.compose import compose_site, read_layout

    layout = write_layout(room_dir, out, dropped)
    site_dir = out / "sites" / "twin-rooms"
    compose_site(read_layout(layout), layout.parent).save(site_dir)
    return site_dir


def render_turn(mesh_ply: Path, labels_ply: Path, out: Path, n: int = 40) -> Path:
    """Render the turning camera in room "a" from the real mesh (with labels, Kinect-like noise)."""
    from cadreg.render import LabelledMesh, render_frames

    render_frames(LabelledMesh.from_ply(mesh_ply, labels_ply), out, 0, poses=turning_poses(n), seed=0)
    return out


def shared_view(scene0470_dir: Path, out: Path):
    """(frame, T_map_camera in room "a") of the turning camera's first view: the table's corner, which both rooms
    show (rendered from the real mesh)."""
    from cadreg.io.frames import RecordedFrames

    render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply", scene0470_dir / "scene0470_00_vh_clean_2.labels.ply",
                out, n=30)
    return RecordedFrames.open(out).load(0)
