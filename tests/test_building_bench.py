"""The building benchmark: layout generator, building mesh with dropped objects, the repeated-view oracle and
views.json, and the bench's unique / repeated figures."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cadreg.bench import FrameOutcome, ViewTruth, format_table, summarize, views_from_doc
from cadreg.cli.main import main
from cadreg.config import NoiseConfig
from cadreg.geometry import make_T
from cadreg.site.layout import LayoutConfig, RoomSource, generate_layout, grid_shape, placed_footprint
from tracking_rooms import look_at

CAD_IDS = tuple(f"cad-{k}" for k in range(7))
CAMERA_M = np.array([1.7, 2.3, 1.4])
CHAIR_M = np.array([3.03, 0.62, 0.4])  # cad-4: dropped in room "c" of the oracle's building
TABLE_CORNER_M = np.array([0.7, 0.6, 0.4])  # seen by every copy (tracking_rooms: a view both rooms share)


def _source(name: str = "s", size=(3.5, 2.9), origin=(-0.2, 0.1)) -> RoomSource:
    lo = np.array(origin, dtype=float)
    return RoomSource(name, f"rooms/{name}", lo, lo + np.array(size, dtype=float), CAD_IDS)


# --- layout generator -----------------------------------------------------------------------------------------


def test_layout_grid_has_exact_gaps_and_no_overlap() -> None:
    gap = 0.6
    sources = [_source("a"), _source("b", size=(4.0, 2.5))]
    layout = generate_layout(sources, LayoutConfig(site_id="b10", rooms=10, gap_m=gap, seed=1))
    assert [r.name for r in layout.rooms] == [f"r{k:03d}" for k in range(10)]
    assert [r.bundle for r in layout.rooms] == ["rooms/a", "rooms/b"] * 5  # cycled
    boxes = []
    for k, r in enumerate(layout.rooms):
        T = np.asarray(r.T_building_room)
        assert set(np.round(T[:3, :3], 12).ravel()) <= {0.0, 1.0, -1.0} and T[2, 3] == 0.0  # quarter turns about z
        src = sources[k % 2]
        box = placed_footprint(src, T)
        assert np.allclose(sorted(box[1] - box[0]), sorted(src.size))
        boxes.append(box)
    for a, b in itertools.combinations(boxes, 2):  # apart by >= gap along x or y
        sep = np.maximum(b[0] - a[1], a[0] - b[1])
        assert sep.max() >= gap - 1e-9
    cols, rows = grid_shape(10)
    assert (cols, rows) == (4, 3)
    for row in range(rows):  # within a row, each room starts exactly `gap` after its left neighbour
        members = boxes[row * cols:(row + 1) * cols]
        assert members[0][0, 0] == pytest.approx(0.0)
        for left, right in zip(members, members[1:]):
            assert right[0, 0] - left[1, 0] == pytest.approx(gap)
            assert right[0, 1] == pytest.approx(left[0, 1])  # one band per row
    bands = [min(b[0, 1] for b in boxes[r * cols:(r + 1) * cols]) for r in range(rows)]
    tops = [max(b[1, 1] for b in boxes[r * cols:(r + 1) * cols]) for r in range(rows)]
    assert all(lo - hi == pytest.approx(gap) for hi, lo in zip(tops, bands[1:]))


def test_layout_is_deterministic_and_drops_at_the_given_rate() -> None:
    config = LayoutConfig(site_id="b100", rooms=100, drop_prob=0.35, seed=5)
    a = generate_layout([_source()], config)
    assert a == generate_layout([_source()], config)
    assert a != generate_layout([_source()], config.model_copy(update={"seed": 6}))
    dropped = [d for r in a.rooms for d in r.drop_objects]
    assert set(dropped) <= set(CAD_IDS)
    assert len(dropped) / (100 * len(CAD_IDS)) == pytest.approx(0.35, abs=0.06)  # 700 draws: sd 0.018
    turns = {round(math.degrees(math.atan2(r.T_building_room[1][0], r.T_building_room[0][0]))) % 360 for r in a.rooms}
    assert turns == {0, 90, 180, 270}
    none = generate_layout([_source()], config.model_copy(update={"drop_prob": 0.0}))
    assert all(not r.drop_objects for r in none.rooms)


def test_layout_with_any_turn_turns_rooms_by_odd_angles_and_keeps_their_boxes_apart() -> None:
    """`any_turn`: each room turned by an angle drawn in [0°, 360°); the boxes about the turned footprints keep the
    grid's gaps (so the rooms themselves are at least that far apart), and the same seed gives the same layout."""
    gap = 0.6
    source = _source()
    config = LayoutConfig(site_id="at10", rooms=10, gap_m=gap, seed=1, any_turn=True)
    layout = generate_layout([source], config)
    assert layout == generate_layout([source], config)
    turns = [math.degrees(math.atan2(r.T_building_room[1][0], r.T_building_room[0][0])) for r in layout.rooms]
    assert sum(abs((t + 45.0) % 90.0 - 45.0) > 1.0 for t in turns) >= 8  # not quarter turns
    boxes = []
    for r in layout.rooms:
        T = np.asarray(r.T_building_room)
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3)) and T[2, 2] == 1.0  # a turn about z
        box = placed_footprint(source, T)
        c, s = abs(T[0, 0]), abs(T[1, 0])
        assert np.allclose(box[1] - box[0], [c * source.size[0] + s * source.size[1],
                                             s * source.size[0] + c * source.size[1]])
        boxes.append(box)
    for a, b in itertools.combinations(boxes, 2):
        assert np.maximum(b[0] - a[1], a[0] - b[1]).max() >= gap - 1e-9


