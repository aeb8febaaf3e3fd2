"""Coarse graph matching: hypotheses from rotation-invariant evidence, Sim under each hypothesis, the geometric
check on the distance field."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadreg.geometry import (invert_T, make_T, pose_errors, rotation_angle_deg, rotation_between,
                             transform_points)
from cadreg.localize.match import (PAIR_REACH_M, Hypotheses, MapGraph, distinct_best, distinct_pairs,
                                   gravity_hypotheses, kabsch_hypotheses, score_graph)
from cadreg.localize.score import DistanceField, score_poses


def _graph() -> MapGraph:
    rng = np.random.default_rng(0)
    cent = np.column_stack([rng.uniform(0, 6, 10), rng.uniform(0, 5, 10), rng.uniform(0.3, 0.8, 10)])
    cls = np.array([0, 0, 0, 1, 1, 2, 2, 0, 1, 2])
    return MapGraph([f"n{i}" for i in range(10)], cls, cent, np.full((10, 3), 0.5), cent[:, 2] + 0.25)


def _true_pose() -> np.ndarray:
    R_map_camera = Rotation.from_euler("zx", [37.0, -120.0], degrees=True).as_matrix()
    return make_T(R_map_camera, [2.0, 1.5, 1.4])


def test_gravity_pairs_recover_the_pose_and_sim_prefers_it() -> None:
    g = _graph()
    T = _true_pose()
    seen = [0, 3, 5]
    scan = transform_points(invert_T(T), g.centroid[seen])
    up_cam = T[:3, :3].T @ [0, 0, 1.0]
    R_level = rotation_between(up_cam, np.array([0, 0, 1.0]))
    hyp = gravity_hypotheses(scan, g.cls[seen], g, R_level=R_level, up=np.array([0, 0, 1.0]), camera_height_m=None)
    errs = np.array([pose_errors(hyp.T(i), T) for i in range(len(hyp))])
    best = int(np.argmin(errs[:, 0] + errs[:, 1] / 100))
    assert errs[best, 0] < 1e-6 and errs[best, 1] < 1e-4
    score_graph(hyp, scan, g.cls[seen], g, edge_max_m=10.0)
    assert hyp.s_v[best] == 1.0 and np.isclose(hyp.s_e[best], 1.0) and np.isclose(hyp.sim[best], 1.0)
    # Sim ranks the true pose at the top (ties allowed), well above the median hypothesis
    assert hyp.sim[best] >= hyp.sim.max() - 1e-9 and hyp.sim[best] > np.median(hyp.sim) + 0.3
    assert list(hyp.assignment[best]) == seen


def test_pairs_posed_together_recover_the_pose_under_a_tilted_up() -> None:
    """Every pair of objects is posed in one pass (`_pair_hypotheses`): under a map whose up is not z, each object
    seeded by its true node has a hypothesis at the true pose, which only a pair can give (the true yaw lies between
    the single objects' 10° steps)."""
    g = _graph()
    R_tilt = Rotation.from_euler("xy", [20.0, -15.0], degrees=True).as_matrix()
    up = R_tilt @ [0, 0, 1.0]
    tilted = MapGraph(g.ids, g.cls, g.centroid @ R_tilt.T, g.extent, g.top)
    T = make_T(R_tilt, [0.0, 0.0, 0.0]) @ _true_pose()
    seen = [0, 3, 5, 6]
    scan = transform_points(invert_T(T), tilted.centroid[seen])
    R_level = rotation_between(T[:3, :3].T @ up, up)
    hyp = gravity_hypotheses(scan, g.cls[seen], tilted, R_level=R_level, up=up, camera_height_m=None)
    for i, node in enumerate(seen[:-1]):
        rows = np.flatnonzero((hyp.seed[:, 0] == i) & (hyp.seed[:, 1] == node))
        errs = np.array([pose_errors(hyp.T(k), T) for k in rows])
        assert errs[:, 0].min() < 1e-6 and errs[:, 1].min() < 1e-4


def test_pair_index_holds_the_node_pairs_within_its_reach_and_far_pairs_match_too() -> None:
    rng = np.random.default_rng(5)
    cent = np.column_stack([rng.uniform(0, 30, 200), rng.uniform(0, 20, 200), rng.uniform(0.3, 0.8, 200)])
    g = MapGraph([f"n{i}" for i in range(200)], rng.integers(0, 3, 200), cent, np.full((200, 3), 0.5))
    D = np.linalg.norm(cent[:, None] - cent[None], axis=-1)
    for ca, cb in ((0, 0), (0, 2), (2, 1)):
        A, B, d = g.pairs_of_classes(ca, cb)
        a, b = np.nonzero((D <= PAIR_REACH_M) & (g.cls[:, None] == ca) & (g.cls[None, :] == cb))
        keep = a != b
        assert sorted(zip(A.tolist(), B.tolist())) == sorted(zip(a[keep].tolist(), b[keep].tolist()))
        assert np.all(np.diff(d) >= 0) and np.array_equal(d, D[A, B])
    # Beyond the reach: exactly the pairs of every node pair of the two classes within the tolerance of a length.
    for ca, cb in ((0, 0), (1, 2)):
        for d in (9.5, 14.0):
            a, b = np.nonzero((np.abs(D - d) < 0.3) & (g.cls[:, None] == ca) & (g.cls[None, :] == cb))
            keep = a != b
            A, B = g.pairs_at(ca, cb, d, 0.3)
            assert list(zip(A.tolist(), B.tolist())) == list(zip(a[keep].tolist(), b[keep].tolist())) and len(A)
    # Two objects within the reach and two beyond it: each pair finds the pose.
    T = make_T(Rotation.from_euler("zx", [-64.0, -110.0], degrees=True).as_matrix(), [12.0, 9.0, 1.4])
    up_cam = T[:3, :3].T @ [0, 0, 1.0]
    R_level = rotation_between(up_cam, np.array([0, 0, 1.0]))
    near = np.argwhere((D > 1.0) & (D < 3.0))[0]
    far = np.argwhere(D > PAIR_REACH_M + 1.0)[0]
    for seen in (near, far):
        scan = transform_points(invert_T(T), cent[seen])
        hyp = gravity_hypotheses(scan, g.cls[seen], g, R_level=R_level, up=np.array([0, 0, 1.0]), camera_height_m=None)
        errs = np.array([pose_errors(hyp.T(i), T) for i in range(len(hyp))])
        assert np.min(errs[:, 0] + errs[:, 1] / 100) < 1e-4


def test_each_object_is_assigned_the_nearest_node_of_its_class_within_the_radius() -> None:
    g = _graph()
    rng = np.random.default_rng(3)
    scan = rng.uniform([-2, -2, 0.5], [2, 2, 3.5], (5, 3))
    scan_cls = np.array([0, 1, 2, 0, 3])  # class 3: no node of it in the map
    R = Rotation.random(400, random_state=4).as_matrix()
    hyp = Hypotheses(R, rng.uniform([0, 0, 0], [6, 5, 2], (400, 3)), np.zeros((400, 2), dtype=np.int64))
    score_graph(hyp, scan, scan_cls, g, match_radius_m=0.8)
    placed = np.einsum("hij,nj->hni", hyp.R, scan) + hyp.t[:, None]
    d = np.linalg.norm(placed[:, :, None] - g.centroid[None, None], axis=-1)
    d[:, scan_cls[:, None] != g.cls[None, :]] = np.inf
    brute = np.where(d.min(axis=2) < 0.8, d.argmin(axis=2), -1)
    assert (brute >= 0).sum() > 20 and (brute == -1).sum() > 20  # both cases occur
    assert np.array_equal(hyp.assignment, brute)
    assert np.all(hyp.assignment[:, 4] == -1)


def test_single_object_yaw_sweep_and_floor_height() -> None:
    g = _graph()
    T = _true_pose()
    scan = transform_points(invert_T(T), g.centroid[[5]])
    R_level = rotation_between(T[:3, :3].T @ [0, 0, 1.0], np.array([0, 0, 1.0]))
    hyp = gravity_hypotheses(scan, g.cls[[5]], g, R_level=R_level, up=np.array([0, 0, 1.0]), camera_height_m=1.4,
                             yaw_step_deg=1.0)
    assert np.allclose(hyp.t[:, 2], 1.4)
    # 3 nodes of class 2 × 360 yaws
    assert len(hyp) == 3 * 360
    errs = np.array([pose_errors(hyp.T(i), T) for i in range(len(hyp))])
    assert (errs[:, 0] < 0.05).any() and errs[np.argmin(errs[:, 0]), 1] < 1.0


def test_single_objects_offsets_are_each_nodes_yaws_by_its_offsets_in_node_order() -> None:
    """A single object's dense sweep (`offset_step_m`): each node of its class, in node order, each yaw by each
    offset of the node's reach (half its largest horizontal extent, at most max_offset_m), none for a node too small
    for one; the nodes of one reach are posed together, with the values one node at a time gives."""
    from cadreg.localize.match import _horizontal_grid, yaw_rotations

    g = _graph()
    g.extent[:] = np.array([[0.5, 0.3, 0.4], [1.2, 0.2, 1.0], [0.05, 0.05, 0.3], [0.4, 0.9, 0.5], [3.0, 0.3, 1.0],
                            [0.5, 0.5, 0.5], [0.6, 0.2, 0.8], [0.3, 0.5, 0.9], [0.5, 0.1, 0.5], [0.2, 0.2, 0.2]])
    T = _true_pose()
    up = np.array([0, 0, 1.0])
    R_level = rotation_between(T[:3, :3].T @ up, up)
    scan = transform_points(invert_T(T), g.centroid[[0, 3]])
    step, reach_max, yaw_step = 0.1, 0.5, 30.0
    hyp = gravity_hypotheses(scan, g.cls[[0, 3]], g, R_level=R_level, up=up, camera_height_m=None,
                             yaw_step_deg=yaw_step, offset_step_m=step, max_offset_m=reach_max,
                             min_pair_horizontal_m=50.0)  # no pairs: the single objects' sweeps alone
    # Written out: per object, the plain sweep of every node of its class, then each node's offsets.
    yaws = np.radians(np.arange(0.0, 360.0, yaw_step))
    Ryaw = yaw_rotations(up, yaws)
    ts, seeds, Rs = [], [], []
    for i, c in enumerate(scan @ R_level.T):
        nodes = np.flatnonzero(g.cls == g.cls[[0, 3]][i])
        Rc = Ryaw @ c
        for k in nodes:
            ts.append(g.centroid[k] - Rc)
            seeds += [[i, k]] * len(yaws)
            Rs.append(Ryaw @ R_level)
        for k in nodes:
            offsets = _horizontal_grid(up, min(reach_max, 0.5 * float(np.max(g.extent[k][:2]))), step)
            if len(offsets) == 0:
                continue
            ts.append(((g.centroid[k] - Rc)[:, None, :] + offsets[None]).reshape(-1, 3))
            seeds += [[i, k]] * (len(yaws) * len(offsets))
            Rs.append(np.repeat(Ryaw @ R_level, len(offsets), axis=0))
    assert len(hyp) == sum(len(t) for t in ts) > len(yaws) * 7
    assert np.array_equal(hyp.t, np.concatenate(ts))
    assert np.array_equal(hyp.seed, np.array(seeds))
    assert np.array_equal(hyp.R, np.concatenate(Rs))


def test_kabsch_triples_without_gravity() -> None:
    g = _graph()
    T = _true_pose()
    seen = [1, 4, 6, 7]
    scan = transform_points(invert_T(T), g.centroid[seen])
    hyp = kabsch_hypotheses(scan, g.cls[seen], g)
    errs = np.array([pose_errors(hyp.T(i), T) for i in range(len(hyp))])
    assert errs[:, 0].min() < 1e-6


def test_kabsch_hypotheses_stop_at_the_cap() -> None:
    """A building's graph has a hundred nodes of a class: the triples agreeing with a scan triple run to tens of
    thousands. The cap holds (before, it ended only the innermost loop and one frame took 27 s), and the triples
    come in order: the first ones are those of the uncapped enumeration."""
    rng = np.random.default_rng(3)
    room = rng.uniform(0.0, 4.0, (6, 3))
    centroid = np.concatenate([room + np.array([6.0 * r, 0.0, 0.0]) for r in range(40)])  # 40 copies of a room
    g = MapGraph([str(i) for i in range(len(centroid))], np.tile(np.arange(6) % 3, 40), centroid)
    scan = centroid[[0, 1, 2, 3]] + rng.normal(0.0, 0.02, (4, 3))
    every = kabsch_hypotheses(scan, g.cls[[0, 1, 2, 3]], g, max_hypotheses=10**9)
    capped = kabsch_hypotheses(scan, g.cls[[0, 1, 2, 3]], g, max_hypotheses=100)
    assert len(every) > 300 and len(capped) == 100
    np.testing.assert_array_equal(capped.seed, every.seed[:100])
    np.testing.assert_allclose(capped.R, every.R[:100])


def test_sim_compares_edge_directions_under_the_hypothesis() -> None:
    g = _graph()
    T = _true_pose()
    seen = [0, 3]
    scan = transform_points(invert_T(T), g.centroid[seen])
    # same translation, rotated by 180° about the scan's midpoint axis: nodes still match in class only if the
    # positions coincide, so build a flipped hypothesis that swaps the two nodes' places
    flip = make_T(Rotation.from_rotvec([0, 0, np.pi]).as_matrix())
    mid = g.centroid[seen].mean(axis=0)
    T_flip = make_T(t=mid) @ flip @ make_T(t=-mid) @ T
    hyp = Hypotheses(np.stack([T[:3, :3], T_flip[:3, :3]]), np.stack([T[:3, 3], T_flip[:3, 3]]), np.zeros((2, 2), int))
    score_graph(hyp, scan, g.cls[seen], g, match_radius_m=10.0, edge_max_m=10.0)
    assert hyp.s_e[0] > 0.99 and hyp.s_e[1] < hyp.s_e[0]


def test_a_yaw_sweep_shares_its_rotations_and_scores_as_one_rotation_a_hypothesis() -> None:
    """Single objects' hypotheses index a table of the sweep's rotations (`Hypotheses.rot`); with object pairs (one
    rotation each) they concatenate into one table, `take` keeps the indices, and `R`, `T`, `rotation` and the
    field's scores are what one (3, 3) a hypothesis gives."""
    g = _graph()
    T = _true_pose()
    scan = transform_points(invert_T(T), g.centroid[[0, 3, 5]])
    R_level = rotation_between(T[:3, :3].T @ [0, 0, 1.0], np.array([0, 0, 1.0]))
    hyp = gravity_hypotheses(scan, g.cls[[0, 3, 5]], g, R_level=R_level, up=np.array([0, 0, 1.0]),
                             camera_height_m=None, yaw_step_deg=10.0, scan_top=np.zeros(3))
    assert hyp.rot is not None and len(hyp.R_table) < len(hyp)  # the sweeps' 36 rotations, shared
    pick = np.unique(np.r_[np.random.default_rng(0).choice(len(hyp), 200, replace=False), len(hyp) - 1])
    sub = hyp.take(pick)
    assert sub.rot is not None and sub.R_table is hyp.R_table
    assert all(np.array_equal(sub.T(k)[:3, :3], hyp.rotation(i)) for k, i in enumerate(pick))
    rng_pts = np.random.default_rng(1)
    field = DistanceField(rng_pts.uniform([0, 0, 0], [6, 5, 2], (3000, 3)), voxel_m=0.05)
    pts = rng_pts.uniform(-1, 1, (40, 3))
    by_table = score_poses(field, pts, sub.R_table, sub.t, rot=sub.rot)
    R = sub.R  # made from the table on first read, then held
    assert sub.rot is None and R.shape == (len(pick), 3, 3)
    assert np.array_equal(R, hyp.R_table[hyp.rot[pick]])
    assert np.array_equal(by_table, score_poses(field, pts, R, sub.t))
    with pytest.raises(ValueError):  # the compiled loop reads the table unchecked: an index past it is refused
        score_poses(field, pts, sub.R_table[:2], sub.t[:3], rot=np.array([0, 1, 2]))
    both = Hypotheses.concat([sub, Hypotheses.of_pose(T), hyp.take(pick[:5])])
    assert both.rot is not None and len(both) == len(pick) + 6
    assert np.array_equal(both.R[len(pick)], T[:3, :3]) and np.array_equal(both.R[-5:], hyp.R[pick[:5]])


def test_distance_field_scores_the_true_pose_highest() -> None:
    rng = np.random.default_rng(3)
    # an L-shaped set of walls so that the pose is observable
    a = np.column_stack([rng.uniform(0, 4, 4000), np.zeros(4000), rng.uniform(0, 2, 4000)])
    b = np.column_stack([np.zeros(3000), rng.uniform(0, 3, 3000), rng.uniform(0, 2, 3000)])
    f = np.column_stack([rng.uniform(0, 4, 4000), rng.uniform(0, 3, 4000), np.zeros(4000)])
    M = np.vstack([a, b, f])
    field = DistanceField(M, voxel_m=0.03)
    assert field.lookup(np.array([[2.0, 0.0, 1.0]]))[0] <= 0.05
    assert np.isclose(field.lookup(np.array([[50.0, 50.0, 50.0]]))[0], field.truncate_m)
    T = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1.0, 1.0, 0.5])
    pts = transform_points(invert_T(T), M[rng.choice(len(M), 300, replace=False)])
    shifts = [T, make_T(t=[0.2, 0, 0]) @ T, make_T(Rotation.from_euler("z", 10, degrees=True).as_matrix()) @ T]
    s = score_poses(field, pts, np.stack([x[:3, :3] for x in shifts]), np.stack([x[:3, 3] for x in shifts]))
    assert s[0] > 0.9 and s[0] > s[1] and s[0] > s[2]


