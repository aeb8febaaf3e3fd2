"""Fallback global registration: the floor-constrained (x, y, yaw) search and FPFH + RANSAC."""

from __future__ import annotations

import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.geometry import invert_T, make_T, pose_errors, rotation_between, transform_points
from cadreg.localize.fallback import FpfhRansac, floor_grid_search
from cadreg.localize.points import frame_to_points, voxel_downsample
from cadreg.localize.refine import RefineMap
from cadreg.localize.score import DistanceField
from cadreg.localize.synthetic import look_pose, make_scene, render_frame


@pytest.fixture(scope="module")
def scene():
    return make_scene(7, n_objects=8)


def test_floor_grid_search_finds_the_pose_among_its_best(scene) -> None:
    site = scene.site
    field = DistanceField(site.map.points)
    rmap = RefineMap(site.map.points, site.map.colors / 255.0)
    T = look_pose(np.array([3.1, 2.2, 1.45]), np.radians(200.0), np.radians(30.0))
    frame = render_frame(scene, T, intrinsics=CameraIntrinsics(160, 120, 144.0, 144.0, 79.5, 59.5))
    pts = voxel_downsample(frame_to_points(frame), 0.05).xyz
    up = np.array([0, 0, 1.0])
    R_level = rotation_between(T[:3, :3].T @ up, up)  # the true up, as a floor fit would give it
    sample = pts[np.random.default_rng(0).choice(len(pts), 300, replace=False)]
    hyp = floor_grid_search(field, sample @ R_level.T, up, 1.45, R_level=R_level, keep=50)
    assert len(hyp) == 50 and np.allclose(hyp.t[:, 2], 1.45)
    # a coarse GICP from the best few brings one of them onto the true pose
    import small_gicp

    src, _ = small_gicp.preprocess_points(pts, 0.08)
    errs = [pose_errors(rmap.coarse_align(src, hyp.T(i)), T) for i in range(10)]
    assert min(e[0] for e in errs) < 0.05


def test_fpfh_ransac_registers_a_piece_of_the_map(scene) -> None:
    """A piece of the map (objects and walls around a spot) moved by a known transform is found again."""
    site = scene.site
    P = np.asarray(site.map.points, dtype=np.float64)
    centre = np.asarray(site.graph.nodes[0].centroid)
    piece = P[np.linalg.norm(P[:, :2] - centre[:2], axis=1) < 1.8]
    T = look_pose(centre + [0.5, -1.0, 1.0], np.radians(70.0), np.radians(30.0))  # T_map_camera
    reg = FpfhRansac(P, voxel_m=0.05, seed=1)
    T_est, fitness = reg.register(transform_points(invert_T(T), piece), max_iterations=20000)
    te, re_ = pose_errors(T_est, T)
    assert fitness > 0.5 and te < 0.05 and re_ < 2.0, (te, re_, fitness)


def test_an_fpfh_pose_that_turns_the_camera_over_is_refused(scene, monkeypatch) -> None:
    """FPFH + RANSAC ignores gravity; on a bare wall it may return the camera upside down. Such a pose is refused."""
    from dataclasses import replace

    from cadreg.config import FallbackConfig, LabelFreeConfig, LocalizeConfig
    from cadreg.localize import Localizer

    T = look_pose(np.array([3.1, 2.2, 1.45]), np.radians(200.0), np.radians(30.0))
    frame = render_frame(scene, T, intrinsics=CameraIntrinsics(160, 120, 144.0, 144.0, 79.5, 59.5))
    frame = replace(frame, labels=None, gravity_camera=T[:3, :3].T @ np.array([0.0, 0.0, -1.0]))
    # min_graph_fitness 1 and no label-free search (with up known, FPFH + RANSAC runs only without it): the
    # fallback comes to FPFH + RANSAC
    loc = Localizer.from_site(scene.site, LocalizeConfig(fallback=FallbackConfig(min_graph_fitness=1.0),
                                                         label_free=LabelFreeConfig(enabled=False)))
    upside_down = T @ make_T(R=np.diag([1.0, -1.0, -1.0]))  # turned 180° about the camera's x axis
    monkeypatch.setattr(FpfhRansac, "register", lambda self, xyz, **kw: (upside_down, 1.0))
    r = loc.localize(frame)
    assert any("fpfh-ransac refused" in n and "client" in n for n in r.diagnostics.notes), r.diagnostics.notes
    assert all(h.source != "fallback:fpfh-ransac" for h in r.hypotheses)
    # the same pose the right way up is taken as a hypothesis
    monkeypatch.setattr(FpfhRansac, "register", lambda self, xyz, **kw: (T, 1.0))
    r = loc.localize(frame)
    assert not any("refused" in n for n in r.diagnostics.notes)
    assert any(h.source == "fallback:fpfh-ransac" for h in r.hypotheses)


