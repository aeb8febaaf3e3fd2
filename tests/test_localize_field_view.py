"""The map's depth along a frame's rays, traced through the distance field, and poses pulled onto the field."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadreg.geometry import pose_errors
from cadreg.localize.field_view import DEFAULT_DEPTH_RANGE_M, MAX_DEPTH_RANGE_M, FieldView, align_on_field, sensor_range_m
from cadreg.localize.points import frame_to_points, voxel_downsample
from cadreg.localize.score import DistanceField, building_field
from cadreg.localize.synthetic import look_pose, make_scene, render_frame


@pytest.fixture(scope="module")
def scene():
    return make_scene(3)


@pytest.fixture(scope="module")
def field(scene) -> DistanceField:
    # The stored (quantized, one byte a cell) field of a building, as a composed site loads it.
    return DistanceField.from_grid(building_field([scene.site.cloud("both").points]))


@pytest.fixture(scope="module")
def view_and_pose(scene):
    T = look_pose(np.array([1.0, 1.0, 1.5]), np.radians(35.0), np.radians(20.0))
    # A depth camera 3 cm beside the colour camera: the rays start there.
    T_cd = np.eye(4)
    T_cd[0, 3] = -0.03
    frame = render_frame(scene, T, T_color_depth=T_cd, labels=False)
    return frame, T


def test_the_render_at_the_true_pose_is_the_measured_depth(field, view_and_pose) -> None:
    frame, T = view_and_pose
    view = FieldView(frame, grid=(40, 30))
    rendered = view.render(field, T)[0]
    both = np.isfinite(rendered) & np.isfinite(view.measured)
    assert both.mean() > 0.9
    assert np.median(np.abs(rendered[both] - view.measured[both])) < 0.035  # the field's cells are 3 cm
    assert view.agreement(rendered[None])[0] > 0.7
    # 30 cm along the view and 10° of yaw away, the map shows something else on most rays
    T_off = T.copy()
    T_off[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix() @ T[:3, :3]
    T_off[:3, 3] += T[:3, 2] * 0.3
    assert view.agreement(view.render(field, T_off))[0] < 0.5


def test_two_renders_are_compared_ray_by_ray_and_an_empty_view_shows_nothing(field, view_and_pose) -> None:
    frame, T = view_and_pose
    view = FieldView(frame, grid=(40, 30))
    away = T.copy()
    away[:3, 3] += np.array([0.0, 0.0, 50.0])  # far above the map: every ray misses it
    r = view.render(field, np.stack([T, T, away]))
    assert r.shape == (3, len(view))
    assert np.isinf(r[2]).all()
    same = view.agreement(r[:2], r[0])
    assert np.allclose(same, 1.0)
    assert view.agreement(r[2:], r[0])[0] == 0.0
    assert view.agreement(r[2:], r[2])[0] == 1.0  # neither shows anything: nothing disagrees


def test_a_thinned_view_traces_every_other_ray_of_every_other_row(field, view_and_pose) -> None:
    frame, T = view_and_pose
    view = FieldView(frame, grid=(40, 30))
    thin = view.thinned(2)
    assert thin.shape == (15, 20) and len(thin) == 300 and view.shape == (30, 40) and len(view) == 1200
    full = view.render(field, T)[0].reshape(30, 40)
    assert np.array_equal(thin.render(field, T)[0], full[::2, ::2].ravel())
    assert np.array_equal(thin.measured, view.measured.reshape(30, 40)[::2, ::2].ravel())
    # the agreement of a quarter of the rays stays close to the whole view's, right pose and wrong
    T_off = T.copy()
    T_off[:3, 3] += T[:3, 0] * 0.2
    for pose in (T, T_off):
        assert abs(thin.agreement(thin.render(field, pose))[0] - view.agreement(view.render(field, pose))[0]) < 0.05
    # a render completed from the thinned one's rays is the whole render, exactly
    poses = np.stack([T, T_off])
    rays = view.thinned_rays(2)
    assert np.array_equal(view.measured[rays], thin.measured)
    assert np.array_equal(view.render_completing(field, poses, rays, thin.render(field, poses)),
                          view.render(field, poses))


def test_the_sensor_range_bounds_what_is_measured_and_rendered(field, view_and_pose) -> None:
    frame, T = view_and_pose
    short = FieldView(frame, grid=(40, 30), max_depth_m=1.0)
    assert np.all(short.measured[np.isfinite(short.measured)] <= 1.0)
    rendered = short.render(field, T)[0]
    assert np.all(rendered[np.isfinite(rendered)] <= 1.0 + 0.05)


def test_the_sensor_range_is_the_clients_else_the_default_or_what_the_frame_measured(view_and_pose) -> None:
    from dataclasses import replace

    frame, _ = view_and_pose
    frame = replace(frame, depth=np.where(frame.depth > 3000, 0, frame.depth).astype(np.uint16))

    def range_m(depth_range_m, depth=frame.depth) -> float:
        return FieldView(replace(frame, depth=depth, depth_range_m=depth_range_m)).max_depth_m

    measured = FieldView(frame, max_depth_m=MAX_DEPTH_RANGE_M).measured
    farthest = float(measured[np.isfinite(measured)].max())  # along the rays
    assert 2.0 < farthest <= 3.0
    assert range_m(None) == DEFAULT_DEPTH_RANGE_M
    assert range_m(5.0) == 5.0
    assert range_m(1.0) == farthest  # it measured farther than it said
    assert range_m(30.0) == MAX_DEPTH_RANGE_M
    far = frame.depth.copy()
    far[:, : far.shape[1] // 4] = 5500  # a far wall in view: the camera reaches that far
    assert range_m(None, far) == 5.5
    far[:, : far.shape[1] // 4] = 65535  # a 16-bit "no depth" that is not 0: no measure of the range
    assert range_m(None, far) == DEFAULT_DEPTH_RANGE_M
    assert sensor_range_m(None, np.zeros(10)) == DEFAULT_DEPTH_RANGE_M


def test_a_surface_beyond_the_sensors_range_on_a_ray_it_measured_nothing_on_is_not_held_against_a_pose(
        field, view_and_pose) -> None:
    """With the frame's far half cut off (a camera that measured nothing there), the map's surfaces beyond the
    camera's range on those rays count neither way; within its range they count against the pose."""
    from dataclasses import replace

    frame, T = view_and_pose
    z = frame.depth.astype(float) / frame.depth_scale
    cut_m = float(np.median(z[z > 0]))
    short = replace(frame, depth=np.where(z > cut_m, 0, frame.depth).astype(np.uint16))
    seen_to_cut = FieldView(replace(short, depth_range_m=cut_m), grid=(40, 30))
    seen_to_far = FieldView(replace(short, depth_range_m=MAX_DEPTH_RANGE_M), grid=(40, 30))
    assert seen_to_cut.max_depth_m == pytest.approx(cut_m, abs=1e-3)
    shown = seen_to_cut.render(field, T)[0]
    assert np.all(shown[np.isfinite(shown)] <= cut_m + 0.05)
    held = seen_to_far.render(field, T)[0]
    beyond = np.isfinite(held) & ~np.isfinite(seen_to_far.measured) & (held > cut_m + 0.05)
    assert beyond.sum() > 0.2 * len(held)
    whole = FieldView(frame, grid=(40, 30))
    at_truth = whole.agreement(whole.render(field, T))[0]  # (the synthetic map and frame agree on ~3/4 of the rays)
    assert seen_to_cut.agreement(shown)[0] == pytest.approx(at_truth, abs=0.03)
    assert seen_to_far.agreement(held)[0] < at_truth - 0.2


