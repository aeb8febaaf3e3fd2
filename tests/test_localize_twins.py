"""Rooms that repeat one another: found from the graph's object layout, and used so that a view a copy repeats
is never answered `ok` in one room."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadreg import Site
from cadreg.config import LocalizeConfig, MatchConfig, RegionConfig
from cadreg.geometry import pose_errors
from cadreg.localize.building_views import Renders
from cadreg.localize.localizer import Localizer
from cadreg.localize.match import MapGraph
from cadreg.localize.stages import Refined
from cadreg.localize.twins import RoomTwins
from cadreg.result import Status


def _graph(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[MapGraph, np.ndarray]:
    centroid = np.concatenate([p for p, _ in parts])
    cls = np.concatenate([c for _, c in parts])
    region = np.concatenate([np.full(len(p), k) for k, (p, _) in enumerate(parts)])
    return MapGraph([str(i) for i in range(len(cls))], cls, centroid), region


def test_copies_are_found_with_their_transform_and_other_rooms_are_not() -> None:
    rng = np.random.default_rng(4)
    room = np.column_stack([rng.uniform(0, 4, 6), rng.uniform(0, 3, 6), rng.uniform(0.3, 1.0, 6)])
    cls = np.array([0, 0, 1, 2, 2, 3])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = [10.0, 2.0, 0.0]
    copy = room @ T[:3, :3].T + T[:3, 3]
    # the copy lacks one object and its others lie a few centimetres off (furniture is never put back exactly)
    copy = np.delete(copy + rng.normal(0, 0.03, copy.shape), 1, axis=0)
    other = np.column_stack([rng.uniform(20, 24, 6), rng.uniform(0, 3, 6), rng.uniform(0.3, 1.0, 6)])
    graph, region = _graph([(room, cls), (copy, np.delete(cls, 1)), (other, cls)])
    twins = RoomTwins(graph, region, np.array([0.0, 0.0, 1.0]), 3)
    (found,) = twins.of(0)
    assert found[0] == 1
    t_err, r_err = pose_errors(found[1], T)
    assert t_err < 0.1 and r_err < 2.0
    (back,) = twins.of(1)
    assert back[0] == 0 and np.allclose(back[1] @ found[1], np.eye(4), atol=0.05)
    assert twins.of(2) == []
    assert twins.one_of_each() == [0, 2]  # the room stands for its copy; the other room for itself
    # objects carried into the copy: each onto its counterpart there; the one the copy lacks, and none, onto -1
    (carried,) = twins.carry_all(np.array([0, 1, 2, -1]), [(1, found[1])])
    n = len(room)  # the copy's nodes follow the room's, less its object 1
    assert carried.tolist() == [n + 0, -1, n + 1, -1]


def test_warm_makes_the_rows_first_use_makes_within_its_budget() -> None:
    """`RoomTwins.warm` makes each region's row as `of` would on first use (a worker's first frames then find them
    made), and stops once its budget is spent: a budget of nothing makes none."""
    rng = np.random.default_rng(6)
    room = np.column_stack([rng.uniform(0, 4, 6), rng.uniform(0, 3, 6), rng.uniform(0.3, 1.0, 6)])
    cls = np.array([0, 0, 1, 2, 2, 3])
    parts = [(room + [5.0 * k, 0.0, 0.0], cls) for k in range(4)] + [(room[::-1] + [30.0, 7.0, 0.0], cls)]
    graph, region = _graph(parts)
    up = np.array([0.0, 0.0, 1.0])
    warmed, lazy = RoomTwins(graph, region, up, 5), RoomTwins(graph, region, up, 5)
    assert warmed.warm(60.0) == 5
    for a in range(5):
        rows = [(b, T) for b, T in lazy.of(a)]
        assert [b for b, _ in warmed.of(a)] == [b for b, _ in rows] and len(rows) == (3 if a < 4 else 0)
        assert all(np.array_equal(T, U) for (_, T), (_, U) in zip(warmed.of(a), rows))
    assert RoomTwins(graph, region, up, 5).warm(0.0) == 0


def test_a_copy_with_moved_furniture_is_placed_by_the_objects_that_stayed() -> None:
    """A copy of a room with a chair pulled 30 cm out: a transform tilted 4.6° between all the objects brings each
    within the match tolerance (the most inliers: it was the copy's transform, 31 cm off at the camera), but the
    copy's transform is the one that lays the objects that stayed exactly."""
    room = np.array([[0.5, 0.5, 0.4], [3.5, 0.6, 0.4], [3.4, 2.6, 0.7], [0.6, 2.5, 0.7], [2.0, 1.5, 0.5],
                     [1.0, 1.5, 0.4]])
    cls = np.array([0, 0, 1, 1, 2, 0])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", -90, degrees=True).as_matrix()
    T[:3, 3] = [12.0, 5.0, 0.0]
    copy = room @ T[:3, :3].T + T[:3, 3]
    copy[1] += [0.187, -0.235, 0.0]  # the chair by the wall, pulled out
    graph, region = _graph([(room, cls), (copy, cls)])
    (found,) = RoomTwins(graph, region, np.array([0.0, 0.0, 1.0]), 2).of(0)
    t_err, r_err = pose_errors(found[1], T)
    assert found[0] == 1 and t_err < 1e-9 and r_err < 1e-6


def test_copies_of_a_view_are_not_told_apart_by_an_object_at_the_match_radius() -> None:
    """A partly seen whiteboard's centroid lies about match_radius_m (0.6 m) from its node: copies of one view a
    few millimetres apart put it 0.598 m from the node in one room and 0.601 m in the other. The copy places it as
    the answer does (within OBJECT_SLACK_M farther) and is kept; a room that lacks the object, or has it 0.699 m off,
    does not."""
    from types import SimpleNamespace

    from cadreg.localize.building_views import OBJECT_SLACK_M, BuildingViews

    graph = MapGraph(["a/wb", "b/wb", "c/wb"], np.array([0, 0, 0]),
                     np.array([[0.598, 0.0, 1.0], [10.601, 0.0, 1.0], [20.699, 0.0, 1.0]]))
    views = BuildingViews()
    views.config, views.graph = LocalizeConfig(), graph
    scan = SimpleNamespace(clusters=[SimpleNamespace(cls=0, centroid=np.zeros(3))], view_shares=np.array([0.5]))
    T_a, T_b, T_c, T_none = (np.eye(4) for _ in range(4))
    T_a[:3, 3], T_b[:3, 3], T_c[:3, 3], T_none[:3, 3] = [0, 0, 1.0], [10.0, 0, 1.0], [20.0, 0, 1.0], [30.0, 0, 1.0]
    distances = views._object_distances(scan, np.array([T_a, T_b, T_c, T_none]))[:, 0]
    assert distances[:3] == pytest.approx([0.598, 0.601, 0.699]) and np.isinf(distances[3])
    assert views._objects_placed(scan, np.array([T_a, T_b]))[:, 0].tolist() == [True, False]  # the radius alone
    assert views._shows_objects(scan, T_a, [T_b, T_c, T_none]).tolist() == [True, False, False]
    assert 0.598 + OBJECT_SLACK_M < 0.699
    # an object the reference pose does not place is credited within the radius only
    assert views._near_as(np.array([[0.65], [0.59]]), np.array([np.inf])).ravel().tolist() == [False, True]


def test_a_large_object_seen_in_part_is_placed_by_its_box_not_by_a_sliver_beside_it() -> None:
    """A whiteboard 2.4 m wide seen in part has its centroid a metre from its node's centre, inside its box. Rooms
    "a", "b" and "c" hold the board (turned by odd angles, as their rooms are); "b" also holds a 0.3 m sliver of it,
    clustered apart, where the frame's centroid lands; "d" lacks the board. By centres alone only "b" placed the
    board; by boxes "a", "b" and "c" place it alike (a view they repeat is not told apart by it), and "d" does not."""
    from types import SimpleNamespace

    from cadreg.localize.building_views import BuildingViews

    def turn(deg: float) -> np.ndarray:
        return Rotation.from_euler("z", deg, degrees=True).as_matrix()

    board, sliver = np.array([2.4, 0.13, 0.46]), np.array([0.3, 0.02, 0.3])
    shift = {"a": 0.0, "b": 10.0, "c": 20.0, "d": 30.0}
    yaw = {"a": 0.0, "b": 30.0, "c": 72.0, "d": 0.0}
    seen = np.array([1.0, 0.0, 1.0])  # the frame's board centroid, room frame: a metre along the board from its centre
    centres, extents, Rs, cls = [], [], [], []
    for room in "abc":
        R = turn(yaw[room])
        centres.append(R @ np.array([0.0, 0.0, 1.0]) + [shift[room], 0, 0])
        extents.append(board), Rs.append(R), cls.append(0)
    R_b = turn(yaw["b"])
    centres.append(R_b @ seen + [shift["b"], 0, 0]), extents.append(sliver), Rs.append(R_b), cls.append(0)
    centres.append(np.array([shift["d"], 3.0, 0.4])), extents.append(np.full(3, 0.5)), Rs.append(np.eye(3)), cls.append(1)
    centre = np.array(centres)
    graph = MapGraph([f"n{i}" for i in range(len(cls))], np.array(cls), centre, np.array(extents),
                     centre[:, 2] + 0.2, centre, np.array(Rs))
    views = BuildingViews()
    views.config, views.graph = LocalizeConfig(), graph
    scan = SimpleNamespace(clusters=[SimpleNamespace(cls=0, centroid=np.zeros(3))], view_shares=np.array([0.5]))
    poses = []
    for room in "abcd":  # the camera at the frame's board centroid (camera frame = room frame there)
        T = np.eye(4)
        T[:3, :3] = turn(yaw[room])
        T[:3, 3] = turn(yaw[room]) @ seen + [shift[room], 0, 0]
        poses.append(T)
    distances = views._object_distances(scan, np.array(poses))[:, 0]
    assert distances[:3].tolist() == [0.0, 0.0, 0.0] and np.isinf(distances[3])
    assert views._shows_objects(scan, poses[0], poses[1:]).tolist() == [True, True, False]
    # the boxes' test itself, along room "a"'s board (1.2 m half-width): inside, within the margin, beyond it
    along = np.array([[1.15, 0.0, 1.0], [1.25, 0.0, 1.0], [1.35, 0.0, 1.0]])
    assert graph.in_box_of_class(along, 0, 0.1).tolist() == [True, True, False]
    assert not graph.in_box_of_class(along[:1], 1, 0.1).any()  # in a box of another class only
    # without boxes (a graph made of centres alone) no point is in one
    assert not MapGraph(graph.ids, graph.cls, graph.centroid).in_box_of_class(centre[:1], 0, 0.1).any()


def test_a_room_with_too_few_objects_has_no_copies() -> None:
    graph, region = _graph([(np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([0, 1])),
                            (np.array([[5.0, 0, 0], [6, 0, 0]]), np.array([0, 1]))])
    assert RoomTwins(graph, region, np.array([0.0, 0.0, 1.0]), 2).of(0) == []


def test_rooms_without_objects_are_copies_when_their_shapes_are() -> None:
    # Four rooms of bare surfaces: an L-shaped room of a floor, walls and a shelf; its copy turned a quarter turn
    # and shifted; a room of the same box whose shelf stands elsewhere (no copy); a copy turned by 37 degrees.
    from cadreg.localize.score import DistanceField

    rng = np.random.default_rng(5)

    def room(shelf_x: float) -> np.ndarray:
        u = rng.uniform(0, 1, (6000, 2))
        floor = np.column_stack([4 * u[:2000, 0], 3 * u[:2000, 1], np.zeros(2000)])
        wall_x = np.column_stack([4 * u[2000:4000, 0], np.zeros(2000), 1.2 * u[2000:4000, 1]])
        wall_y = np.column_stack([np.zeros(1000), 3 * u[4000:5000, 0], 1.2 * u[4000:5000, 1]])
        shelf = np.column_stack([shelf_x + 0.8 * u[5000:, 0], 2.0 + np.zeros(1000), 1.2 * u[5000:, 1]])
        return np.concatenate([floor, wall_x, wall_y, shelf])

    def turned(deg: float, shift: list[float]) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
        T[:3, 3] = shift
        return T

    a = room(0.5)
    T_quarter, T_odd = turned(90, [10.0, 1.0, 0.0]), turned(37, [2.0, 14.0, 0.0])
    clouds = [a, a @ T_quarter[:3, :3].T + T_quarter[:3, 3], room(2.7) + [0.0, 8.0, 0.0],
              a @ T_odd[:3, :3].T + T_odd[:3, 3]]
    field = DistanceField(np.concatenate(clouds), voxel_m=0.03)
    graph, region = _graph([(np.zeros((0, 3)), np.zeros(0, dtype=np.int64))] * 4)
    read: list[int] = []

    def sample(k: int) -> np.ndarray:
        read.append(k)
        return clouds[k][::5]

    twins = RoomTwins(graph, region, np.array([0.0, 0.0, 1.0]), 4, field=field, sample=sample)
    found = dict(twins.of(0))
    assert sorted(found) == [1, 3]
    for b, T in [(1, T_quarter), (3, T_odd)]:  # a room turned by any angle, not only by quarter turns
        t_err, r_err = pose_errors(found[b], T)
        assert t_err < 0.05 and r_err < 0.5
    assert [b for b, _ in twins.of(2)] == []  # the same box, its shelf elsewhere: no copy
    assert sorted(read) == [0, 1, 2, 3]  # each room's points read once, whatever it is tried against
    # without the field (a graph's objects only), bare rooms have no copies
    assert RoomTwins(graph, region, np.array([0.0, 0.0, 1.0]), 4).of(0) == []


@pytest.mark.realdata
def test_a_copy_the_graph_match_left_out_still_makes_a_shared_view_ambiguous(twin_rooms_dir: Path,
                                                                                 twin_shared_view) -> None:
    from tracking_rooms import ROOM_B_OFFSET_M

    frame, T_true = twin_shared_view
    # The graph verifies one room only (no tie margin): the other copy can come in only through the twin check.
    config = LocalizeConfig(regions=RegionConfig(tie_margin=0.0, max_verified=1), match=MatchConfig(candidates=1))
    localizer = Localizer.from_site(Site.load(twin_rooms_dir), config)
    (a, T_ba), = localizer.twins.of(0)
    assert a == 1 and abs(T_ba[0, 3] - ROOM_B_OFFSET_M) < 0.05 and np.allclose(T_ba[:3, :3], np.eye(3), atol=0.01)
    r = localizer.localize(frame)
    assert r.status == Status.AMBIGUOUS
    T_b = np.eye(4)
    T_b[0, 3] = ROOM_B_OFFSET_M
    near = lambda T, U: pose_errors(T, U)[0] < 0.05 and pose_errors(T, U)[1] < 5.0  # noqa: E731
    assert any(h.region == "a" and near(h.T_map_camera, T_true) for h in r.hypotheses)
    assert any(h.region == "b" and near(h.T_map_camera, T_b @ T_true) for h in r.hypotheses)
    assert any(h.source == "twin" for h in r.hypotheses)


@pytest.mark.realdata
def test_poses_that_look_alike_are_told_apart_by_the_frame_objects(twin_rooms_dir: Path, scene0470_dir: Path,
                                                                   twin_shared_view, tmp_path: Path) -> None:
    """`Localizer._told_by_objects`: room "b" copies room "a" without a chair and the bin. A frame of room "a"
    that sees them, answered in "b" with "a" as a rival that looks the same along its rays, is answered in "a"
    (the rival refined and put first); the view both rooms show explains as many objects at both poses and
    keeps its rival."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.stages import Candidate, StageTimer
    from cadreg.result import Diagnostics, Hypothesis
    from tracking_rooms import ROOM_B_OFFSET_M, render_turn

    loc = Localizer.from_site(Site.load(twin_rooms_dir))
    to_b = np.eye(4)
    to_b[0, 3] = ROOM_B_OFFSET_M

    def scan_of(frame):
        diag = Diagnostics(site_id="s", bundle_version="v")
        return loc._scan(frame, diag, StageTimer(diag.stage_ms)), diag

    def entry(T):
        c = Candidate(T, 0.9, Hypothesis(T, 0.0, 0.0, 0.0, 0.9), np.zeros(0, np.int64))
        return Refined(0.9, RefineOutcome(T, None, 1, True, "small_gicp"), c)

    def answered_in_b(frame, T_a):
        scan, diag = scan_of(frame)
        in_b, in_a = entry(to_b @ T_a), entry(T_a)
        refined, candidates = [in_b], [in_b.candidate, in_a.candidate]
        refine_calls = []

        def refine(c):  # the rival's refinement: its pose is already the true one
            refine_calls.append(c)
            return Refined(0.9, in_a.outcome, c)

        told = loc._told_by_objects(scan, refined, [in_a.candidate], refine, candidates, diag)
        return told, refined, refine_calls, scan

    frames = render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                         scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", tmp_path / "turn", n=2)

    chair_view, T_a = RecordedFrames.open(frames).load(1)  # the chair and the bin only room "a" holds
    told, refined, refine_calls, scan = answered_in_b(chair_view, T_a)
    explained = scan.view_shares @ loc._objects_placed(scan, np.array([T_a, to_b @ T_a])).T
    assert explained[0] - explained[1] >= 0.05
    assert told and len(refine_calls) == 1 and pose_errors(refined[0].T_map_camera, T_a)[0] < 1e-9
    shared, T_shared = twin_shared_view  # the table's corner, which both rooms show
    told, refined, refine_calls, _ = answered_in_b(shared, T_shared)
    assert not told and not refine_calls and pose_errors(refined[0].T_map_camera, to_b @ T_shared)[0] < 1e-9


def test_the_copies_of_a_pose_the_objects_put_first_are_looked_at(scene0470_site_dir: Path, scene0470_dir: Path,
                                                                  twin_shared_view, tmp_path: Path) -> None:
    """`Localizer._promoted_twins`: when the frame's objects put a rival first, the copies of the rival's view are
    looked at before the answer may stand alone. Rooms "a" and "c" are the same room, "b" lacks the chair and the
    bin: the chair view's pose in "a" has its copy in "c" (the same view along every ray) as a rival, and its
    copy in "b", which lacks an object the frame shows, is not looked at (`Localizer._shows_objects`); a view of
    the table's corner, which all three rooms hold, has a copy in each."""
    import json

    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.stages import Candidate, StageTimer
    from cadreg.result import Diagnostics, Hypothesis
    from cadreg.site.compose import compose_site, read_layout
    from tracking_rooms import DROPPED, ROOM_B_OFFSET_M, render_turn

    def moved(dx: float) -> list:
        T = np.eye(4)
        T[0, 3] = dx
        return T.tolist()

    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"site_id": "three-rooms", "rooms": [
        {"name": "a", "bundle": str(scene0470_site_dir), "T_building_room": moved(0.0)},
        {"name": "b", "bundle": str(scene0470_site_dir), "T_building_room": moved(ROOM_B_OFFSET_M), "drop_objects": DROPPED},
        {"name": "c", "bundle": str(scene0470_site_dir), "T_building_room": moved(2 * ROOM_B_OFFSET_M)},
    ]}))
    compose_site(read_layout(layout), tmp_path).save(tmp_path / "site")
    loc = Localizer.from_site(Site.load(tmp_path / "site"))
    frames = render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                         scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", tmp_path / "turn", n=2)
    chair_view, T_a = RecordedFrames.open(frames).load(1)  # the chair and the bin only rooms "a" and "c" hold
    diag = Diagnostics(site_id="s", bundle_version="v")
    scan = loc._scan(chair_view, diag, StageTimer(diag.stage_ms))
    render = scan.view.render(loc.field, T_a)[0]
    score = float(scan.view.agreement(render)[0])
    out = RefineOutcome(T_a, None, 1, True, "small_gicp")
    winner = Candidate(T_a, score, Hypothesis(T_a, 0.0, 0.0, 0.0, score), np.zeros(0, np.int64))
    candidates, renders = [winner], Renders()
    renders[out] = render
    twins = loc._promoted_twins(scan, [Refined(score, out, winner)], scan.center_camera, candidates, renders)
    in_b, in_c = np.array(moved(ROOM_B_OFFSET_M)) @ T_a, np.array(moved(2 * ROOM_B_OFFSET_M)) @ T_a
    assert any(pose_errors(t.T_map_camera, in_c)[0] < 0.05 and t.hypothesis.region == "c" for t in twins)
    assert all(any(t is c for c in candidates) for t in twins)  # listed among the candidates the result reports
    # the copy in "b" lacks the chair the frame shows: not a copy of this view, and never rendered as one
    assert loc._shows_objects(scan, T_a, [in_b, in_c]).tolist() == [False, True]
    assert not any(t.hypothesis.region == "b" for t in twins)
    shared, T_shared = twin_shared_view
    shared_scan = loc._scan(shared, diag, StageTimer(diag.stage_ms))
    assert shared_scan.clusters  # (the test means something only with objects in view)
    copies = [np.array(moved(dx)) @ T_shared for dx in (ROOM_B_OFFSET_M, 2 * ROOM_B_OFFSET_M)]
    assert loc._shows_objects(shared_scan, T_shared, copies).tolist() == [True, True]


