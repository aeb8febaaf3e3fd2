"""Frame validation at the entry: a field of view no camera has is refused (hostile-client finding: fx = 1e12
answered `ok` 3 m off, fx = 1e-12 flooded the log with Open3D warnings)."""

from __future__ import annotations

import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.errors import InvalidFrame
from cadreg.frame import Frame


def _frame(K: CameraIntrinsics, Kc: CameraIntrinsics | None = None) -> Frame:
    Kc = Kc or K
    return Frame(depth=np.full((K.height, K.width), 1500, np.uint16), color=np.zeros((Kc.height, Kc.width, 3), np.uint8),
                 depth_intrinsics=K, color_intrinsics=Kc)


@pytest.mark.parametrize("fx", [1e12, 1e-12, 2000.0, 50.0])
def test_implausible_field_of_view_is_refused(fx: float) -> None:
    with pytest.raises(InvalidFrame, match="field of view") as info:
        _frame(CameraIntrinsics(640, 480, fx, 577.0, 319.5, 239.5))
    assert info.value.detail["field"] == "depth_intrinsics"


def test_colour_camera_is_checked_too() -> None:
    good = CameraIntrinsics(640, 480, 577.0, 577.0, 319.5, 239.5)
    with pytest.raises(InvalidFrame, match="color intrinsics"):
        _frame(good, CameraIntrinsics(640, 480, 577.0, 1e9, 319.5, 239.5))


@pytest.mark.parametrize("K", [
    CameraIntrinsics(640, 480, 577.87, 577.87, 319.5, 239.5),  # ScanNet depth, 58°
    CameraIntrinsics(640, 480, 585.0, 585.0, 320.0, 240.0),  # 7-Scenes Kinect
    CameraIntrinsics(1296, 968, 1170.19, 1170.19, 647.75, 483.75),  # ScanNet colour
    CameraIntrinsics(1920, 1440, 560.0, 560.0, 959.5, 719.5),  # a phone's ultra-wide, ~120°
])
def test_real_cameras_pass(K: CameraIntrinsics) -> None:
    h, v = K.fov_deg
    assert 20 <= h <= 150 and 20 <= v <= 150
    _frame(K)


def test_huge_transform_is_refused_without_overflow() -> None:
    import warnings

    K = CameraIntrinsics(640, 480, 577.0, 577.0, 319.5, 239.5)
    depth, color = np.full((480, 640), 1500, np.uint16), np.zeros((480, 640, 3), np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the fuzz run found an overflow warning in the rigidity check
        with pytest.raises(InvalidFrame, match="pose prior"):
            Frame(depth=depth, color=color, depth_intrinsics=K, color_intrinsics=K, T_map_camera_prior=np.eye(4) * 1e300)
        with pytest.raises(InvalidFrame, match="T_color_depth"):
            Frame(depth=depth, color=color, depth_intrinsics=K, color_intrinsics=K, T_color_depth=np.eye(4) * 1e300)