def test_a_coarse_gicp_far_off_the_map_pairs_only_the_points_near_it(scene, monkeypatch) -> None:
    """small_gicp's KD-tree visits most of the map for each point far from it: a hypothesis with most of its
    points beyond the field's truncation aligns the others, with the result of aligning them alone; one with
    none near the map stays where it is."""
    from types import SimpleNamespace

    import small_gicp

    import cadreg.localize.refine as refine_module
    from cadreg.localize import Localizer

    loc = Localizer.from_site(scene.site)
    T = look_pose(np.array([3.1, 2.2, 1.45]), np.radians(200.0), np.radians(30.0))
    frame = render_frame(scene, T, intrinsics=CameraIntrinsics(160, 120, 144.0, 144.0, 79.5, 59.5))
    near = voxel_downsample(frame_to_points(frame), 0.08).xyz
    far = near + np.array([0.0, 0.0, 30.0])  # 30 m on along the view: beyond every wall
    sizes: list[int] = []
    align = refine_module.small_gicp.align
    monkeypatch.setattr(refine_module.small_gicp, "align",
                        lambda target, source, *a, **k: sizes.append(source.size()) or align(target, source, *a, **k))

    def cloud(xyz: np.ndarray) -> small_gicp.PointCloud:
        pc = small_gicp.PointCloud(xyz)
        small_gicp.estimate_covariances(pc, num_neighbors=10)
        return pc

    scan = SimpleNamespace(center_camera=near.mean(axis=0))
    T0 = make_T(np.eye(3), np.array([0.05, -0.04, 0.02])) @ T
    both = np.vstack([near, far])
    moved = loc._coarse_align(cloud(both), both, T0, scan)
    assert sizes == [len(near)]
    alone = loc.refine_map.coarse_align(cloud(near), T0)
    np.testing.assert_allclose(moved, alone, atol=1e-9)
    assert pose_errors(moved, T)[0] < 0.02
    np.testing.assert_array_equal(loc._coarse_align(cloud(far), far, T0, scan), T0)
    assert len(sizes) == 2  # no GICP for the pose with nothing near the map


def test_each_kept_leaf_has_its_best_same_place_alternate_verified_too() -> None:
    """`FallbackStage._same_place_alternates`: of the polished leaves not kept, the best-scoring one within the
    distinct-pose radius of a kept leaf but beyond the refinement's reach stands beside it; one within the reach is
    the kept leaf again, and one beyond the radius is another place (the region ranking's to keep or drop)."""
    from types import SimpleNamespace

    from cadreg.config import LocalizeConfig
    from cadreg.localize.fallback_stage import FallbackStage
    from cadreg.localize.match import Hypotheses, yaw_rotations

    mc = LocalizeConfig().match
    x = np.array([0.0, 0.05, 0.18, 0.22, mc.distinct_translation_m + 0.2, 3.0, 3.2])
    t = np.column_stack([x, np.zeros(len(x)), np.full(len(x), 1.4)])
    hyp = Hypotheses(yaw_rotations(np.array([0, 0, 1.0]), np.zeros(len(x))), t, np.full((len(x), 2), -1))
    hyp.geometric = np.array([0.9, 0.95, 0.7, 0.8, 0.99, 0.6, 0.5])
    owner = SimpleNamespace(config=LocalizeConfig())
    assert FallbackStage._same_place_alternates(owner, hyp, [0]) == [3]  # 0.22 m beats 0.18 m; 0.05 m is leaf 0
    assert FallbackStage._same_place_alternates(owner, hyp, [0, 5]) == [3, 6]
    # each kept leaf has its own: 0.05 m is 0.13 m from the leaf at 0.18 m, and 0.5 m lies 0.28 m from the one at 0.22
    assert FallbackStage._same_place_alternates(owner, hyp, [0, 2, 3]) == [1, 4]
    assert FallbackStage._same_place_alternates(owner, hyp, list(range(len(x)))) == []