def _shared_view_scan(twin_rooms_dir: Path, twin_shared_view):
    """(localizer of the two-room site, the shared view's Scan, its pose in room "a", the move from room "a" to
    "b") for tests that drive the refine stage's steps by hand."""
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics
    from tracking_rooms import ROOM_B_OFFSET_M

    loc = Localizer.from_site(Site.load(twin_rooms_dir))
    frame, T_a = twin_shared_view
    diag = Diagnostics(site_id="s", bundle_version="v")
    to_b = np.eye(4)
    to_b[0, 3] = ROOM_B_OFFSET_M
    return loc, loc._scan(frame, diag, StageTimer(diag.stage_ms)), T_a, to_b


def _refined_entry(T: np.ndarray, score: float) -> Refined:
    """A refine-stage entry at pose T with view agreement `score`."""
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.stages import Candidate
    from cadreg.result import Hypothesis

    c = Candidate(T, score, Hypothesis(T, 0.0, 0.0, 0.0, score), np.zeros(0, np.int64))
    return Refined(score, RefineOutcome(T, None, 1, True, "small_gicp"), c)


@pytest.mark.realdata
def test_a_copy_a_little_behind_the_answer_is_refined_once(twin_rooms_dir: Path, twin_shared_view) -> None:
    """`Localizer._promote_twins`: a copy of the winner's view is its pose moved into the copy's room, refined in
    the winner's room; one that shows the frame a little worse (within RegionConfig.contender_margin, beyond the
    ambiguity margin) with no copy closer is refined, once a frame, and stands as a rival when its refinement
    brings it within the ambiguity margin. A copy already within the margin, or far behind, is not refined."""
    from cadreg.localize.refine import RefineOutcome

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    aside = np.eye(4)
    aside[1, 3] = 0.5
    entry = _refined_entry

    def promote(behind: list[float]):
        """(refine calls, refined, copies left, renders, candidates, copies given) for copies in room "b"
        `behind` the winner's view agreement of 0.8."""
        winner = entry(T_a, 0.8)
        twins = [entry(aside @ to_b @ T_a if k else to_b @ T_a, 0.8 - d) for k, d in enumerate(behind)]
        calls = []

        def refine(c):  # the copy's refinement fits it to its room: it comes within the ambiguity margin
            calls.append(c)
            return Refined(0.79, RefineOutcome(c.T_map_camera, None, 1, True, "small_gicp"), c)

        refined, candidates = [winner], [winner.candidate]
        renders = Renders()
        renders[winner.outcome] = scan.view.render(loc.field, T_a)[0]
        left = loc._promote_twins(scan, refined, list(twins), refine, candidates, renders, scan.center_camera)
        return calls, refined, left, renders, candidates, twins

    calls, refined, left, renders, candidates, twins = promote([0.05, 0.06])
    assert len(calls) == 1 and calls[0] is twins[0].candidate  # the nearest copy, and only it
    assert len(left) == 1 and left[0] is twins[1]
    assert [r.score for r in refined] == [0.8, 0.79] and refined[1].candidate is twins[0].candidate
    has_rival, margin, rivals = loc._view_rivals(refined, renders, candidates, scan)
    assert has_rival and margin < loc.config.match.ambiguity_margin
    assert len(rivals) == 1 and rivals[0].hypothesis.region == "b"
    assert pose_errors(rivals[0].T_map_camera, to_b @ T_a)[0] < 1e-9
    assert promote([0.01, 0.05])[0] == []  # a copy within the ambiguity margin makes the answer ambiguous as it is
    assert promote([0.15])[0] == []  # beyond the contender margin: not the same view