def test_layout_turned_as_a_whole_is_the_same_building_turned() -> None:
    """`building_turn_deg`: every room's placement is the unturned layout's turned about z through the origin; the
    drops are the same."""
    config = LayoutConfig(site_id="b10", rooms=10, seed=1)
    plain = generate_layout([_source()], config)
    turned = generate_layout([_source()], config.model_copy(update={"building_turn_deg": 30.0}))
    R = make_T(np.array([[math.cos(math.radians(30)), -math.sin(math.radians(30)), 0],
                         [math.sin(math.radians(30)), math.cos(math.radians(30)), 0], [0, 0, 1]]))
    for a, b in zip(plain.rooms, turned.rooms):
        assert np.allclose(np.asarray(b.T_building_room), R @ np.asarray(a.T_building_room))
        assert a.drop_objects == b.drop_objects
    assert generate_layout([_source()], config.model_copy(update={"building_turn_deg": 0.0})) == plain


def test_layout_on_storeys_raises_each_storeys_grid_and_keeps_the_seeds_turns_and_drops() -> None:
    """--storeys: the first ⌈N / storeys⌉ rooms on the ground storey, and so on, each storey laid out on the grid
    its rooms alone would take and raised by a storey's height; the corridors of each storey with it, named by it."""
    one = LayoutConfig(site_id="b10", rooms=10, corridor_m=2.4, seed=1)
    flat, tall = (generate_layout([_source()], c) for c in (one, one.model_copy(update={"storeys": 3,
                                                                                             "storey_height_m": 3.5})))
    assert [(r.name, r.drop_objects) for r in tall.rooms] == [(r.name, r.drop_objects) for r in flat.rooms]
    heights = [np.asarray(r.T_building_room)[2, 3] for r in tall.rooms]
    assert heights == [0.0] * 4 + [3.5] * 4 + [7.0] * 2
    # the ground storey is the 4-room layout of the seed (its first draws, a grid of 4), the others its grid raised
    ground = generate_layout([_source()], one.model_copy(update={"rooms": 4})).rooms
    assert [r.T_building_room for r in tall.rooms[:4]] == [r.T_building_room for r in ground]
    for r in tall.rooms[4:]:
        box = placed_footprint(_source(), np.asarray(r.T_building_room))
        assert box[0].min() >= -1e-9 and box[1, 0] <= max(placed_footprint(_source(), np.asarray(g.T_building_room))[1, 0]
                                                         for g in ground) + 1.5  # on a grid of two columns
    assert [c.name for c in tall.corridors] == ["s0c00", "s1c00", "s2c00"]
    assert [np.asarray(c.T_building_corridor)[2, 3] for c in tall.corridors] == pytest.approx([0.0, 3.5, 7.0])
    assert [c.name for c in flat.corridors] == ["c00", "c01"]
    with pytest.raises(ValueError, match="storey_height_m"):
        LayoutConfig(site_id="b", rooms=4, storeys=2, storey_height_m=1.0)