def test_the_best_overall_and_of_each_group_are_what_sorting_keeps() -> None:
    """`best_overall_and_by_group` (a building's screen of its graph hypotheses): the `count` best scores and each
    group's `per_group` best, equal scores in index order, as sorting all by score (then index) and each group
    likewise keeps; scores with many ties, groups with fewer members than asked for, -1 a group of its own."""
    from cadreg.localize.match import best_overall_and_by_group

    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 300))
        scores = np.round(rng.random(n) * rng.integers(1, 6)) / 5.0
        group = rng.integers(-1, int(rng.integers(1, 12)), n)
        count, per_group = int(rng.integers(0, 40)), int(rng.integers(0, 5))
        order = np.lexsort((np.arange(n), -scores))
        expected = set(order[:count].tolist())
        for g in np.unique(group):
            expected |= set(order[group[order] == g][:per_group].tolist())
        assert best_overall_and_by_group(scores, group, count=count, per_group=per_group).tolist() == sorted(expected)
    assert best_overall_and_by_group(np.zeros(0), np.zeros(0, dtype=np.int64), count=3, per_group=1).tolist() == []


def test_distinct_best_suppresses_near_duplicates() -> None:
    R = np.stack([np.eye(3)] * 3)
    t = np.array([[0, 0, 0], [0.05, 0, 0], [1.0, 0, 0]])
    assert distinct_best(R, t, np.arange(3), count=5) == [0, 2]


