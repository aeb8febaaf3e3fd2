"""The distance field that scores hypotheses (localize/score.py): it reads the distance to the nearest map point to
within about half a voxel, the truncation beyond it and outside the grid, and the truncation for coordinates that
are not finite (a degenerate hypothesis must score zero, not read an arbitrary cell)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cadreg.localize.score import DistanceField, building_field, inlier_score, score_poses


def test_field_reads_the_nearest_map_distance_and_the_truncation_outside() -> None:
    rng = np.random.default_rng(0)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(4000, 3))
    field = DistanceField(room, voxel_m=0.03, truncate_m=0.5)
    probes = rng.uniform([-0.25, -0.25, -0.25], [2.25, 1.75, 1.25], size=(20000, 3))  # inside the 0.3 m margin
    exact = np.minimum(cKDTree(room).query(probes)[0], 0.5)
    # the grid's distance is exact at cell centres; a probe lies up to half a cell diagonal from its centre
    assert np.max(np.abs(field.lookup(probes) - exact)) <= np.sqrt(3) * 0.03 / 2 + 0.03
    far = np.array([[50.0, 0.5, 0.5], [0.5, -40.0, 0.5], [np.nan, 0.5, 0.5], [0.5, np.inf, 0.5], [0.5, 0.5, -np.inf]])
    assert np.all(field.lookup(far) == np.float32(0.5))


@pytest.mark.parametrize("stored", [False, True])
def test_a_coarse_field_is_a_lower_bound_within_its_cell(stored: bool) -> None:
    rng = np.random.default_rng(2)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(3000, 3))
    field = (DistanceField.from_grid(building_field([room], voxel_m=0.03)) if stored
             else DistanceField(room, voxel_m=0.03))
    coarse = field.coarsened(4)
    assert coarse.voxel_m == pytest.approx(0.12) and coarse.grid.dtype == field.grid.dtype
    assert np.all(coarse.dims == -(-field.dims // 4)) and coarse.grid.size == np.prod(coarse.dims + 2)
    probes = rng.uniform([-0.5, -0.5, -0.5], [2.5, 2.0, 1.5], size=(20000, 3))
    fine, low = field.lookup(probes), coarse.lookup(probes)
    assert np.all(low <= fine + 1e-6)
    # The least distance of a cell's fine cells: within its diagonal of every fine value in it.
    assert np.max(fine - low) <= np.sqrt(3) * 0.12 + 0.03
    assert np.any(fine - low > 0.03)  # and coarse: not the fine field again
    # Beyond the map, the truncation distance, as the fine field reads it.
    assert np.all(coarse.lookup(np.array([[50.0, 0.5, 0.5], [np.nan, 0.5, 0.5]])) == np.float32(0.5))


@pytest.mark.parametrize("stored", [True, False])
@pytest.mark.parametrize("spacing_m", [0.03, 0.05, 0.1])
def test_surface_points_are_the_occupied_cells_one_per_cube(spacing_m: float, stored: bool) -> None:
    rng = np.random.default_rng(6)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(3000, 3))
    field = DistanceField.from_grid(building_field([room], voxel_m=0.03)) if stored else DistanceField(room)
    got = field.surface_points(spacing_m)
    # Written out: the cells within half a voxel of the map, one per thinned cube (its first corner), in order.
    d = field.dims + 2
    within = 0.015 if field.step_m is None else 0.015 / field.step_m  # metres in a float field, steps in a stored one
    ijk = np.stack(np.unravel_index(np.flatnonzero(field.grid <= within), tuple(d)), axis=1)
    thin = max(1, int(round(spacing_m / 0.03)))
    expected = field.origin + (np.unique(ijk // thin, axis=0) * thin - 1 + 0.5) * 0.03
    assert np.array_equal(got, expected)
    # Each within its cube's diagonal of a map point (an occupied cell's point lies anywhere in it).
    assert np.max(cKDTree(room).query(got)[0]) <= 0.03 * np.sqrt(3) * (thin - 0.5) + 1e-6


def test_score_poses_scores_each_pose_like_one_lookup() -> None:
    rng = np.random.default_rng(1)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(4000, 3))
    field = DistanceField(room, voxel_m=0.03)
    pts = room[rng.choice(len(room), 300)]
    R = np.stack([np.eye(3)] * 3)
    t = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [5.0, 5.0, 5.0]])
    scores = score_poses(field, pts, R, t, tau_m=0.1)
    for k in range(3):
        assert scores[k] == pytest.approx(inlier_score(field.lookup(pts + t[k]), 0.1), abs=1e-6)
    assert scores[0] > 0.9 and scores[2] == 0.0


def test_score_poses_reads_the_cells_lookup_reads_under_any_pose() -> None:
    """`field_kernels.score_poses` folds the division by the voxel into each pose's constants; under arbitrary
    turned and shifted poses (the points off the cell boundaries) it reads the cells `lookup`'s division does."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(4000, 3))
    field = DistanceField(room, voxel_m=0.03)
    pts = rng.normal(scale=0.4, size=(200, 3))
    R = Rotation.random(300, random_state=3).as_matrix()
    t = rng.uniform([-0.5, -0.5, -0.5], [2.5, 2.0, 1.5], size=(300, 3))
    scores = score_poses(field, pts, R, t, tau_m=0.1)
    expected = [inlier_score(field.lookup(pts @ R[k].T + t[k]), 0.1) for k in range(len(R))]
    assert np.allclose(scores, expected, rtol=0, atol=1e-6)  # (a float32 grid: lookup returns float32)
    assert scores.min() < 0.05 and scores.max() > 0.3  # (poses off the map and on it)


