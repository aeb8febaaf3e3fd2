"""Frame -> points (paper eq. 1–2): back-projection, depth -> colour transfer, colour and label look-up."""

from __future__ import annotations

import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.errors import InvalidFrame
from cadreg.frame import Frame
from cadreg.geometry import make_T
from cadreg.localize.points import (
    MAX_NOISE_OCTAVE, FramePoints, _project_to_color, frame_to_points, noise_octaves, octave_voxel_indices, voxel_budget,
    voxel_downsample, voxel_indices, window_colours,
)


def _plane_frame(depth_m: float = 2.0, *, color_size=(64, 48), T_color_depth=None) -> Frame:
    Kd = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    Kc = Kd.scaled_to(*color_size)
    depth = np.full((24, 32), int(depth_m * 1000), dtype=np.uint16)
    color = np.zeros((color_size[1], color_size[0], 3), dtype=np.uint8)
    color[:, : color_size[0] // 2] = (255, 0, 0)  # left half red
    color[:, color_size[0] // 2:] = (0, 0, 255)  # right half blue
    labels = np.zeros(color.shape[:2], dtype=np.uint16)
    labels[:, color_size[0] // 2:] = 5
    return Frame(depth=depth, color=color, labels=labels, depth_intrinsics=Kd, color_intrinsics=Kc,
                 T_color_depth=np.eye(4) if T_color_depth is None else T_color_depth)


def test_back_projection_follows_eq_1_2() -> None:
    f = _plane_frame(2.0, color_size=(32, 24))
    p = frame_to_points(f, pixel_stride=1)
    assert len(p) == 32 * 24
    assert np.allclose(p.xyz[:, 2], 2.0)
    # pixel (0, 0): X = (0 - cx) Z / fx
    assert np.allclose(p.xyz[0], [(0 - 15.5) * 2.0 / 30.0, (0 - 11.5) * 2.0 / 30.0, 2.0])
    # the principal point's neighbours are symmetric about the optical axis
    assert abs(p.xyz[:, 0].mean()) < 1e-9


def test_colour_and_label_read_in_a_larger_colour_image() -> None:
    f = _plane_frame(2.0, color_size=(64, 48))
    p = frame_to_points(f, pixel_stride=1)
    left = p.xyz[:, 0] < -0.05
    right = p.xyz[:, 0] > 0.05
    assert np.allclose(p.rgb[left], [1, 0, 0]) and np.allclose(p.rgb[right], [0, 0, 1])
    assert np.all(p.labels[left] == 0) and np.all(p.labels[right] == 5)


def test_window_colours_average_the_pixels_about_each_points_own() -> None:
    f = _plane_frame(2.0, color_size=(64, 48))
    rng = np.random.default_rng(0)
    noisy = np.clip(f.color.astype(np.float64) * 0.5 + 64 + rng.normal(0, 20, f.color.shape), 0, 255).astype(np.uint8)
    f = Frame(depth=f.depth, color=noisy, labels=f.labels, depth_intrinsics=f.depth_intrinsics,
              color_intrinsics=f.color_intrinsics)
    p = frame_to_points(f, pixel_stride=1)
    mean = window_colours(f, p.xyz, 2)
    inner = np.abs(p.xyz[:, 0]) > 0.4  # windows that stay on one half
    truth = np.where(p.xyz[inner, :1] < 0, [191.5, 64, 64], [64, 64, 191.5]) / 255.0
    # a 5 × 5 window's noise is a fifth of one pixel's
    assert np.std(mean[inner] - truth) < 0.35 * np.std(p.rgb[inner] - truth)
    assert np.abs(np.mean(mean[inner] - truth)) < 0.01
    # windows at the image's border are clipped to it, and every point has its mean
    assert mean.shape == p.rgb.shape and np.all((mean >= 0) & (mean <= 1))


def test_depth_to_colour_extrinsic_moves_points() -> None:
    T = make_T(t=[-0.1, 0.0, 0.0])
    f = _plane_frame(2.0, color_size=(32, 24), T_color_depth=T)
    p0 = frame_to_points(_plane_frame(2.0, color_size=(32, 24)), pixel_stride=1)
    p1 = frame_to_points(f, pixel_stride=1)
    # Points are in the colour camera: shifted by -0.1 m in x; those leaving the colour image are dropped.
    assert len(p1) < len(p0)
    assert np.isclose(p1.xyz[:, 0].max(), p0.xyz[:, 0].max() - 0.1)
    assert np.all(np.isin(np.round(p1.xyz[:, 0] + 0.1, 6), np.round(p0.xyz[:, 0], 6)))


def test_stride_depth_range_and_missing_labels() -> None:
    f = _plane_frame(2.0, color_size=(32, 24))
    f.labels = None
    assert len(frame_to_points(f, pixel_stride=2)) == 16 * 12
    assert len(frame_to_points(f, max_depth_m=1.5)) == 0
    assert np.all(frame_to_points(f).labels == -1)


def test_registered_frame_reads_the_pixels_the_projection_would() -> None:
    # A registered frame (same intrinsics, identity T_color_depth) skips the projection into the colour image;
    # it must give exactly what the projection gives, on a depth image with holes and far pixels.
    rng = np.random.default_rng(3)
    f = _plane_frame(2.0, color_size=(32, 24))
    f.depth = rng.integers(0, 7000, size=f.depth.shape).astype(np.uint16)
    f.color = rng.integers(0, 256, size=f.color.shape).astype(np.uint8)
    f.labels = rng.integers(0, 40, size=f.labels.shape).astype(np.uint16)
    p = frame_to_points(f, pixel_stride=1)
    v, u = np.nonzero((f.depth / 1000.0 > 0.1) & (f.depth / 1000.0 < 6.0))
    z = f.depth[v, u] / 1000.0
    K = f.depth_intrinsics
    xyz, ui, vi = _project_to_color(f, np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1))
    assert np.array_equal(p.xyz, xyz)
    assert np.array_equal(p.rgb, f.color[vi, ui] / 255.0)
    assert np.array_equal(p.labels, f.labels[vi, ui])


def test_voxel_downsample_keeps_one_point_per_voxel() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 1, size=(5000, 3))
    idx = voxel_indices(xyz, 0.25)
    assert len(idx) == 64
    keys = np.floor(xyz[idx] / 0.25)
    assert len(np.unique(keys, axis=0)) == 64
    # the first point met in each voxel, in the points' order
    _, first = np.unique(np.floor(xyz / 0.25), axis=0, return_index=True)
    assert np.array_equal(idx, np.sort(first))
    f = _plane_frame(2.0, color_size=(32, 24))
    d = voxel_downsample(frame_to_points(f, pixel_stride=1), 0.5)
    assert 0 < len(d) < 32 * 24 and d.rgb.shape == (len(d), 3)


def test_a_points_voxel_doubles_each_time_its_depth_noise_doubles() -> None:
    sigma = np.array([0.005, 0.02, 0.021, 0.04, 0.041, 0.08, 5.0])
    assert noise_octaves(sigma, 0.02).tolist() == [0, 0, 1, 1, 2, 2, MAX_NOISE_OCTAVE]
    assert not noise_octaves(sigma, 0.0).any()  # 0: every point alike


def _patch(x0: float, z: float) -> np.ndarray:
    """A 1 m square of points 1 cm apart, at depth z (camera axes: z forward)."""
    g = np.stack(np.meshgrid(np.arange(100) * 0.01, np.arange(100) * 0.01), axis=-1).reshape(-1, 2)
    return np.column_stack([g[:, 0] + x0, g[:, 1], np.full(len(g), z)])


def test_a_noisier_points_voxel_keeps_fewer_of_its_surfaces_points() -> None:
    xyz = np.vstack([_patch(0.0, 1.0), _patch(3.0, 5.0)])
    points = FramePoints(xyz, np.zeros((len(xyz), 3)), np.full(len(xyz), -1))
    far = xyz[:, 2] > 2.0
    octaves = np.where(far, 2, 0)
    out = voxel_budget(points, 0.04, 10_000, octaves=octaves)
    # the near square on 4 cm voxels (25 x 25), the far one on 16 cm voxels (7 x 7): a sixteenth of the weight
    assert (out.xyz[:, 2] < 2.0).sum() == 625 and (out.xyz[:, 2] > 2.0).sum() == 49
    # without octaves the plain grid, and the same point set in the frame's order either way
    assert np.array_equal(voxel_budget(points, 0.04, 10_000).xyz, voxel_downsample(points, 0.04).xyz)
    kept = octave_voxel_indices(xyz, 0.04, octaves)
    assert np.all(np.diff(kept) > 0) and np.array_equal(out.xyz, xyz[kept])
    # a frame seen only from afar is not starved: its octaves come down until a quarter of the budget is kept
    only_far = points.subset(np.flatnonzero(far))
    kept = voxel_budget(only_far, 0.04, 1000, octaves=np.full(int(far.sum()), MAX_NOISE_OCTAVE))
    assert len(kept) == 169  # octave 1 (8 cm, 13 x 13): at least a quarter of the 625 the plain grid keeps


def test_bad_frames_raise_invalid_frame() -> None:
    Kd = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    good = dict(depth=np.ones((24, 32), np.uint16), color=np.zeros((24, 32, 3), np.uint8), depth_intrinsics=Kd,
                color_intrinsics=Kd)
    with pytest.raises(InvalidFrame):
        Frame(**{**good, "depth": np.ones((24, 32), np.float32)})
    with pytest.raises(InvalidFrame):
        Frame(**{**good, "depth": np.zeros((24, 32), np.uint16)})
    with pytest.raises(InvalidFrame):
        Frame(**{**good, "color": np.zeros((10, 32, 3), np.uint8)})


@pytest.mark.parametrize("voxel_m", [0.01, 0.07, 0.5, 100.0])
def test_voxel_indices_keep_the_first_point_of_each_voxel_as_a_sort_would(voxel_m: float) -> None:
    """`first_of_each`'s hash set gives what np.unique(return_index=True) gives: the index of each voxel's first
    point, ascending (negative coordinates, one voxel for all, one point a voxel, a repeated point)."""
    rng = np.random.default_rng(1)
    xyz = np.vstack([rng.normal(size=(20000, 3)), [[0.3, -0.2, 0.1]] * 3])
    _, first = np.unique(np.floor(xyz / voxel_m), axis=0, return_index=True)
    assert np.array_equal(voxel_indices(xyz, voxel_m), np.sort(first))
    assert np.array_equal(voxel_indices(xyz[:1], voxel_m), [0])
    assert len(voxel_indices(np.zeros((0, 3)), voxel_m)) == 0


def test_first_of_each_takes_any_int64_key() -> None:
    """The hash set keeps no sentinel key: -1 and the extremes of int64 are keys like any other."""
    from cadreg.localize.points import first_of_each

    keys = np.array([-1, 5, -1, 3, 5, np.iinfo(np.int64).min, np.iinfo(np.int64).max, -1, 0], dtype=np.int64)
    assert first_of_each(keys).tolist() == [0, 1, 3, 5, 6, 8]
    keys = np.random.default_rng(2).integers(-(2 ** 62), 2 ** 62, size=5000)
    _, first = np.unique(keys, return_index=True)
    assert np.array_equal(first_of_each(keys), np.sort(first))