@pytest.mark.realdata
def test_a_refinement_that_shows_the_frame_worse_along_its_rays_than_its_start_is_redone_on_the_whole_frame(
        twin_rooms_dir: Path, twin_shared_view, monkeypatch: pytest.MonkeyPatch) -> None:
    """`RefineStage._unslid` in a building: a contender's ROI refinement whose check points still lie on the map (its
    whole-frame fitness within SLIDE_TOLERANCE of its start's) but which shows the frame along its rays worse than
    its start by more than VIEW_SLIDE_TOLERANCE has slid; the whole frame refines the start again, and of the two
    the pose that shows the frame better is kept. A refinement that shows it about as well as its start is kept as
    it is, with no second refinement."""
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.refine_stage import SLIDE_TOLERANCE, VIEW_SLIDE_TOLERANCE
    from cadreg.localize.stages import Candidate
    from cadreg.result import Diagnostics, Hypothesis

    loc, scan, T_a, _ = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    start = float(scan.view.agreement(scan.view.render(loc.field, T_a))[0])
    c = Candidate(T_a, start, Hypothesis(T_a, 0.0, 0.0, 0.0, start), np.zeros(0, np.int64))
    run = loc._refine_run(scan, [c], loc.config.refine.method, Diagnostics(site_id="s", bundle_version="v"))
    refine_map = loc.maps_at(T_a, run.center_camera).refine_map
    calls = []
    refine_one = loc._refine_one
    monkeypatch.setattr(loc, "_refine_one", lambda *a: calls.append(a) or refine_one(*a))

    along_axis = np.eye(4)
    along_axis[2, 3] = 0.04  # 4 cm along the camera's axis: every check point still within 5 cm of the map
    slid = RefineOutcome(T_a @ along_axis, None, 1, True, "grid_gicp")
    fit = lambda T: loc._whole_fit(run, refine_map, T)  # noqa: E731
    assert fit(slid.T_map_camera) >= fit(T_a) - SLIDE_TOLERANCE  # (the fitness alone would keep it)
    assert loc._view_agreement(run, slid) < start - VIEW_SLIDE_TOLERANCE
    out = loc._unslid(run, refine_map, c, slid)
    assert len(calls) == 1 and calls[0][2] is T_a  # the start refined again, once
    assert out is not slid and pose_errors(out.T_map_camera, T_a)[0] < 0.01
    assert loc._view_agreement(run, out) > loc._view_agreement(run, slid)
    assert run.diag.notes[-1] == "the ROI refinement slid: refined with the whole frame"

    calls.clear()
    held = RefineOutcome(T_a.copy(), None, 1, True, "grid_gicp")
    assert loc._unslid(run, refine_map, c, held) is held and calls == []