def test_a_stored_field_scores_poses_from_its_table_as_the_formula_does() -> None:
    """A building's quantized field is scored through a table of its 256 values (`field_kernels.score_poses` with
    a table): the same scores, bit for bit, as the formula per read, for each tau."""
    from scipy.spatial.transform import Rotation

    from cadreg.localize import field_kernels

    rng = np.random.default_rng(2)
    room = rng.uniform([0, 0, 0], [2, 1.5, 1], size=(4000, 3))
    field = DistanceField.from_grid(building_field([room]))
    assert field.step_m is not None
    pts = room[rng.choice(len(room), 200)] + rng.normal(0, 0.05, (200, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.05, (50, 3))).as_matrix()
    t = rng.normal(0, 0.1, (50, 3))
    for tau in (0.05, 0.1, 0.15):
        by_formula = np.empty(len(R))
        field_kernels.score_poses(*field.kernel_args(), pts, R, np.arange(len(R)), t, tau, field_kernels.NO_TABLE,
                                  by_formula)
        scores = score_poses(field, pts, R, t, tau_m=tau)
        assert np.array_equal(scores, by_formula)
        assert 0.0 < scores.min() and scores.max() <= 1.0
        assert scores[0] == pytest.approx(inlier_score(field.lookup(pts @ R[0].T + t[0]), tau), abs=1e-6)


