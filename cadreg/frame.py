"""One RGB-D query frame, validated once at the entry.

Frames: the depth camera `depth`, the colour camera `color` (= "camera" of `T_map_camera`; labels are aligned
with it). `T_color_depth` moves depth-camera points into the colour camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import CameraIntrinsics
from .errors import InvalidFrame
from .geometry import is_rigid
from .labels import label_set_name
from .site.regions import SearchRegion

# Fields of view of real depth and colour cameras: telephoto phones ~25°, Kinect / RealSense / Structure 55–90°,
# ultra-wide phones ~120°. Intrinsics outside these are a unit mistake (fx in metres, or in another image size)
# and would otherwise be registered as they are: fx = 1e12 squeezes the frame into a point, fx = 1e-12 spreads it
# over kilometres.
MIN_FOV_DEG = 20.0
MAX_FOV_DEG = 150.0


@dataclass
class Frame:
    """An RGB-D frame.

    depth : (H, W) uint16, `depth_scale` units per metre, 0 = invalid; H, W = depth_intrinsics size.
    color : (h, w, 3) uint8 RGB; h, w = color_intrinsics size.
    labels : (h, w) uint16 or uint8 label ids in `label_set`, aligned with colour; None when the client has none.
    T_color_depth : (4, 4) float64 rigid transform, depth camera -> colour camera.
    gravity_camera : (3,) unit vector of gravity ("down") in the colour camera frame, optional.
    T_map_camera_prior : (4, 4) optional pose prior (colour camera -> map).
    search_region : where the client says the camera is (a ball in the map frame, or region ids): hypotheses whose
        camera lies elsewhere (outside the ball, or the regions' boxes grown by `site.regions.CAMERA_MARGIN_M`) are
        not considered.
    depth_range_m : the farthest depth (metres, along the optical axis) the depth camera measures a surface at, when
        the client knows it (a Kinect v1 about 4, a render its cut-off); None: not known (`localize.field_view`
        takes 4 m, or what the frame shows it reaches: `sensor_range_m`).
    """

    depth: np.ndarray
    color: np.ndarray
    depth_intrinsics: CameraIntrinsics
    color_intrinsics: CameraIntrinsics
    T_color_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_scale: float = 1000.0
    labels: np.ndarray | None = None
    label_set: str = "nyu40"
    gravity_camera: np.ndarray | None = None
    T_map_camera_prior: np.ndarray | None = None
    frame_id: str | None = None
    search_region: SearchRegion | None = None
    depth_range_m: float | None = None

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise InvalidFrame naming the first thing wrong."""
        d, c = self.depth, self.color
        if not isinstance(d, np.ndarray) or d.ndim != 2:
            raise InvalidFrame(f"depth must be a 2-D array, got shape {getattr(d, 'shape', None)}")
        if d.dtype != np.uint16:
            raise InvalidFrame(f"depth must be uint16, got {d.dtype}")
        if (d.shape[1], d.shape[0]) != (self.depth_intrinsics.width, self.depth_intrinsics.height):
            raise InvalidFrame(
                f"depth is {d.shape[1]}x{d.shape[0]} but its intrinsics say "
                f"{self.depth_intrinsics.width}x{self.depth_intrinsics.height}"
            )
        for name, K in (("depth", self.depth_intrinsics), ("color", self.color_intrinsics)):
            h_fov, v_fov = K.fov_deg
            if not (MIN_FOV_DEG <= h_fov <= MAX_FOV_DEG and MIN_FOV_DEG <= v_fov <= MAX_FOV_DEG):
                raise InvalidFrame(
                    f"{name} intrinsics give a {h_fov:.3g}° × {v_fov:.3g}° field of view for {K.width}x{K.height} "
                    f"(fx={K.fx:g}, fy={K.fy:g}); a camera sees {MIN_FOV_DEG:g}°–{MAX_FOV_DEG:g}°",
                    detail={"field": f"{name}_intrinsics", "fov_deg": [h_fov, v_fov]})
        if not isinstance(c, np.ndarray) or c.ndim != 3 or c.shape[2] != 3 or c.dtype != np.uint8:
            raise InvalidFrame(f"color must be (h, w, 3) uint8, got {getattr(c, 'shape', None)} {getattr(c, 'dtype', None)}")
        if (c.shape[1], c.shape[0]) != (self.color_intrinsics.width, self.color_intrinsics.height):
            raise InvalidFrame(
                f"color is {c.shape[1]}x{c.shape[0]} but its intrinsics say "
                f"{self.color_intrinsics.width}x{self.color_intrinsics.height}"
            )
        self.label_set = label_set_name(self.label_set)
        if self.labels is not None:
            lb = self.labels
            if not isinstance(lb, np.ndarray) or lb.ndim != 2 or lb.dtype not in (np.uint8, np.uint16):
                raise InvalidFrame(f"labels must be a 2-D uint8/uint16 array, got {getattr(lb, 'shape', None)} {getattr(lb, 'dtype', None)}")
            if lb.shape != c.shape[:2]:
                raise InvalidFrame(f"labels are {lb.shape[1]}x{lb.shape[0]} but colour is {c.shape[1]}x{c.shape[0]}")
        if not (np.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise InvalidFrame(f"depth_scale must be a positive number, got {self.depth_scale}")
        T = np.asarray(self.T_color_depth, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not is_rigid(T):
            raise InvalidFrame("T_color_depth must be a finite rigid 4x4 transform")
        self.T_color_depth = T
        if self.gravity_camera is not None:
            g = np.asarray(self.gravity_camera, dtype=float).reshape(-1)
            if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
                raise InvalidFrame("gravity must be a finite non-zero 3-vector")
            self.gravity_camera = g / np.linalg.norm(g)
        if self.T_map_camera_prior is not None:
            P = np.asarray(self.T_map_camera_prior, dtype=float)
            if P.shape != (4, 4) or not np.all(np.isfinite(P)) or not is_rigid(P):
                raise InvalidFrame("pose prior must be a finite rigid 4x4 transform")
            self.T_map_camera_prior = P
        if self.search_region is not None and not isinstance(self.search_region, SearchRegion):
            raise InvalidFrame(f"search_region must be a SearchRegion, got {type(self.search_region).__name__}")
        if self.depth_range_m is not None:
            self.depth_range_m = depth_range_metres(self.depth_range_m)
        if not np.any(d):
            raise InvalidFrame("depth has no valid pixel (all zero)")


def depth_range_metres(value: object) -> float:
    """`value` as a depth camera's range (`Frame.depth_range_m`): a finite positive number of metres, else
    InvalidFrame."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidFrame(f"depth_range_m must be a positive number of metres, got {value!r:.40}")
    try:
        metres = float(value)
    except OverflowError:
        metres = float("inf")
    if not (np.isfinite(metres) and metres > 0):
        raise InvalidFrame(f"depth_range_m must be a positive number of metres, got {value!r:.40}")
    return metres