def _boxed_source() -> RoomSource:
    """`_source()` with a 0.4 × 0.6 m box for each CAD object, spread over the room: objects to move."""
    base = _source()
    centres = [np.array([0.3 + 0.45 * k, 0.6 + 0.25 * (k % 3)]) for k in range(len(CAD_IDS))]
    corners = tuple(np.array([[x, y] for x in (-0.2, 0.2) for y in (-0.3, 0.3) for _ in (0, 1)]) + c for c in centres)
    return RoomSource(base.name, base.bundle, base.footprint_min, base.footprint_max, CAD_IDS, cad_corners=corners)


def test_layout_moves_kept_objects_inside_the_room_and_keeps_the_turns_and_drops() -> None:
    """--move-prob: each CAD object a copy keeps is turned about the vertical through its box centre (at most
    move_max_deg) and shifted (at most move_max_m) so that its box stays in the footprint; the turns and drops of a
    seed do not depend on it, nor does anything without it (no "move_objects")."""
    source = _boxed_source()
    still = LayoutConfig(site_id="b20", rooms=20, drop_prob=0.35, seed=3)
    moving = still.model_copy(update={"move_prob": 1.0, "move_max_m": 0.3, "move_max_deg": 30.0})
    a, b = generate_layout([source], still), generate_layout([source], moving)
    assert b == generate_layout([source], moving)
    assert all(not r.move_objects for r in a.rooms)
    turns_and_drops = [[(r.T_building_room, r.drop_objects) for r in x.rooms] for x in (a, b)]
    assert turns_and_drops[0] == turns_and_drops[1]
    corners = dict(zip(CAD_IDS, source.cad_corners))
    moved = 0
    for r in b.rooms:
        assert not set(r.move_objects) & set(r.drop_objects)
        for node_id, T in r.moves().items():
            assert T[2, 3] == 0.0 and np.allclose(T[2, :3], [0, 0, 1])  # about the vertical, no lift
            assert math.degrees(abs(math.atan2(T[1, 0], T[0, 0]))) <= 30.0 + 1e-9
            xy = corners[node_id]
            centre = (xy.min(axis=0) + xy.max(axis=0)) / 2
            assert np.linalg.norm(T[:2, :2] @ centre + T[:2, 3] - centre) <= 0.3 + 1e-9
            after = xy @ T[:2, :2].T + T[:2, 3]
            assert np.all(after >= source.footprint_min) and np.all(after <= source.footprint_max)
            moved += 1
    kept = sum(len(CAD_IDS) - len(r.drop_objects) for r in b.rooms)
    assert moved >= 0.8 * kept  # a box near the wall may find no place within MOVE_TRIES draws
    with pytest.raises(Exception, match="no object boxes"):
        generate_layout([_source()], moving)


@pytest.mark.realdata
def test_layout_cli_writes_a_layout_compose_reads(scene0470_site_dir: Path, tmp_path: Path, capsys) -> None:
    from cadreg.site.compose import read_layout

    out = tmp_path / "deep" / "layout.json"
    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "4", "--seed", "1",
                 "--site-id", "b4", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["rooms"] == 4 and report["grid"] == [2, 2] and report["cad_objects"] == 28
    layout = read_layout(out)
    assert layout.site_id == "b4" and len(layout.rooms) == 4
    bundle = Path(layout.rooms[0].bundle)
    assert not bundle.is_absolute() and (out.parent / bundle).resolve() == scene0470_site_dir.resolve()
    first = out.read_text()
    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "4", "--seed", "1",
                 "--site-id", "b4", "--out", str(out)]) == 0
    assert out.read_text() == first
    with pytest.raises(SystemExit):  # a malformed --room
        main(["site", "layout", "--room", "nonsense", "--rooms", "4", "--site-id", "x", "--out", str(out)])
    moved = tmp_path / "moved.json"
    capsys.readouterr()
    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "4", "--seed", "1",
                 "--move-prob", "1", "--move-max-m", "0.2", "--site-id", "m4", "--out", str(moved)]) == 0
    report = json.loads(capsys.readouterr().out)
    with_moves = read_layout(moved)
    assert report["moved"] == sum(len(r.move_objects) for r in with_moves.rooms) > 0
    assert [r.drop_objects for r in with_moves.rooms] == [r.drop_objects for r in layout.rooms]  # the same drops
    assert '"move_objects"' not in first and '"move_objects"' in moved.read_text()


# --- building mesh and oracle (real scene0470 mesh) -------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_mesh(scene0470_dir: Path):
    from cadreg.render import LabelledMesh

    return LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")