@pytest.mark.parametrize("up", [True, False])
def test_poses_far_off_are_pulled_onto_the_map(field, view_and_pose, up) -> None:
    frame, T = view_and_pose
    down = voxel_downsample(frame_to_points(frame), 0.03)
    points = down.xyz[np.random.default_rng(0).choice(len(down), 300, replace=False)]
    rng = np.random.default_rng(1)
    n = 12
    yaw = rng.uniform(-6, 6, n)
    R0 = Rotation.from_euler("z", yaw[:, None], degrees=True).as_matrix() @ T[:3, :3]
    t0 = T[:3, 3] + rng.uniform(-0.2, 0.2, (n, 3)) * np.array([1.0, 1.0, 0.3])
    R1, t1 = align_on_field(field, points, R0, t0, up=np.array([0.0, 0.0, 1.0]) if up else None,
                            iterations=15, reach_m=(0.5, 0.06))
    errors = []
    for k in range(n):
        A = np.eye(4)
        A[:3, :3], A[:3, 3] = R1[k], t1[k]
        errors.append(pose_errors(A, T))
    errors = np.array(errors)
    assert np.mean((errors[:, 0] < 0.05) & (errors[:, 1] < 2.0)) >= 0.9  # a start for the fine refinement
    start = np.array([pose_errors(np.block([[R0[k], t0[k][:, None]], [0, 0, 0, 1]]), T)[0] for k in range(n)])
    assert np.median(errors[:, 0]) < 0.25 * np.median(start)
    if up:  # turned about up only: the tilt of the start stays
        tilt = [np.degrees(np.arccos(np.clip((R1[k] @ R0[k].T)[2, 2], -1, 1))) for k in range(n)]
        assert max(tilt) < 1e-3