@pytest.mark.realdata
def test_a_weak_answer_of_a_cut_search_leaves_its_copies_to_the_deeper_search(twin_rooms_dir: Path,
                                                                              twin_shared_view) -> None:
    """`RefineStage._copies_wait`: after a label-free search of the whole building cut at its node cap
    (`Scan.search_cut`), an answer that shows the frame along its rays less than `Scan.deeper_below`, with no copy
    of its view that does better, leaves its copies unrefined: the deeper search follows
    (`Localizer._weak_after_a_cut_search`), even for an answer off the map, and its refine stage looks at the
    copies of its own winner. A copy that shows the frame as well as RegionConfig.min_view_agreement asks, or a
    search that was not cut, has the copies refined as before; so does an answer, or a copy of its view, between
    that bar and the deeper look's (`deeper_view_agreement`), whose deeper look then follows the copies'
    refinement."""
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.stages import Choice

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    rc = loc.config.regions
    bar = rc.min_view_agreement
    assert rc.deeper_view_agreement > bar + 0.05
    scan.deeper_below = rc.deeper_view_agreement  # what a cut search sets (`FallbackStage._label_free`)
    winner, copy = _refined_entry(T_a, bar - 0.05), _refined_entry(to_b @ T_a, bar - 0.03)
    assert not loc._copies_wait(scan, [winner], [copy])  # no cut search: no deeper one follows
    scan.search_cut = True
    assert loc._copies_wait(scan, [winner], [copy])
    assert not loc._copies_wait(scan, [winner], [_refined_entry(to_b @ T_a, bar + 0.01)])  # it may lift the answer
    between = _refined_entry(T_a, bar + 0.03)
    assert not loc._copies_wait(scan, [between], [_refined_entry(to_b @ T_a, bar + 0.02)])
    on_the_map = Choice(between.candidate, RefineOutcome(T_a, None, 1, True, "grid_gicp"), 0.0, False,
                        loc.config.refine.min_fitness, 0.02, scan.center_camera, 100, view_agreement=between.score)
    assert loc._weak_after_a_cut_search(scan, on_the_map)  # the deeper look follows, its copies refined first
    off_the_map = Choice(winner.candidate, RefineOutcome(T_a, None, 1, True, "grid_gicp"), 0.0, False,
                         0.5 * loc.config.refine.min_fitness, 0.02, scan.center_camera, 100,
                         view_agreement=winner.score)
    assert not loc._weak_after_a_cut_search(scan, off_the_map)
    scan.copies_wait = True
    assert loc._weak_after_a_cut_search(scan, off_the_map)