@pytest.fixture(scope="module")
def scene_nodes(scene0470_site_dir: Path):
    from cadreg.site.bundle import Site

    return Site.load(scene0470_site_dir).graph.nodes


def _three_rooms_layout(bundle: str):
    """Rooms a and b: whole copies; c: without the chair cad-4 and the bin cad-0, turned by 90°. 20 m apart, so
    that no room sees another (the same surroundings: none)."""
    from cadreg.site.compose import Layout, RoomEntry

    turned = make_T(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [43.0, 0.0, 0.0])
    return Layout(site_id="three", rooms=[
        RoomEntry(name="a", bundle=bundle, T_building_room=np.eye(4).tolist()),
        RoomEntry(name="b", bundle=bundle, T_building_room=make_T(t=[20.0, 0.0, 0.0]).tolist()),
        RoomEntry(name="c", bundle=bundle, T_building_room=turned.tolist(), drop_objects=["cad-4", "cad-0"]),
    ])


@pytest.mark.realdata
def test_building_mesh_drops_the_faces_of_dropped_objects(scene_mesh, scene_nodes) -> None:
    from cadreg.render.building import building_mesh, building_rooms
    from cadreg.site.compose import inside_boxes

    rooms = building_rooms(_three_rooms_layout("r"), {"r": scene_mesh}, {"r": scene_nodes})
    assert rooms[0].mesh is scene_mesh and rooms[1].mesh is scene_mesh
    c = rooms[2].mesh
    dropped = [n for n in scene_nodes if n.id in ("cad-4", "cad-0")]
    inside = inside_boxes(scene_mesh.vertices, dropped)
    chair, bin_ = (next(n for n in dropped if n.id == i) for i in ("cad-4", "cad-0"))
    assert (chair.cls, bin_.cls) == ("chair", "otherfurniture")
    gone = (inside_boxes(scene_mesh.vertices, [chair]) & (scene_mesh.labels == 5)) | (
        inside_boxes(scene_mesh.vertices, [bin_]) & (scene_mesh.labels == 39))  # NYU40 chair, otherfurniture
    assert gone.sum() > 200
    assert not np.any(gone[c.faces])  # no face of the dropped objects is left
    removed = len(scene_mesh.faces) - len(c.faces)
    assert removed == int(np.any(gone[scene_mesh.faces], axis=1).sum()) > 500
    # the floor under them, the wall behind the bin and the door beside it stay: a room without them shows those
    kept = np.all((inside & ~gone)[c.faces], axis=1)
    assert kept.sum() > 50 and {1, 2} <= set(np.unique(scene_mesh.labels[c.faces[kept]]))
    building = building_mesh(rooms)
    assert len(building.faces) == 3 * len(scene_mesh.faces) - removed
    nv = len(scene_mesh.vertices)
    assert np.allclose(building.vertices[nv:2 * nv], scene_mesh.vertices + [20.0, 0.0, 0.0])
    assert building.n_instances == 3 * scene_mesh.n_instances
    with pytest.raises(Exception, match="cad-99"):
        from cadreg.site.compose import Layout, RoomEntry

        building_rooms(Layout(site_id="x", rooms=[RoomEntry(name="a", bundle="r", T_building_room=np.eye(4).tolist(),
                                                            drop_objects=["cad-99"])]),
                       {"r": scene_mesh}, {"r": scene_nodes})


@pytest.mark.realdata
def test_oracle_repeats_shared_views_and_not_views_of_a_dropped_object(scene_mesh, scene_nodes) -> None:
    from cadreg.render import MeshRenderer, camera_rig
    from cadreg.render.building import RepeatOracle, building_mesh, building_rooms

    rooms = building_rooms(_three_rooms_layout("r"), {"r": scene_mesh}, {"r": scene_nodes})
    depth_intr, _, T_color_depth = camera_rig()
    oracle = RepeatOracle(MeshRenderer(building_mesh(rooms)), rooms, depth_intr, T_color_depth)
    at_chair = look_at(CAMERA_M, CHAIR_M)
    agree = oracle.agreements(0, at_chair)
    assert agree["b"] > 0.999 and agree["c"] < 0.9  # the chair (and the bin) are missing in c
    assert oracle.repeated_in(0, at_chair) == ["b"]
    assert oracle.repeated_in(1, at_chair) == ["a"]
    assert oracle.repeated_in(2, at_chair) == []  # c's view (no chair) is repeated nowhere
    at_table = look_at(CAMERA_M, TABLE_CORNER_M)
    assert oracle.repeated_in(0, at_table) == ["b", "c"]  # turning room c does not matter: nothing around it


