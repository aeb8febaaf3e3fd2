"""Query-frame rendering from a labelled mesh: ray-cast depth, colour and labels with a Kinect-like noise model.

    LabelledMesh                    mesh + per-vertex colours, labels, object instances (mesh.py)
    MeshRenderer                    RaycastingScene wrapper: cast / render_frame (raycast.py)
    camera_rig(config)              depth and colour intrinsics and T_color_depth of the rendered sensor
    PoseSampler, look_pose          hand-held camera poses inside the room (poses.py)
    apply_depth_noise               the noise model (noise.py)
    render_frames(mesh, out_dir, n) a recorded-frames folder of rendered views (sequence.py)
"""

from .mesh import LabelledMesh
from .noise import apply_depth_noise, axial_sigma_m
from .poses import PoseSampler, look_pose, pose_height_pitch_roll
from .raycast import MeshRenderer, camera_rig
from .sequence import RenderedFrame, count_visible_objects, render_frames

__all__ = [
    "LabelledMesh", "MeshRenderer", "PoseSampler", "RenderedFrame", "apply_depth_noise", "axial_sigma_m",
    "camera_rig", "count_visible_objects", "look_pose", "pose_height_pitch_roll", "render_frames",
]