@pytest.mark.realdata
def test_a_copy_that_wins_has_its_copies_looked_at_only_in_the_rooms_that_stood(twin_rooms_dir: Path,
                                                                                 twin_shared_view) -> None:
    """`_twin_views(among=...)` looks at the copies in the rooms named only; when a promoted copy wins,
    `_promote_twins` looks again at the rooms whose copies stood from the earlier pose, not at every copy; and not
    at all when the copy's refinement left it where the twin check put it (its copies' poses are the ones looked
    at)."""
    from cadreg.localize.refine import RefineOutcome

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    start = loc._roi_region(T_a, scan.center_camera)

    def looked(among):
        candidates = [_refined_entry(T_a, 0.8).candidate]
        return loc._twin_views(scan, T_a, scan.center_camera, candidates, Renders(), 1, 0.8, among=among)

    everywhere = looked(None)
    assert [loc._roi_region(t.T_map_camera, scan.center_camera) for t in everywhere] == [1 - start]
    assert looked({1 - start})[0].score == everywhere[0].score
    assert looked(set()) == [] and looked({start}) == []

    aside = np.eye(4)
    aside[1, 3] = 0.3
    winner = _refined_entry(T_a, 0.8)
    # a copy in room b that shows the frame better (promoted, and it wins), and one more pose in room a standing
    twins = [_refined_entry(to_b @ T_a, 0.85), _refined_entry(aside @ T_a, 0.78)]
    asked = []

    def twin_views(*args, among=None):
        asked.append(among)
        return []

    loc._twin_views = twin_views

    def promote(moved_m: float) -> list:
        renders = Renders()
        renders[winner.outcome] = scan.view.render(loc.field, T_a)[0]
        refined, candidates = [winner], [winner.candidate]
        nudge = np.eye(4)
        nudge[0, 3] = moved_m
        left = loc._promote_twins(scan, refined, list(twins), lambda c: Refined(
            0.86, RefineOutcome(nudge @ c.T_map_camera, None, 1, True, "small_gicp"), c), candidates, renders,
            scan.center_camera)
        assert refined[0].candidate is twins[0].candidate
        return left + [r.candidate for r in refined]

    promote(0.02)  # refined 2 cm off the copy's pose: its copies are looked at again
    assert asked == [{loc._roi_region(aside @ T_a, scan.center_camera)}]
    asked.clear()
    # 1 mm off: not looked at again, and the copy that stood stays (here refined next: within the contender margin)
    seen = promote(0.001)
    assert asked == [] and any(k is twins[1].candidate for k in seen)
    asked.clear()
    # No copy stood but the promoted one: the room of the pose it beat is looked at (its copy of the new winner
    # was never looked at: the beaten pose's refinement may have slid off the truth there).
    twins = twins[:1]
    promote(0.02)
    assert asked == [{start}]


@pytest.mark.realdata
def test_a_copy_at_a_refined_pose_stands_only_where_it_shows_the_frame_clearly_better(twin_rooms_dir: Path,
                                                                                       twin_shared_view) -> None:
    """`_twin_views` beside the refined contenders: a copy at a refined contender's pose is that contender, and is
    not looked at; one within the refinement's reach of a contender (NEAR_REACH_M) stands only when it shows the
    frame better than that contender by the ambiguity margin (the contender's refinement slid off the view there);
    one beyond every contender's reach stands as it would alone."""
    from cadreg.localize.stages import NEAR_REACH_M

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)

    def looked(off_m: float, contender_score: float) -> list[Refined]:
        """The copies of the winner's view (in room "a") with a refined contender in room "b" off_m from the
        copy's pose, its view agreement contender_score."""
        off = np.eye(4)
        off[1, 3] = off_m
        candidates = [_refined_entry(T_a, 0.8).candidate, _refined_entry(off @ to_b @ T_a, contender_score).candidate]
        return loc._twin_views(scan, T_a, scan.center_camera, candidates, Renders(), 2, 0.8)

    (alone,) = looked(1.0, 0.9)  # a contender 1 m away, beyond its reach: the copy as it stands alone
    assert loc._roi_region(alone.T_map_camera, scan.center_camera) == loc._roi_region(to_b @ T_a, scan.center_camera)
    assert looked(0.0, 0.0) == []  # the contender's own pose: judged already
    near = 0.5 * NEAR_REACH_M
    assert looked(near, alone.score - 0.01) == []  # within reach and about as good: that contender again
    (better,) = looked(near, alone.score - 2 * loc.config.match.ambiguity_margin)  # it slid: the copy stands
    assert better.score == alone.score


def test_a_render_belongs_to_its_outcome_not_to_an_id_a_discarded_one_freed() -> None:
    """`Renders`: the refine stage discards outcomes (copies the twin check replaces); keyed by a bare id, a new
    outcome could take a discarded one's id and read its render as its own."""
    from cadreg.localize.refine import RefineOutcome

    renders = Renders()
    for k in range(200):
        outcome = RefineOutcome(np.eye(4), None, 0, False, "field")  # the previous one is unreferenced here
        assert outcome not in renders
        renders[outcome] = np.full(3, float(k))
        assert outcome in renders and renders[outcome][0] == k
    with pytest.raises(KeyError):
        renders[RefineOutcome(np.eye(4), None, 0, False, "field")]


@pytest.mark.realdata
def test_of_poses_that_look_alike_the_one_the_frames_points_fit_closest_goes_first(
        twin_rooms_dir: Path, scene0470_dir: Path, twin_shared_view, tmp_path: Path) -> None:
    """`Localizer._closest_fit_first`: room "b" copies room "a" without a chair and the bin. A frame of room "a"
    that sees them (no labels), answered in "b" with "a" as a rival along its rays, has "a" put first: the frame's
    points lie on the map there, on nothing where the copy lacks the chair. The view both rooms show fits both
    alike and keeps its order."""
    from dataclasses import replace

    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.refine import RefineOutcome
    from cadreg.localize.stages import Candidate, StageTimer
    from cadreg.result import Diagnostics, Hypothesis
    from tracking_rooms import ROOM_B_OFFSET_M, render_turn

    loc = Localizer.from_site(Site.load(twin_rooms_dir))
    to_b = np.eye(4)
    to_b[0, 3] = ROOM_B_OFFSET_M

    def entry(T):
        c = Candidate(T, 0.9, Hypothesis(T, 0.0, 0.0, 0.0, 0.9), np.zeros(0, np.int64))
        return Refined(0.9, RefineOutcome(T, None, 1, True, "small_gicp"), c)

    def answered_in_b(frame, T_a):
        diag = Diagnostics(site_id="s", bundle_version="v")
        scan = loc._scan(replace(frame, labels=None), diag, StageTimer(diag.stage_ms))
        in_b, in_a = entry(to_b @ T_a), entry(T_a)
        refined, candidates, calls = [in_b], [in_b.candidate, in_a.candidate], []

        def refine(c):  # the rival's refinement: its pose is already the true one
            calls.append(c)
            return Refined(0.9, in_a.outcome, c)

        loc._closest_fit_first(scan, refined, [in_a.candidate], refine, candidates, diag)
        return refined, calls, diag.notes

    frames = render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                         scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", tmp_path / "turn", n=2)
    chair_view, T_a = RecordedFrames.open(frames).load(1)  # the chair and the bin only room "a" holds
    refined, calls, notes = answered_in_b(chair_view, T_a)
    assert len(calls) == 1 and pose_errors(refined[0].T_map_camera, T_a)[0] < 1e-9
    assert pose_errors(refined[1].T_map_camera, to_b @ T_a)[0] < 1e-9  # the answer before it stays, second
    assert any("lie closest to the map" in n for n in notes)
    shared, T_shared = twin_shared_view  # the table's corner, which both rooms show
    refined, calls, _ = answered_in_b(shared, T_shared)
    assert not calls and len(refined) == 1 and pose_errors(refined[0].T_map_camera, to_b @ T_shared)[0] < 1e-9