def test_a_depth_image_of_noise_is_sampled_and_described_within_bounds(scene, monkeypatch) -> None:
    """A hostile client's depth image of noise fills its whole frustum with points: the search samples a large
    image no denser than a 640 x 480 one (`points.stride_for`), and the last resort describes at most
    FallbackConfig.fpfh_max_points of its voxels (one of 640 x 480 noise took 5.4 s, one of 1280 x 960 over 20 s),
    on a grid coarse enough, and a frame of surfaces on its 5 cm grid whole."""
    from dataclasses import replace

    from cadreg.config import LocalizeConfig
    from cadreg.localize import Localizer
    from cadreg.localize.points import stride_for

    config = LocalizeConfig()
    described: list[int] = []
    features = FpfhRansac._features
    monkeypatch.setattr(FpfhRansac, "_features", lambda self, pcd: described.append(len(pcd.points)) or features(self, pcd))
    loc = Localizer.from_site(scene.site, config)
    K = CameraIntrinsics(1280, 960, 1155.7, 1155.7, 639.5, 479.5)
    rng = np.random.default_rng(0)
    noise = replace(render_frame(scene, look_pose(np.array([3.1, 2.2, 1.45]), 0.0, np.radians(30.0)), intrinsics=K),
                    depth=rng.integers(100, 6000, (960, 1280)).astype(np.uint16), labels=None, gravity_camera=None)
    assert stride_for(noise, config.frame.pixel_stride, config.frame.stride_reference_pixels) == 4
    r = loc.localize(noise)
    assert r.status.value != "ok"
    assert r.diagnostics.frame_points <= (640 // 2) * (480 // 2)  # as many as a 640 x 480 image's at stride 2
    assert described and described[-1] <= config.fallback.fpfh_max_points  # the frame's, after the map's own
    surfaces = voxel_downsample(frame_to_points(render_frame(scene, look_pose(np.array([3.1, 2.2, 1.45]), 0.0,
                                                                              np.radians(30.0)))), 0.03).xyz
    whole = len(voxel_downsample(frame_to_points(render_frame(scene, look_pose(np.array([3.1, 2.2, 1.45]), 0.0,
                                                                               np.radians(30.0)))), 0.05))
    loc.fpfh().register(surfaces, max_points=config.fallback.fpfh_max_points, max_iterations=1000)
    assert abs(described[-1] - whole) <= 0.05 * whole  # under the bound: its 5 cm voxels, none left out


def test_the_sampling_stride_grows_with_the_image_and_names_itself_when_too_few_points_remain(scene) -> None:
    from dataclasses import replace
    from types import SimpleNamespace

    from cadreg.errors import InvalidFrame
    from cadreg.localize import Localizer
    from cadreg.localize.points import stride_for

    frame = render_frame(scene, look_pose(np.array([3.1, 2.2, 1.45]), 0.0, np.radians(30.0)),
                         intrinsics=CameraIntrinsics(160, 120, 144.0, 144.0, 79.5, 59.5))
    shaped = lambda w, h: SimpleNamespace(depth=np.empty((h, w), np.uint16))  # noqa: E731  (its size is all it reads)
    sizes = ((160, 120), (640, 480), (848, 480), (640, 576), (1280, 720), (1280, 960), (4096, 3072))
    assert [stride_for(shaped(w, h), 2, 640 * 480) for w, h in sizes] == [2, 2, 2, 2, 3, 4, 13]
    assert stride_for(shaped(1280, 960), 7, 640 * 480) == 14  # the tracking stride grows alike
    sparse = np.zeros_like(frame.depth)
    sparse[::16, ::16] = frame.depth[::16, ::16]  # 80 valid pixels, of which the sampling sees the even ones
    with pytest.raises(InvalidFrame, match=r"only \d+ valid depth points .* \(one depth pixel in 2 along each row"):
        Localizer.from_site(scene.site).localize(replace(frame, depth=sparse))