def test_see_through_counts_map_in_front_of_the_depth_but_not_a_silhouette() -> None:
    """`ViewCheck.see_through`: map points in front of the measured depth count, except on the far side of a
    depth edge, where a point on the near surface's rim lands a cell past it as often as not (a building's low
    walls, a scan's holes)."""
    from cadreg.camera import CameraIntrinsics
    from cadreg.localize.score import ViewCheck

    K = CameraIntrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
    # Measured: a wall 2 m ahead on the left half of the view, open space 5 m deep on the right half.
    zbuf = np.full((15, 20), 5.0)
    zbuf[:, :10] = 2.0

    def points_at(depth: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        x, y = (u - K.cx) / K.fx * depth, (v - K.cy) / K.fy * depth
        return np.column_stack([x, y, np.full(len(u), depth)])

    rng = np.random.default_rng(0)
    v = rng.uniform(0, 120, 400)
    # the wall's rim, mapped a few pixels into the first cell of open space: no violation
    rim = points_at(2.0, rng.uniform(80, 86, 400), v)
    assert ViewCheck(rim).see_through(np.eye(4), zbuf, K) == 0.0
    # a map wall 2 m ahead across the open half: the sensor saw through it
    wall = points_at(2.0, rng.uniform(96, 160, 400), v)
    assert ViewCheck(wall).see_through(np.eye(4), zbuf, K) > 0.9


def test_view_checks_project_as_numpy_projects() -> None:
    """The compiled projections of `ViewCheck` (`view_kernels.py`) against the numpy passes they replace: the same
    cells hold the same nearest depths (to a rounding of the transform), and see-through counts the same points."""
    from scipy.ndimage import minimum_filter
    from scipy.spatial.transform import Rotation

    from cadreg.camera import CameraIntrinsics
    from cadreg.localize.score import ViewCheck

    K = CameraIntrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
    rng = np.random.default_rng(4)
    world = rng.uniform([-3, -3, -1], [3, 3, 2], size=(20000, 3))
    check = ViewCheck(world, sample=5000)

    def zbuffer(p: np.ndarray, cell_px: int) -> np.ndarray:  # the numpy pass, as it was
        rows, cols = int(np.ceil(K.height / cell_px)), int(np.ceil(K.width / cell_px))
        u = ((K.fx * p[:, 0] / p[:, 2] + K.cx) // cell_px).astype(np.int64)
        v = ((K.fy * p[:, 1] / p[:, 2] + K.cy) // cell_px).astype(np.int64)
        inside = (u >= 0) & (u < cols) & (v >= 0) & (v < rows)
        zb = np.full(rows * cols, np.inf)
        np.minimum.at(zb, v[inside] * cols + u[inside], p[inside, 2])
        return zb.reshape(rows, cols)

    for k in range(5):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=k).as_matrix()
        T[:3, 3] = rng.uniform(-0.5, 0.5, 3)
        camera = (world - T[:3, 3]) @ T[:3, :3]
        assert np.allclose(ViewCheck.zbuffer(camera, K), zbuffer(camera[camera[:, 2] > 1e-3], 8), rtol=0, atol=1e-12)
        surface = (check.surface_xyz - T[:3, 3]) @ T[:3, :3]
        assert np.allclose(check.map_depth(T, K, cell_px=16), zbuffer(surface[surface[:, 2] > 0.2], 16), rtol=0,
                           atol=1e-12)
        zbuf = zbuffer(camera[(camera[:, 2] > 1e-3) & (rng.random(len(camera)) < 0.3)], 8) + 0.3
        sample = (check.map_xyz - T[:3, 3]) @ T[:3, :3]
        sample = sample[(sample[:, 2] > 0.2) & (sample[:, 2] < 4.0)]
        u = ((K.fx * sample[:, 0] / sample[:, 2] + K.cx) // 8).astype(np.int64)
        v = ((K.fy * sample[:, 1] / sample[:, 2] + K.cy) // 8).astype(np.int64)
        inside = (u >= 0) & (u < zbuf.shape[1]) & (v >= 0) & (v < zbuf.shape[0])
        measured = minimum_filter(zbuf, size=3, mode="nearest")[v[inside], u[inside]]
        seen = np.isfinite(measured)
        front = sample[inside, 2][seen] < measured[seen] - (0.1 + 0.04 * measured[seen])
        expected = float(front.mean()) if seen.sum() >= 50 else 0.0
        assert check.see_through(T, zbuf, K) == pytest.approx(expected, abs=1e-12)


def test_see_through_samples_the_maps_points_in_their_order_and_counts_them_in_any() -> None:
    """A large map's see-through sample is the seeded random choice of its points, taken in the map's order (read in
    order, not at random); the check counts them, so the same points in the choice's own order give the same share."""
    from cadreg.camera import CameraIntrinsics
    from cadreg.localize.score import ViewCheck

    K = CameraIntrinsics(160, 120, 100.0, 100.0, 79.5, 59.5)
    rng = np.random.default_rng(5)
    world = rng.uniform([-3, -3, 0.5], [3, 3, 4], size=(40000, 3))
    check = ViewCheck(world, sample=6000, seed=3)
    chosen = np.random.default_rng(3).choice(len(world), 6000, replace=False)
    assert np.array_equal(check.map_xyz, world[np.sort(chosen)])
    shuffled = ViewCheck(world[chosen], sample=6000)  # the same points in the choice's order: no sampling
    assert not np.array_equal(shuffled.map_xyz, check.map_xyz)
    zbuf = np.full((15, 20), 2.0)
    zbuf[:, :10] = np.inf
    shares = [check.see_through(np.eye(4), zbuf, K), shuffled.see_through(np.eye(4), zbuf, K)]
    assert 0.05 < shares[0] < 0.95 and shares[0] == shares[1]


def test_the_reference_camera_keeps_the_field_of_view_at_a_reference_images_pixels() -> None:
    """`reference_camera`: the same camera at about the reference image's pixels (a 640 x 480 one unchanged)."""
    from cadreg.camera import CameraIntrinsics
    from cadreg.localize.score import reference_camera

    K = CameraIntrinsics(640, 480, 585.0, 585.0, 320.0, 240.0)
    assert reference_camera(K) is K
    for w, h in ((80, 60), (256, 192), (4096, 3072)):
        small = K.scaled_to(w, h)
        R = reference_camera(small)
        assert (R.width, R.height) == (640, 480)
        assert R.fx == pytest.approx(585.0) and R.cx == pytest.approx(320.0)


@pytest.mark.realdata
def test_a_small_depth_image_is_compared_with_the_map_on_as_many_cells_as_a_full_one(
        scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """The free-space check's z-buffer cells span the same angle at any resolution (`reference_camera`): a view of
    scene0470 at 640 x 480 and shrunk to 80 x 60 is compared with the map on the same 80 x 60 cells of 8 pixels of
    the full image, and a pose slid 1 m sideways disagrees with the map's depth at both sizes. (In the small image's
    own pixels its z-buffer held 5 x 4 cells once pooled, too few to compare: no evidence against any pose. Real
    RedKitchen frames so shrunk were answered `ok` 0.4-1.05 m off.)"""
    from dataclasses import replace

    from cadreg import Site
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.localizer import Localizer
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics
    from tracking_rooms import render_turn

    loc = Localizer.from_site(Site.load(scene0470_site_dir))
    frames = render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                         scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", tmp_path / "turn", n=2)
    frame, T = RecordedFrames.open(frames).load(0)
    rows, cols = np.arange(60) * 8 + 4, np.arange(80) * 8 + 4  # nearest pixels, as a smaller sensor sees
    small = replace(frame, depth=frame.depth[np.ix_(rows, cols)], color=frame.color[np.ix_(rows, cols)],
                    labels=None, depth_intrinsics=frame.depth_intrinsics.scaled_to(80, 60),
                    color_intrinsics=frame.color_intrinsics.scaled_to(80, 60))
    slid = T.copy()
    slid[:3, 3] += T[:3, 0]
    for f in (frame, small):
        diag = Diagnostics(site_id="s", bundle_version="v")
        scan = loc._scan(f, diag, StageTimer(diag.stage_ms))
        assert scan.zbuf.shape == (60, 80)
        assert loc._depth_agreement(T, scan, scan.center_camera) > 0.8
        assert loc._depth_agreement(slid, scan, scan.center_camera) < 0.5