@pytest.mark.realdata
def test_a_rival_put_first_without_a_render_is_rendered_for_the_answer(twin_rooms_dir: Path, twin_shared_view,
                                                                        monkeypatch) -> None:
    """The refine stage's last step reads the answer's render; a rival put first by a tie-break
    (`_closest_fit_first`, `_told_by_objects`) may come from a refinement that left it as it was (a pose the frame
    sees through), with no render: the answer is rendered then, not a KeyError (a request's 500)."""
    from cadreg.localize.refine import RefineOutcome

    loc = Localizer.from_site(Site.load(twin_rooms_dir))
    frame, T_a = twin_shared_view

    def put_a_bare_outcome_first(scan, refined, rivals, refine, candidates, diag):
        c = rivals[0] if rivals else refined[0].candidate
        refined.insert(0, Refined(1.0, RefineOutcome(c.T_map_camera, None, 0, False, "small_gicp"), c))

    monkeypatch.setattr(Localizer, "_closest_fit_first", staticmethod(put_a_bare_outcome_first))
    r = loc.localize(frame)  # the view both rooms show: its rivals are there
    assert r.status == Status.AMBIGUOUS
    assert any(pose_errors(h.T_map_camera, T_a)[0] < 0.05 for h in r.hypotheses)


@pytest.mark.realdata
def test_of_two_refinements_at_one_place_the_one_whose_depth_agrees_goes_first(twin_rooms_dir: Path,
                                                                               twin_shared_view) -> None:
    """`Localizer._deepest_at_the_winners_place_first`: a refinement that ended 15 cm ahead of the view's pose, put
    first by a higher view agreement, gives way to the one at the pose, whose depth agrees with the frame's on the
    rays both show a surface on; a distinct pose (the view in the other room) is no contender at the winner's
    place, and one whose depth agrees about as well (1 cm off) leaves the order as it is."""
    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    ahead, beside = T_a.copy(), T_a.copy()
    ahead[:3, 3] += 0.15 * T_a[:3, 2]
    beside[:3, 3] += 0.01 * T_a[:3, 0]
    refined = [_refined_entry(ahead, 0.9), _refined_entry(T_a, 0.8)]
    loc._deepest_at_the_winners_place_first(scan, refined, Renders())
    assert refined[0].T_map_camera is T_a and refined[1].T_map_camera is ahead
    in_b = to_b @ T_a
    refined = [_refined_entry(ahead, 0.9), _refined_entry(in_b, 0.8)]
    loc._deepest_at_the_winners_place_first(scan, refined, Renders())
    assert refined[0].T_map_camera is ahead
    refined = [_refined_entry(T_a, 0.9), _refined_entry(beside, 0.8)]
    loc._deepest_at_the_winners_place_first(scan, refined, Renders())
    assert refined[0].T_map_camera is T_a


@pytest.mark.realdata
def test_of_poses_that_tie_along_the_rays_the_one_whose_depth_agrees_is_the_answer(twin_rooms_dir: Path,
                                                                                 twin_shared_view) -> None:
    """`Localizer._told_by_depth`: answered 40 cm ahead of the view's pose with the view's pose as a rival (their
    view agreements within the ambiguity margin), the view's pose, whose depth agrees with the frame's on the rays
    both show a surface on, is put first and the tie is told; the same view in the room that copies it (its depth
    agrees as well) is not told apart from the answer."""
    from cadreg.result import Diagnostics

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    ahead = T_a.copy()
    ahead[:3, 3] += 0.4 * T_a[:3, 2]
    winner, rival = _refined_entry(ahead, 0.80), _refined_entry(T_a, 0.79)
    refined, candidates, diag = [winner], [winner.candidate, rival.candidate], Diagnostics()
    told = loc._told_by_depth(scan, refined, [rival.candidate], lambda c: rival, candidates, Renders(),
                              [winner, rival], diag)
    assert told and refined[0] is rival and refined[0].T_map_camera is T_a
    assert any("the depth along the frame's rays" in n for n in diag.notes)
    copy = _refined_entry(to_b @ T_a, 0.79)
    refined, candidates = [_refined_entry(T_a, 0.80)], []
    assert not loc._told_by_depth(scan, refined, [copy.candidate], lambda c: copy, candidates, Renders(),
                                  refined + [copy], Diagnostics())
    assert refined[0].T_map_camera is not copy.T_map_camera


@pytest.mark.realdata
def test_of_candidates_at_one_place_the_one_whose_depth_agrees_stands_for_it(twin_rooms_dir: Path,
                                                                           twin_shared_view) -> None:
    """`Localizer._one_per_place`: the verify stage lists each place once, by its best candidate, unless a later one
    there agrees with the frame's depth on the rays both show a surface on clearly better: a candidate 15 cm ahead
    of the view's pose, first by its view agreement, gives way to the one at the pose; a distinct place (the view in
    the other room) is listed too, and one 1 cm off the first does not displace it."""
    from cadreg.localize.stages import Candidate
    from cadreg.result import Hypothesis

    loc, scan, T_a, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)

    def candidate(T, score):
        return Candidate(T, score, Hypothesis(T, 0.0, 0.0, 0.0, score), np.zeros(0, np.int64),
                         scan.view.render(loc.field, T)[0])

    ahead, beside = T_a.copy(), T_a.copy()
    ahead[:3, 3] += 0.15 * T_a[:3, 2]
    beside[:3, 3] += 0.01 * T_a[:3, 0]
    kept = loc._one_per_place(scan, [candidate(ahead, 0.9), candidate(T_a, 0.8), candidate(to_b @ T_a, 0.7)])
    assert kept[0].T_map_camera is T_a
    assert len(kept) == 2 and pose_errors(kept[1].T_map_camera, to_b @ T_a)[0] < 1e-9
    kept = loc._one_per_place(scan, [candidate(T_a, 0.9), candidate(beside, 0.8)])
    assert len(kept) == 1 and kept[0].T_map_camera is T_a


@pytest.mark.realdata
def test_the_ambiguity_margin_between_view_agreements_grows_where_they_are_noisier(twin_rooms_dir: Path,
                                                                                   twin_shared_view) -> None:
    """`BuildingViews._view_margin`: the ambiguity margin holds from a view agreement of 0.8 up (and far below,
    where a share is as sure again) and grows as √(p(1 − p)) in between, by a quarter at one half. A distinct pose
    0.032 behind an answer at 0.64 is its rival (`_view_rivals`); behind one at 0.85 it is not."""
    loc, scan, T_a, _ = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    margin = loc.config.match.ambiguity_margin
    assert loc._view_margin(0.95) == loc._view_margin(0.8) == loc._view_margin(0.1) == margin
    assert loc._view_margin(0.5) == pytest.approx(1.25 * margin)
    assert margin < loc._view_margin(0.64) < loc._view_margin(0.5)
    aside = T_a.copy()
    aside[1, 3] += 0.5  # a distinct pose whose render is not the answer's
    for score, rival in [(0.64, True), (0.85, False)]:
        refined = [_refined_entry(T_a, score), _refined_entry(aside, score - 0.032)]
        has_rival, behind, rivals = loc._view_rivals(refined, Renders(), [r.candidate for r in refined], scan)
        assert has_rival and behind == pytest.approx(0.032)
        assert [c.T_map_camera for c in rivals] == ([aside] if rival else [])