def test_no_poses_and_no_points_leave_the_poses_as_they_are(field) -> None:
    R, t = align_on_field(field, np.zeros((0, 3)), np.eye(3)[None], np.zeros((1, 3)))
    assert np.allclose(R, np.eye(3)) and np.allclose(t, 0)
    R, t = align_on_field(field, np.ones((5, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
    assert R.shape == (0, 3, 3)


def test_shared_rays_give_the_depth_agreement_and_the_map_coverage(field, view_and_pose) -> None:
    frame, T = view_and_pose
    view = FieldView(frame, grid=(40, 30))
    agreement, coverage = view.shared(view.render(field, T)[0])
    assert agreement > 0.8 and coverage > 0.9
    # a map that shows nothing along the rays says nothing against the pose, and covers none of the frame
    assert view.shared(np.full(len(view), np.inf)) == (1.0, 0.0)
    # the map everywhere 20 cm nearer than measured: covered, and disagreeing
    agreement, coverage = view.shared(view.measured - 0.2)
    assert agreement == 0.0 and coverage == 1.0


def test_a_float_field_and_a_stored_read_only_one_render_and_score_alike(scene, field, view_and_pose) -> None:
    """The compiled loops (`field_kernels`) read a field built in memory (float32 metres, writable) and a stored one
    (one byte a cell, a read-only memory map) the same way: renders agree ray by ray and scores to the quantization."""
    from cadreg.localize.score import score_poses

    floats = DistanceField(scene.site.cloud("both").points, voxel_m=field.voxel_m, margin_m=0.3)
    stored = DistanceField.from_grid(building_field([scene.site.cloud("both").points]))
    stored.grid = stored.grid.copy()
    stored.grid.flags.writeable = False  # as np.load(mmap_mode="r") gives it
    frame, T = view_and_pose
    view = FieldView(frame)
    a, b = view.render(floats, T)[0], view.render(stored, T)[0]
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.8 and abs(int(np.isfinite(a).sum()) - int(np.isfinite(b).sum())) <= 0.01 * len(a)
    assert np.median(np.abs(a[both] - b[both])) < 0.01
    pts = voxel_downsample(frame_to_points(frame), 0.05).xyz[:300]
    R = np.stack([T[:3, :3]] * 3)
    t = T[:3, 3] + np.array([[0.0, 0.0, 0.0], [0.3, 0.3, 0.3], [0.0, 0.0, 3.0]])
    s_float, s_stored = score_poses(floats, pts, R, t, tau_m=0.1), score_poses(stored, pts, R, t, tau_m=0.1)
    assert s_float[0] > 0.8 > s_float[1] and s_float[2] == 0.0
    assert np.allclose(s_float, s_stored, atol=0.05)


def test_a_surface_nearer_than_the_sensor_sees_hides_what_lies_behind_it() -> None:
    """A camera 30 cm from a wall that fills the left half of its view, a second wall 1.5 m ahead: the sensor
    measures nothing on the left (nearer than its 0.4 m) and 1.5 m on the right. The map along the rays shows the
    same: the near wall is no measurement, and it hides the far wall behind it. (Traced from 0.4 m on, the rays
    passed the near wall and met the far one: a view close to a room's wall saw the corridor behind it, and copies
    of a room with different neighbours looked 0.1 of view agreement apart.)"""
    from cadreg.camera import CameraIntrinsics
    from cadreg.frame import Frame

    step = 0.01
    a, b = np.meshgrid(np.arange(-1.5, 1.5, step), np.arange(-1.5, 1.5, step))
    near = np.column_stack([a.ravel(), b.ravel(), np.full(a.size, 0.3)])
    near = near[near[:, 0] < -0.02]  # the left half of the view
    far = np.column_stack([a.ravel(), b.ravel(), np.full(a.size, 1.5)])
    field = DistanceField.from_grid(building_field([np.concatenate([near, far])]))
    K = CameraIntrinsics(160, 120, 140.0, 140.0, 79.5, 59.5)
    u = np.arange(K.width)
    depth = np.where(u < K.cx, 0, 1500).astype(np.uint16)[None, :].repeat(K.height, axis=0)
    frame = Frame(depth=depth, color=np.zeros((K.height, K.width, 3), np.uint8), depth_intrinsics=K,
                  color_intrinsics=K)
    view = FieldView(frame, grid=(16, 12))
    rendered = view.render(field, np.eye(4))[0]
    left = view.dirs_camera[:, 0] < -0.1  # rays that meet the near wall
    right = view.dirs_camera[:, 0] > 0.0
    assert np.isinf(view.measured[left]).all() and np.isinf(rendered[left]).all()
    assert np.abs(rendered[right] - 1.5).max() < 0.05
    assert view.agreement(rendered[None])[0] > 0.95