def test_distinct_best_keeps_what_pairwise_tests_keep() -> None:
    # The compiled suppression against the rule written out: kept in order, each farther than the minimum from, or
    # turned more than the minimum against, every one kept before it.
    rng = np.random.default_rng(3)
    for trial in range(10):
        h = int(rng.integers(1, 800))
        R = Rotation.from_rotvec(rng.normal(scale=0.3, size=(h, 3))).as_matrix()
        t = rng.uniform(0.0, 1.0, size=(h, 3))
        order, count = rng.permutation(h), int(rng.integers(1, 40))
        expected: list[int] = []
        for i in order:
            if len(expected) < count and all(np.linalg.norm(t[i] - t[k]) > 0.25 or rotation_angle_deg(R[i].T @ R[k]) > 15.0
                                             for k in expected):
                expected.append(int(i))
        assert distinct_best(R, t, order, count=count) == expected
    assert distinct_best(R, t, np.array([], dtype=np.int64), count=3) == []


def test_distinct_pairs_tell_every_pair_as_the_rule_written_out() -> None:
    rng = np.random.default_rng(4)
    T = np.tile(np.eye(4), (60, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.3, size=(60, 3))).as_matrix()
    T[:, :3, 3] = rng.uniform(0.0, 0.5, size=(60, 3))
    A, B = T[:25], T[25:]
    expected = np.array([[np.linalg.norm(a[:3, 3] - b[:3, 3]) > 0.25 or rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) > 15.0
                          for b in B] for a in A])
    got = distinct_pairs(A, B, min_translation_m=0.25, min_rotation_deg=15.0)
    assert got.shape == (25, 35) and 0 < got.sum() < got.size and np.array_equal(got, expected)