@pytest.mark.realdata
def test_a_view_from_a_robots_height_is_not_held_back_by_the_one_room_depth_gate(twin_rooms_dir: Path,
                                                                                 scene0470_dir: Path,
                                                                                 tmp_path: Path) -> None:
    """RegionConfig.min_depth_agreement: a view from 0.54 m up at two chairs, one of which (cad-4) only room "a"
    holds (the pose of a 10-room view at robot height that was held `uncertain`, moved into room "a"). Its depth agrees with the map's along the rays on less than one room's 0.75 (the map's chairs are the CAD
    models: a few centimetres off the scanned ones, and whole where the scan saw parts), yet it is the answer by a
    wide margin among the rooms: a building's gate lets it be `ok`; at one room's 0.75 it was `uncertain`."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.render import LabelledMesh, render_frames
    from tracking_rooms import look_at

    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    camera = np.array([2.749, 1.878, 0.539])
    render_frames(mesh, tmp_path / "low", 0, poses=[look_at(camera, camera + [-0.093, -0.990, -0.104])], seed=0)
    frame, T_true = RecordedFrames.open(tmp_path / "low").load(0)
    site = Site.load(twin_rooms_dir)
    r = Localizer.from_site(site).localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] < 0.05, r.diagnostics.notes
    trust = next(n for n in r.diagnostics.notes if n.startswith("trust"))
    depth = float(trust.split("depth agreement ")[1].split(",")[0])
    assert LocalizeConfig().regions.min_depth_agreement <= depth < MatchConfig().min_depth_agreement
    strict = Localizer.from_site(site, LocalizeConfig(regions=RegionConfig(min_depth_agreement=0.75)))
    assert strict.localize(frame).status == Status.UNCERTAIN


@pytest.mark.realdata
def test_a_buildings_wall_directions_hold_its_copies_turned_by_odd_angles(scene0470_site_dir: Path,
                                                                        tmp_path: Path) -> None:
    """`Localizer._building_wall_directions`: room "b" is room "a" turned by 30° (a copy the twins find), room "c"
    by a quarter turn. The building's histogram is room "a"'s own and the same turned by 30°, half each (the quarter
    turn adds nothing): the label-free search then tries the yaws of views in "b", which "a"'s alone left out."""
    import json

    from cadreg.localize.bbs import map_direction_histogram
    from cadreg.localize.regions import region_cloud
    from cadreg.site.compose import compose_site, read_layout

    def placed(deg: float, dx: float) -> list:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
        T[0, 3] = dx
        return T.tolist()

    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"site_id": "turned-rooms", "rooms": [
        {"name": "a", "bundle": str(scene0470_site_dir), "T_building_room": placed(0.0, 0.0)},
        {"name": "b", "bundle": str(scene0470_site_dir), "T_building_room": placed(30.0, 8.0)},
        {"name": "c", "bundle": str(scene0470_site_dir), "T_building_room": placed(90.0, 16.0)},
    ]}))
    compose_site(read_layout(layout), tmp_path).save(tmp_path / "site")
    site = Site.load(tmp_path / "site")
    loc = Localizer.from_site(site)
    assert sorted(b for b, _ in loc.twins.of(0)) == [1, 2]
    R_level = np.eye(3)  # the building is z-up
    own = map_direction_histogram(region_cloud(site, loc.maps.regions[0], "both").normals.astype(np.float64))
    walls, each = loc._building_wall_directions(R_level)
    assert walls == pytest.approx(0.5 * (own + np.roll(own, 15)), abs=0.01 * own.max())  # 30° = 15 bins of 2°
    assert walls[15] > 3 * own[15]  # the directions of "b"'s walls, which "a"'s alone barely holds
    # Each room's own: "a"'s, "a"'s turned by 30° for "b", and "a"'s again for "c" (a quarter turn).
    assert each[0] == pytest.approx(own, abs=0.01 * own.max()) and np.array_equal(each[2], each[0])
    assert np.array_equal(each[1], np.roll(each[0], 15))
    assert loc.rooms_face_their_own_ways()  # "b" faces its own ways


@pytest.mark.realdata
def test_a_pose_that_looks_like_the_one_a_tie_break_put_first_stands_as_its_rival(
        twin_rooms_dir: Path, twin_shared_view, scene0470_dir: Path, tmp_path: Path) -> None:
    """`Localizer._rank_building`: a tie-break tells the pose it puts first only from the poses that looked like
    the answer it replaces. Answered 40 cm ahead of the view's pose (view agreement 0.85), with the view's pose a
    rival (0.835, as rendered) and the same view in the copy room refined too (0.81: beyond the ambiguity margin of
    the answer, within that of the view's pose), the depth puts the view's pose first; the copy, never told from
    it, stands as its rival. A view only room "a" shows (its chair and bin), answered the same way, is told."""
    loc, shared_scan, T_shared, to_b = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    rank = lambda scan, T_a, others: _ranked_from_ahead(loc, scan, T_a, others)  # noqa: E731
    in_b = to_b @ T_shared
    assert shared_scan.view.agreement(shared_scan.view.render(loc.field, T_shared))[0] == pytest.approx(0.835, abs=0.005)
    assert 0.85 - 0.81 >= loc._view_margin(0.85) and 0.835 - 0.81 < loc._view_margin(0.835)
    refined, has_rival, margin, rivals, notes = rank(shared_scan, T_shared, [_refined_entry(in_b, 0.81)])
    assert refined[0].T_map_camera is T_shared  # put first by the depth along the rays
    assert any("the depth along the frame's rays" in n for n in notes)
    assert has_rival and margin < loc._view_margin(refined[0].score)
    assert any(pose_errors(c.T_map_camera, in_b)[0] < 1e-9 for c in rivals)
    # the answer is no rival of its own, and no pose is listed twice
    assert loc._distinct_from_all([c.T_map_camera for c in rivals], [T_shared]).all()
    assert all(loc._distinct_from_all([c.T_map_camera for c in rivals[k + 1:]], [a.T_map_camera]).all()
               for k, a in enumerate(rivals))
    assert any("were not told from it: 1," in n for n in notes)
    chair_scan, T_chair = _chair_view_scan(loc, scene0470_dir, tmp_path)
    refined, has_rival, margin, rivals, notes = rank(chair_scan, T_chair, [])
    assert refined[0].T_map_camera is T_chair and not has_rival and rivals == []