@pytest.mark.realdata
def test_render_layout_writes_frames_and_views_json(scene0470_dir: Path, scene0470_site_dir: Path, tmp_path: Path,
                                                    capsys) -> None:
    from cadreg.io.frames import RecordedFrames

    layout = _three_rooms_layout(str(scene0470_site_dir))
    layout_path = tmp_path / "three.json"
    layout_path.write_text(layout.model_dump_json())
    out = tmp_path / "frames"
    argv = ["render", "--layout", str(layout_path), "--mesh", str(scene0470_dir / "scene0470_00_vh_clean_2.ply"),
            "--labels", str(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"), "--out", str(out), "--n", "4",
            "--seed", "3"]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["frames"] == 4 and printed["rooms"] == 3
    doc = json.loads((out / "views.json").read_text())
    assert set(doc["rooms"]) == {"a", "b", "c"} and doc["oracle"]["min_agreement"] == 0.97
    frames = RecordedFrames.open(out)
    assert frames.indices == [0, 1, 2, 3]
    assert frames.depth_range_m == NoiseConfig().max_depth_m  # the sensor the views were rendered with reaches 6 m
    for v in doc["views"]:
        assert set(v) >= {"index", "room", "repeated", "repeated_in", "T_room_camera"}
        assert v["room"] not in v["repeated_in"] and v["repeated"] == bool(v["repeated_in"])
        assert v["repeated_in"] == [r for r, a in v["agreement"].items() if a >= 0.97]
        T_building_room = np.asarray(doc["rooms"][v["room"]]["T_building_room"])
        assert np.allclose(frames.pose(v["index"]), T_building_room @ np.asarray(v["T_room_camera"]), atol=1e-6)
    truth = views_from_doc(doc)
    assert set(truth) == {0, 1, 2, 3} and all(len(t.T_twins) == len(t.repeated_in) for t in truth.values())
    (out / "pose" / "0.txt").unlink()
    assert main(argv) == 0  # same seed, same views
    again = json.loads((out / "views.json").read_text())
    assert again["views"] == doc["views"]
    # Without --mesh each room bundle's own scan (site.json inputs) is rendered: the same mesh here, the same views.
    own = tmp_path / "own"
    assert main(["render", "--layout", str(layout_path), "--out", str(own), "--n", "1", "--seed", "3"]) == 0
    assert json.loads((own / "views.json").read_text())["views"][0] == doc["views"][0]
    # The bench reads views.json frame after frame (the second frame once found the first's view in its place).
    report_path = tmp_path / "bench.json"
    assert main(["bench", "--site", str(scene0470_site_dir), "--frames", str(out), "--limit", "3",
                 "--json", str(report_path)]) == 0
    summary = json.loads(report_path.read_text())["methods"]["cadreg"]
    assert summary["frames"] == 3 and summary["unique"]["frames"] + summary["repeated"]["frames"] == 3


# --- bench figures ------------------------------------------------------------------------------------------------


def test_bench_splits_unique_and_repeated_views() -> None:
    inf = math.inf
    outs = [
        # unique views: two right (one ok, one ambiguous), one wrong ok, one failed
        FrameOutcome(0, "ok", 0.01, 1.0, 10.0, confidence=0.9, truth_in_hypotheses=True, repeated=False),
        FrameOutcome(1, "ambiguous", 0.02, 1.0, 10.0, confidence=0.5, truth_in_hypotheses=True, repeated=False),
        FrameOutcome(2, "ok", 6.0, 90.0, 10.0, confidence=0.8, repeated=False),
        FrameOutcome(3, "no_match", inf, inf, 10.0, confidence=0.0, repeated=False),
        # repeated views: ambiguous with the truth among hypotheses (answer elsewhere), ambiguous without it,
        # ok in the right room, ok in the twin room, low overlap
        FrameOutcome(4, "ambiguous", 6.0, 0.5, 10.0, confidence=0.4, truth_in_hypotheses=True, repeated=True),
        FrameOutcome(5, "ambiguous", 3.0, 20.0, 10.0, confidence=0.4, truth_in_hypotheses=False, repeated=True),
        FrameOutcome(6, "ok", 0.01, 0.5, 10.0, confidence=0.95, truth_in_hypotheses=True, repeated=True),
        FrameOutcome(7, "ok", 6.0, 0.5, 10.0, confidence=0.95, repeated=True, twin_answer=True),
        FrameOutcome(8, "low_overlap", inf, inf, 10.0, confidence=0.1, repeated=True),
        # a frame views.json does not know counts overall only
        FrameOutcome(9, "ok", 0.01, 0.5, 10.0, confidence=0.9, truth_in_hypotheses=True),
    ]
    s = summarize(outs)
    assert s["unique"] == {"frames": 4, "success_5cm_5deg": 0.5, "ok_precision": 0.5, "ok_wrong": 1}
    assert s["repeated"] == {"frames": 5, "ambiguous": 0.4, "ambiguous_with_truth": 0.2, "ok_right_room": 1,
                             "ok_wrong": 1, "ok_twin_room": 1}
    assert s["ok_precision"] == pytest.approx(3 / 5) and s["wrong_ok"] == 2  # overall figures unchanged
    assert set(s["reliability"]) == {"0.0-0.5", "0.5-0.7", "0.7-0.9", "0.9-1.0"}
    json.dumps(s)
    table = format_table({"frames": 10, "skipped": [], "methods": {"cadreg": s}})
    assert "unique views: 4, @5cm/5° 50.0%" in table and "ambiguous with the truth among hypotheses 20.0%" in table
    # Frames without views.json: no unique / repeated keys, the table as before.
    plain = summarize([FrameOutcome(0, "ok", 0.01, 1.0, 10.0)])
    assert "unique" not in plain and "repeated" not in plain
    only_unique = summarize([FrameOutcome(0, "ok", 0.01, 1.0, 10.0, repeated=False)])
    assert only_unique["repeated"]["frames"] == 0 and only_unique["repeated"]["ambiguous_with_truth"] is None


def test_views_doc_gives_the_twin_poses() -> None:
    T_room = make_T(t=[0.5, 0.2, 1.3])
    doc = {"rooms": {"a": {"T_building_room": np.eye(4).tolist()},
                     "b": {"T_building_room": make_T(t=[10.0, 0.0, 0.0]).tolist()}},
           "views": [{"index": 3, "room": "a", "repeated": True, "repeated_in": ["b"], "T_room_camera": T_room.tolist()},
                     {"index": 4, "room": "b", "repeated": False, "repeated_in": [], "T_room_camera": T_room.tolist()}]}
    truth = views_from_doc(doc)
    assert (truth[3].room, truth[3].repeated_in, truth[3].repeated) == ("a", ("b",), True)
    assert isinstance(truth[4], ViewTruth) and not truth[4].repeated
    assert np.allclose(truth[3].T_twins[0][:3, 3], [10.5, 0.2, 1.3])
    with pytest.raises(ValueError, match="views.json"):
        views_from_doc({"views": []})


@pytest.mark.realdata
def test_a_room_without_labels_joins_a_labelled_building_as_unlabelled(scene_mesh, scene_nodes) -> None:
    """A Replica or fused room (a mesh without labels) beside labelled rooms: its vertices read label 0 and no
    instance; rooms of another label set are refused."""
    from dataclasses import replace

    from cadreg.errors import ConfigError
    from cadreg.render.building import building_mesh, building_rooms

    plain = replace(scene_mesh, labels=None, instances=None)
    rooms = building_rooms(_three_rooms_layout("r"), {"r": scene_mesh}, {"r": scene_nodes})
    rooms[1] = replace(rooms[1], mesh=plain)
    building = building_mesh(rooms)
    nv = len(scene_mesh.vertices)
    assert np.array_equal(building.labels[:nv], scene_mesh.labels)
    assert not building.labels[nv:2 * nv].any() and np.all(building.instances[nv:2 * nv] == -1)
    assert building.n_instances == 2 * scene_mesh.n_instances
    rooms[1] = replace(rooms[1], mesh=replace(scene_mesh, label_set="ade20k"))
    with pytest.raises(ConfigError, match="share a label set"):
        building_mesh(rooms)


@pytest.mark.realdata
def test_a_composed_room_without_an_object_keeps_the_floor_it_stood_on(twin_rooms_dir, scene0470_site_dir) -> None:
    """Room "b" of the twin rooms lacks the chair cad-4 and the bin cad-0: inside their boxes it has no point of
    their classes, and the floor and wall points there stay (room "a", the same room moved by ROOM_B_OFFSET_M,
    has both)."""
    from tracking_rooms import DROPPED, ROOM_B_OFFSET_M

    from cadreg.site.bundle import Site
    from cadreg.site.compose import inside_boxes

    room, site = Site.load(scene0470_site_dir), Site.load(twin_rooms_dir)
    nodes = [n for n in room.graph.nodes if n.id in DROPPED]
    for cloud in (site.map, site.raw):
        xyz = cloud.points.astype(np.float64)
        for node in nodes:
            k = site.classes.index(node.cls)
            in_a = inside_boxes(xyz, [node])
            in_b = inside_boxes(xyz - np.array([ROOM_B_OFFSET_M, 0.0, 0.0]), [node])
            assert np.count_nonzero(in_a & (cloud.class_index == k)) > 20
            assert not np.any(in_b & (cloud.class_index == k))
            structure_a = np.count_nonzero(in_a & (cloud.class_index < 0))
            assert structure_a > 20 and np.count_nonzero(in_b & (cloud.class_index < 0)) >= 0.8 * structure_a


def _moved_chair_layout(bundle: str):
    """Rooms a and b, 20 m apart: b has the chair cad-4 turned by 90° about its centre and pushed 0.4 m along y."""
    from cadreg.site.compose import Layout, RoomEntry

    return Layout(site_id="moved", rooms=[
        RoomEntry(name="a", bundle=bundle, T_building_room=np.eye(4).tolist()),
        RoomEntry(name="b", bundle=bundle, T_building_room=make_T(t=[20.0, 0.0, 0.0]).tolist(),
                  move_objects={"cad-4": _chair_move().tolist()}),
    ])


def _chair_move() -> np.ndarray:
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return make_T(turn, CHAIR_M * [1, 1, 0] + [0.0, 0.4, 0.0] - turn @ (CHAIR_M * [1, 1, 0]))


@pytest.mark.realdata
def test_a_composed_room_with_a_moved_object_carries_its_node_and_points(scene0470_site_dir: Path,
                                                                        tmp_path: Path) -> None:
    """`move_objects`: the moved node's centroid and box and its points in both clouds are carried by the
    transform; the floor where it stood stays; a room keeps as many of the object's points as its copy."""
    from cadreg.site.bundle import Site
    from cadreg.site.compose import RoomEntry, compose_site, inside_boxes

    room = Site.load(scene0470_site_dir)
    layout = _moved_chair_layout(str(scene0470_site_dir))
    site = compose_site(layout, tmp_path)
    T_b = make_T(t=[20.0, 0.0, 0.0])
    chair = next(n for n in room.graph.nodes if n.id == "cad-4")
    moved = next(n for n in site.graph.nodes if n.id == "b/cad-4")
    M = T_b @ _chair_move()
    assert np.allclose(moved.centroid, M[:3, :3] @ chair.centroid + M[:3, 3])
    assert np.allclose(moved.box_R, M[:3, :3] @ chair.box_R)
    k = site.classes.index("chair")
    for cloud in (site.map, site.raw):
        xyz = cloud.points.astype(np.float64)
        in_a = inside_boxes(xyz, [chair]) & (cloud.class_index == k)
        old_b = inside_boxes(xyz - [20.0, 0.0, 0.0], [chair])
        new_b = inside_boxes(xyz, [moved]) & (cloud.class_index == k)
        assert in_a.sum() > 20 and new_b.sum() >= in_a.sum() - 3  # (float32 at the box's faces)
        carried = xyz[in_a] @ M[:3, :3].T + M[:3, 3]  # room a's chair points, where room b has them
        assert np.all(cKDTree(xyz[new_b]).query(carried)[0] < 1e-4)
        assert not np.any(old_b & (cloud.class_index == k) & ~new_b)
        assert np.count_nonzero(old_b & (cloud.class_index < 0)) >= 0.8 * np.count_nonzero(
            inside_boxes(xyz, [chair]) & (cloud.class_index < 0))  # the floor under it stays
    assert site.manifest["inputs"]["composed"][1]["move_objects"] == {"cad-4": _chair_move().tolist()}
    assert "move_objects" not in site.manifest["inputs"]["composed"][0]
    with pytest.raises(Exception, match="both dropped and moved"):
        RoomEntry(name="x", bundle="r", T_building_room=np.eye(4).tolist(), drop_objects=["cad-4"],
                  move_objects={"cad-4": np.eye(4).tolist()})
    with pytest.raises(Exception, match="rigid"):
        RoomEntry(name="x", bundle="r", T_building_room=np.eye(4).tolist(),
                  move_objects={"cad-4": (2 * np.eye(4)).tolist()})
    unknown = layout.rooms[0].model_copy(update={"move_objects": {"cad-99": np.eye(4).tolist()}})
    bad = layout.model_copy(update={"rooms": [unknown]})
    with pytest.raises(Exception, match="cad-99"):
        compose_site(bad, tmp_path)


@pytest.mark.realdata
def test_a_bundle_that_several_rooms_copy_is_read_once(scene0470_site_dir: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """`compose_site` reads each bundle once, however many rooms copy it and however its path is spelled (the
    100-room benchmark held 100 reads of one room, 0.9 GB); each room is its copy all the same. Unversioned, for a
    caller that saves it at once, it saves as the same bundle."""
    from cadreg.site import compose
    from cadreg.site.bundle import Site

    reads = []
    load = Site.load
    monkeypatch.setattr(compose.Site, "load", lambda path, **kw: reads.append(path) or load(path, **kw))
    spelled = [str(scene0470_site_dir), str(scene0470_site_dir / "." / ".." / scene0470_site_dir.name),
               str(scene0470_site_dir)]
    layout = compose.Layout(site_id="three", rooms=[
        compose.RoomEntry(name=name, bundle=bundle, T_building_room=make_T(t=[8.0 * k, 0.0, 0.0]).tolist())
        for k, (name, bundle) in enumerate(zip("abc", spelled))])
    site = compose.compose_site(layout, tmp_path)
    assert len(reads) == 1
    room = load(scene0470_site_dir)
    assert [r.id for r in site.regions] == ["a", "b", "c"] and len(site.map) == 3 * len(room.map)
    c = site.regions[2]
    assert np.allclose(site.map.points[c.map_range[0]:c.map_range[1]], room.map.points + [16.0, 0.0, 0.0], atol=1e-4)
    # left for `save` to version (`site compose` saves at once), the same bundle
    unversioned = compose.compose_site(layout, tmp_path, versioned=False)
    assert unversioned.version == ""
    unversioned.save(tmp_path / "saved")
    assert load(tmp_path / "saved").version == site.version


@pytest.mark.realdata
def test_building_mesh_moves_the_faces_of_moved_objects_and_the_oracle_tells_the_rooms_apart(scene_mesh,
                                                                                             scene_nodes) -> None:
    """A moved object's faces are carried by its transform onto copies of their vertices and leave where it stood;
    a view of the chair is then repeated in neither room, a view away from it in both."""
    from cadreg.render import MeshRenderer, camera_rig
    from cadreg.render.building import RepeatOracle, building_mesh, building_rooms
    from cadreg.site.compose import inside_boxes

    rooms = building_rooms(_moved_chair_layout("r"), {"r": scene_mesh}, {"r": scene_nodes})
    b = rooms[1].mesh
    chair = next(n for n in scene_nodes if n.id == "cad-4")
    mine = inside_boxes(scene_mesh.vertices, [chair]) & (scene_mesh.labels == 5)  # NYU40 chair
    own = np.all(mine[scene_mesh.faces], axis=1)
    touching = np.any(mine[scene_mesh.faces], axis=1)
    assert own.sum() > 500
    assert len(b.faces) == len(scene_mesh.faces) - touching.sum() + own.sum()
    n = len(scene_mesh.vertices)
    assert not np.any(mine[b.faces[b.faces < n].reshape(-1)])  # nothing of the chair where it stood
    new = b.faces[np.all(b.faces >= n, axis=1)]
    assert len(new) == own.sum() and np.all(b.labels[new] == 5)
    M = _chair_move()
    used = np.unique(scene_mesh.faces[own])
    assert np.allclose(b.vertices[n:], scene_mesh.vertices[used] @ M[:3, :3].T + M[:3, 3])
    depth_intr, _, T_color_depth = camera_rig()
    oracle = RepeatOracle(MeshRenderer(building_mesh(rooms)), rooms, depth_intr, T_color_depth)
    at_chair = look_at(CAMERA_M, CHAIR_M)
    assert oracle.agreements(0, at_chair)["b"] < 0.9
    assert oracle.repeated_in(0, at_chair) == [] and oracle.repeated_in(1, at_chair) == []
    assert oracle.repeated_in(0, look_at(CAMERA_M, TABLE_CORNER_M)) == ["b"]
