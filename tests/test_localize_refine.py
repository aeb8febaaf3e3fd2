"""Fine refinement: each method recovers a perturbed pose on a synthetic scene; the hand-written colour GICP
agrees with small_gicp on the same input, and its colour term resolves what geometry cannot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cadreg.camera import CameraIntrinsics
from cadreg.geometry import make_T, pose_errors, transform_points
from cadreg.localize.color_gicp import ColorGicpTarget, color_gicp, plane_covariances, prepare_cloud, rgb_to_lab
from cadreg.localize.points import frame_to_points
from cadreg.localize.refine import RefineMap
from cadreg.localize.synthetic import look_pose, make_scene, render_frame


@pytest.fixture(scope="module")
def scene_and_frame():
    scene = make_scene(4)
    T = look_pose(np.array([2.0, 1.2, 1.5]), np.radians(60.0), np.radians(30.0))
    frame = render_frame(scene, T, intrinsics=CameraIntrinsics(240, 180, 216.0, 216.0, 119.5, 89.5), depth_noise_m=0.002)
    site = scene.site
    rmap = RefineMap(site.map.points, site.map.colors / 255.0, site.map.class_index)
    return scene, frame, T, rmap


def _perturbed(T: np.ndarray, seed: int = 0, t_m: float = 0.1, r_deg: float = 5.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    P = make_T(Rotation.from_rotvec(np.radians(r_deg) * a / np.linalg.norm(a)).as_matrix(), t_m * d / np.linalg.norm(d))
    return P @ T


@pytest.mark.parametrize("method", ["small_gicp", "color_gicp", "open3d_colored_icp"])
def test_methods_recover_a_perturbed_pose(scene_and_frame, method: str) -> None:
    _, frame, T, rmap = scene_and_frame
    pts = frame_to_points(frame)
    out = rmap.refine(pts, _perturbed(T), method=method, max_correspondence_m=0.3)
    te, re_ = pose_errors(out.T_map_camera, T)
    # Open3D's coloured ICP is there for comparison and is the least precise of the three on this scene.
    tol_m, tol_deg = (0.05, 2.0) if method == "open3d_colored_icp" else (0.01, 0.5)
    assert te < tol_m and re_ < tol_deg, (method, te, re_)
    if method != "open3d_colored_icp":
        assert out.covariance is not None and out.covariance.shape == (6, 6)
        assert np.all(np.linalg.eigvalsh(out.covariance) > 0)


def test_a_cropped_fine_target_refines_as_the_whole_map_does(scene_and_frame) -> None:
    scene, frame, T, rmap = scene_and_frame
    pts = frame_to_points(frame)
    site = scene.site
    cropping = RefineMap(site.map.points, site.map.colors / 255.0, site.map.class_index, crop_fine_target=True)
    T0 = _perturbed(T, seed=5, t_m=0.08, r_deg=3.0)
    a = cropping.refine(pts, T0, method="small_gicp").T_map_camera
    b = rmap.refine(pts, T0, method="small_gicp").T_map_camera
    te, re_ = pose_errors(a, b)
    assert te < 1e-3 and re_ < 0.05, (te, re_)
    # The crop holds the map around the placed frame only, and is not kept; a map that no longer crops builds its
    # whole target, kept.
    placed = transform_points(T, pts.xyz)
    around = cropping.fine_target_around(placed, 0.3)
    assert around is not cropping.fine_target_around(placed, 0.3)
    cropping.crop_fine_target = False
    whole = cropping.fine_target_around(placed, 0.3)
    assert around[0].size() < 0.8 * whole[0].size() and cropping.fine_target_around(placed, 0.3) is whole


def test_the_crop_holds_every_map_point_within_its_margin_of_the_frame(scene_and_frame) -> None:
    scene, frame, T, rmap = scene_and_frame
    placed = transform_points(T, frame_to_points(frame).xyz)
    xyz = scene.site.map.points
    gap, _ = cKDTree(placed).query(xyz)
    for margin in (0.1, 0.3, 0.5):
        kept = np.zeros(len(xyz), dtype=bool)
        kept[rmap.near(placed, margin)] = True
        assert kept[gap <= margin].all()
        # Beyond the margin only what shares cells with it (at most 2.3 margins away), and not most of the box.
        assert gap[kept].max() <= 2.31 * margin
        assert kept.sum() < 0.9 * np.all((xyz >= placed.min(0) - margin) & (xyz <= placed.max(0) + margin), axis=1).sum()


def test_color_gicp_agrees_with_small_gicp(scene_and_frame) -> None:
    _, frame, T, rmap = scene_and_frame
    pts = frame_to_points(frame)
    T0 = _perturbed(T, seed=3, t_m=0.05, r_deg=2.0)
    a = rmap.refine(pts, T0, method="color_gicp").T_map_camera
    b = rmap.refine(pts, T0, method="small_gicp", max_correspondence_m=0.3).T_map_camera
    te, re_ = pose_errors(a, b)
    assert te < 0.01 and re_ < 0.5, (te, re_, pose_errors(a, T), pose_errors(b, T))


def test_colour_resolves_sliding_on_a_textured_plane() -> None:
    """A flat textured wall: GICP without colour cannot see an in-plane shift; colour GICP recovers it."""
    rng = np.random.default_rng(0)
    n = 40000
    xy = rng.uniform(0, 2, size=(n, 2))
    xyz = np.column_stack([xy, np.zeros(n)])
    stripes = (np.floor(xy[:, 0] / 0.1) % 2)[:, None]
    rgb = np.where(stripes > 0, [[0.9, 0.2, 0.1]], [[0.1, 0.3, 0.9]])
    target = ColorGicpTarget(prepare_cloud(xyz, rgb, 0.02), color_weight_m=0.1)
    # The source is a patch of the same wall; the true pose is identity, the start is shifted 4 cm along x.
    patch = (xy[:, 0] > 0.5) & (xy[:, 0] < 1.5) & (xy[:, 1] > 0.5) & (xy[:, 1] < 1.5)
    source = prepare_cloud(xyz[patch], rgb[patch], 0.02)
    start = make_T(t=[0.04, 0.0, 0.0])
    out = color_gicp([target], [source], start, correspondence_factor=3.0, max_iterations=60)
    assert abs(out.T_target_source[0, 3]) < 0.01
    colourless = ColorGicpTarget(prepare_cloud(xyz, np.full_like(rgb, 0.5), 0.02), color_weight_m=0.1)
    src_grey = prepare_cloud(xyz[patch], np.full_like(rgb[patch], 0.5), 0.02)
    out_grey = color_gicp([colourless], [src_grey], start, correspondence_factor=3.0, max_iterations=60)
    assert abs(out_grey.T_target_source[0, 3]) > 0.03  # geometry alone leaves the shift


def test_building_blocks() -> None:
    lab = rgb_to_lab(np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    assert np.allclose(lab[0], [100, 0, 0], atol=0.05) and np.allclose(lab[1], [0, 0, 0], atol=1e-6)
    assert np.allclose(lab[2], [53.24, 80.09, 67.20], atol=0.1)
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 1, (500, 2)), np.zeros(500)])
    C = plane_covariances(plane)
    assert np.allclose(C[:, 2, 2], 1e-3, atol=1e-6)  # normal direction squashed
    assert np.allclose(np.trace(C, axis1=1, axis2=2), 2 + 1e-3)


def test_fitness_and_agreement(scene_and_frame) -> None:
    _, frame, T, rmap = scene_and_frame
    pts = frame_to_points(frame)
    fit, rmse = rmap.fitness(transform_points(T, pts.xyz))
    assert fit > 0.95 and rmse < 0.03
    far = rmap.fitness(transform_points(make_T(t=[0.0, 0.0, 5.0]) @ T, pts.xyz))
    assert far[0] == 0.0
    cls = np.full(len(pts), -1)
    geo, sem, col = rmap.agreement(transform_points(T, pts.xyz), rgb_to_lab(pts.rgb), cls)
    assert geo > 0.95 and col > 0.7
    wrong = rmap.agreement(transform_points(T, pts.xyz), rgb_to_lab(1.0 - pts.rgb), cls)
    assert wrong[2] < col - 0.3