@pytest.mark.realdata
def test_a_runner_up_whose_copies_the_twin_check_had_no_rays_left_for_stands_as_a_rival(
        twin_rooms_dir: Path, scene0470_dir: Path, tmp_path: Path) -> None:
    """RegionConfig.twin_check_rays: the copies of the answer's view are always looked at, a tied runner-up's only
    while the frame's twin check has rays left (a flat plane of depth, which every copy of every contender shows
    alike, rendered 3.3 M rays at 100 rooms: 1.1 s). The view only room "a" shows (its chair and bin), answered at
    its pose with a pose 40 cm ahead the runner-up, is told by its objects when the copies of both were looked at;
    with no rays left the runner-up's copies are not rendered, and the answer, never told from them, keeps a
    rival. A runner-up the objects put first has its copies looked at all the same (`_promoted_twins`)."""
    seen = Localizer.from_site(Site.load(twin_rooms_dir))
    spent = Localizer.from_site(Site.load(twin_rooms_dir), LocalizeConfig(regions=RegionConfig(twin_check_rays=0)))
    scan, T_chair = _chair_view_scan(seen, scene0470_dir, tmp_path)
    refined, has_rival, margin, rivals, notes = _ranked_from_ahead(seen, scan, T_chair, [], ahead_first=False)
    assert refined[0].T_map_camera is T_chair and not has_rival and rivals == []
    assert not any("were not looked at" in n for n in notes)

    scan, T_chair = _chair_view_scan(spent, scene0470_dir, tmp_path)
    looked_from = []
    twin_views = spent._twin_views
    spent._twin_views = lambda scan, T, *args, **kw: looked_from.append(T) or twin_views(scan, T, *args, **kw)
    refined, has_rival, margin, rivals, notes = _ranked_from_ahead(spent, scan, T_chair, [], ahead_first=False)
    assert looked_from == [T_chair]  # the answer's copies only
    assert refined[0].T_map_camera is T_chair and has_rival and margin == 0.0
    assert any("the copies of 1 tied runner-ups' views were not looked at" in n for n in notes)
    # answered ahead, the objects put the runner-up (the view's pose) first, and its copies are looked at
    looked_from.clear()
    refined, has_rival, margin, rivals, notes = _ranked_from_ahead(spent, scan, T_chair, [])
    assert len(looked_from) == 2 and looked_from[1] is T_chair
    assert refined[0].T_map_camera is T_chair and not has_rival and rivals == []


@pytest.mark.realdata
def test_the_twin_check_counts_every_ray_it_renders(twin_rooms_dir: Path, twin_shared_view,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """`Scan.twin_rays`, what RegionConfig.twin_check_rays bounds: every ray the twin check traces at every pose (its
    first look, the aligned copies' second, the full renders), and no other render."""
    from cadreg.localize.field_view import FieldView

    loc, scan, T_a, _ = _shared_view_scan(twin_rooms_dir, twin_shared_view)
    traced = []
    render = FieldView.render
    monkeypatch.setattr(FieldView, "render", lambda view, field, T: traced.append(
        len(np.asarray(T).reshape(-1, 4, 4)) * len(view)) or render(view, field, T))
    scan.view.render(loc.field, T_a)  # not the twin check's
    traced.clear()
    copies = loc._twin_views(scan, T_a, scan.center_camera, [_refined_entry(T_a, 0.8).candidate], Renders(), 1, 0.8)
    assert copies and len(traced) >= 2 and sum(traced) >= len(scan.view)  # a first look, the rest of the rays
    assert scan.twin_rays == sum(traced)


def _ranked_from_ahead(loc: Localizer, scan, T_a: np.ndarray, others: list[Refined], *, ahead_first: bool = True):
    """`_rank_building` of a frame answered 40 cm ahead of T_a (view agreement 0.85), T_a refined as its
    runner-up (0.835), or (ahead_first False) the other way round, and `others` after them: (refined, has a rival,
    margin, rivals, notes)."""
    from cadreg.localize.refine_stage import RefineRun
    from cadreg.result import Diagnostics

    ahead = T_a.copy()
    ahead[:3, 3] += 0.4 * T_a[:3, 2]
    first, second = (ahead, T_a) if ahead_first else (T_a, ahead)
    entries = [_refined_entry(first, 0.85), _refined_entry(second, 0.835)] + others
    candidates, refined, diag = [e.candidate for e in entries], list(entries), Diagnostics()
    run = RefineRun(scan, "small_gicp", diag, candidates[:1], None, scan.down, scan.down, len(scan.down),
                    scan.center_camera, Renders())
    has_rival, margin, rivals = loc._rank_building(
        run, refined, candidates, lambda c: next(e for e in entries if e.candidate is c))
    return refined, has_rival, margin, rivals, diag.notes


def _chair_view_scan(loc: Localizer, scene0470_dir: Path, tmp_path: Path):
    """(Scan, T_map_camera) of a view of the chair and the bin that only room "a" of the twin rooms holds."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics
    from tracking_rooms import render_turn

    frames = render_turn(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                         scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", tmp_path / "turn", n=2)
    chair_view, T_chair = RecordedFrames.open(frames).load(1)
    diag = Diagnostics(site_id="s", bundle_version="v")
    return loc._scan(chair_view, diag, StageTimer(diag.stage_ms)), T_chair


@pytest.fixture(scope="module")
def exact_copies(scene0470_site_dir: Path, scene0470_dir: Path, tmp_path_factory: pytest.TempPathFactory):
    """(site dir, frame, T_map_camera) of two exact copies of the scene0470 room, "b" 6 m along x from "a", and a
    view from room "a" along x, over its far wall (1.37 m high), rendered from the building (Kinect-like noise, a
    6 m cut-off): room "b" lies 5.4-6 m from the camera."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.render import LabelledMesh, render_frames
    from cadreg.render.building import building_mesh, building_rooms
    from cadreg.site.compose import read_layout
    from tracking_rooms import look_at, twin_site

    out = tmp_path_factory.mktemp("exact-copies")
    site_dir = twin_site(scene0470_site_dir, out, dropped=[])
    layout = read_layout(out / "LAYOUT.json")
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    nodes = Site.load(scene0470_site_dir).graph.nodes
    rooms = building_rooms(layout, {str(scene0470_site_dir): mesh}, {str(scene0470_site_dir): nodes})
    T = look_at(np.array([0.6, 1.5, 1.7]), np.array([3.5, 1.4, 1.3]))
    render_frames(building_mesh(rooms), out / "view", 0, poses=[T], seed=0)
    frame, T_map_camera = RecordedFrames.open(out / "view").load(0)
    return site_dir, frame, T_map_camera


@pytest.mark.parametrize("labels", [True, False])
def test_a_copy_told_only_by_surfaces_beyond_the_sensors_range_stands_as_a_rival(exact_copies, labels: bool) -> None:
    """`field_view.sensor_range_m`: a camera that measures to 6 m (the render says so) sees room "b" over room
    "a"'s far wall, and from the same place in room "b" nothing is there: `ok` in "a". The same frame as a camera
    that measures nothing beyond 4 m (its depth beyond 3.8 m cut, no range given) has no word on room "b": the
    two rooms show it alike, `ambiguous`, both listed. (Counted against "a", room "b"'s surfaces had it answered
    `ok` in "b", 6 m off, as real RedKitchen frames were in a building of two copies of their fused kitchen.)"""
    from dataclasses import replace

    from tracking_rooms import ROOM_B_OFFSET_M, near

    site_dir, frame, T = exact_copies
    frame = frame if labels else replace(frame, labels=None)
    to_b = np.eye(4)
    to_b[0, 3] = ROOM_B_OFFSET_M
    assert frame.depth_range_m == 6.0 and frame.depth.max() > 5400
    loc = Localizer.from_site(Site.load(site_dir))
    seen_far = loc.localize(frame)
    assert seen_far.status is Status.OK and near(seen_far.T_map_camera, T)
    short = replace(frame, depth=np.where(frame.depth > 3800, 0, frame.depth).astype(np.uint16), depth_range_m=None)
    seen_near = loc.localize(short)
    assert seen_near.status is Status.AMBIGUOUS
    listed = [h.T_map_camera for h in seen_near.hypotheses]
    assert any(near(P, T) for P in listed) and any(near(P, to_b @ T) for P in listed)
