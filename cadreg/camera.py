"""Pinhole camera intrinsics.

Convention (paper eq. 1–2): pixel (u, v) with integer u, v at the pixel centre sees the ray
((u - cx) / fx, (v - cy) / fy, 1) in OpenCV axes (x right, y down, z forward). ScanNet's cx = 319.5 for a
640-wide image follows it. Open3D's ray-caster puts rays through u + 0.5, so renderers shift cx, cy by 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InvalidFrame


@dataclass(frozen=True)
class CameraIntrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise InvalidFrame(f"intrinsics must be finite numbers, got fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if self.fx <= 0 or self.fy <= 0:
            raise InvalidFrame(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InvalidFrame(f"image size must be positive, got {self.width}x{self.height}")
        if not (-self.width <= self.cx <= 2 * self.width and -self.height <= self.cy <= 2 * self.height):
            raise InvalidFrame(f"principal point ({self.cx}, {self.cy}) is far outside a {self.width}x{self.height} image")

    @property
    def fov_deg(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view, degrees, for a centred principal point."""
        return (math.degrees(2.0 * math.atan(0.5 * self.width / self.fx)),
                math.degrees(2.0 * math.atan(0.5 * self.height / self.fy)))

    @property
    def K(self) -> np.ndarray:
        """3×3 float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> "CameraIntrinsics":
        K = np.asarray(K, dtype=float)
        return cls(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    def scaled_to(self, width: int, height: int) -> "CameraIntrinsics":
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(
            width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        )

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}


def axial_noise_sigma_m(z_m: np.ndarray, a_m: float, b_per_m: float, z0_m: float) -> np.ndarray:
    """σ (metres) of a depth sensor's noise along its rays at depth z_m (metres, along the optical axis), elementwise:
    a + b·(z − z0)², the model of structured-light sensors such as the Kinect (Nguyen, Izadi, Lovell 2012). What
    the renderer adds to its frames (`render.noise`) and what the refinement assumes of a frame (`FrameConfig`)."""
    z = np.asarray(z_m, dtype=np.float64)
    return a_m + b_per_m * (z - z0_m) ** 2
