"""Corridors in the building benchmark: the layout generator's corridors between pairs of rows, their panels as map
points and as a mesh, a composed building with corridors (regions per segment, its up stated), views rendered in
them, and the bench's corridor figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from cadreg.bench import FrameOutcome, format_table, summarize, views_from_doc, within_5cm_5deg
from cadreg.cli.main import main
from cadreg.errors import ConfigError
from cadreg.geometry import make_T
from cadreg.site.compose import CorridorEntry, Layout, RoomEntry
from cadreg.site.corridor import FLOOR_LABEL, WALL_LABEL, corridor_cloud
from cadreg.site.layout import (CORRIDOR_WALL_M, LayoutConfig, RoomSource, generate_layout, grid_shape,
                                placed_footprint)

CAD_IDS = tuple(f"cad-{k}" for k in range(7))


def _source(name: str, size=(3.5, 2.9), floor_z: float = 0.06) -> RoomSource:
    lo = np.array([-0.2, 0.1])
    return RoomSource(name, f"rooms/{name}", lo, lo + np.array(size, dtype=float), CAD_IDS, floor_z=floor_z)


# --- layout --------------------------------------------------------------------------------------------------------


def test_layout_corridors_run_between_pairs_of_rows_against_every_room() -> None:
    """--corridor-m: corridor c<k> between rows 2k and 2k + 1, its clear width between walls CORRIDOR_WALL_M from
    the footprints, every room's footprint against one of its walls, none over it; the turns and drops of the seed
    are those of the layout without corridors."""
    width = 1.8
    sources = [_source("a"), _source("b", size=(4.0, 2.5), floor_z=0.1)]
    plain = LayoutConfig(site_id="c11", rooms=11, seed=2)
    layout = generate_layout(sources, plain.model_copy(update={"corridor_m": width, "corridor_height_m": 2.7}))
    cols, rows = grid_shape(11)
    assert (cols, rows) == (4, 3)
    assert [c.name for c in layout.corridors] == ["c00", "c01"]  # rows 0-1, and row 2 alone
    boxes = [placed_footprint(sources[k % 2], np.asarray(r.T_building_room)) for k, r in enumerate(layout.rooms)]
    for k, c in enumerate(layout.corridors):
        T = np.asarray(c.T_building_corridor)
        assert np.allclose(T[:3, :3], np.eye(3)) and (c.width_m, c.height_m) == (width, 2.7)
        assert T[2, 3] == pytest.approx(np.median([0.06, 0.1] * 4 if k == 0 else [0.06, 0.1, 0.06]))
        lo_y, hi_y = T[1, 3] - width / 2, T[1, 3] + width / 2
        below = boxes[2 * k * cols:(2 * k + 1) * cols]
        above = boxes[(2 * k + 1) * cols:(2 * k + 2) * cols]
        assert all(b[1, 1] + CORRIDOR_WALL_M == pytest.approx(lo_y) for b in below)  # backs against its wall
        assert all(b[0, 1] - CORRIDOR_WALL_M == pytest.approx(hi_y) for b in above)
        assert T[0, 3] == 0.0 and c.length_m == pytest.approx(max(b[1, 0] for b in below + above))
        for b in boxes:  # no footprint reaches into the corridor or its walls
            assert b[1, 1] <= lo_y - CORRIDOR_WALL_M + 1e-9 or b[0, 1] >= hi_y + CORRIDOR_WALL_M - 1e-9
    without = generate_layout(sources, plain)
    assert not without.corridors
    assert [r.drop_objects for r in layout.rooms] == [r.drop_objects for r in without.rooms]
    assert [np.asarray(r.T_building_room)[:3, :3].tolist() for r in layout.rooms] == \
        [np.asarray(r.T_building_room)[:3, :3].tolist() for r in without.rooms]


def test_layout_storeys_stand_above_every_floor_of_the_storey_below() -> None:
    """Rooms keep their own floors; each storey rises by the storey height plus their spread, so that no floor of a
    storey lies less than a storey over one of the storey below, and the building's storeys are told apart
    (`regions.Storeys`). Raised by the storey height alone, an office whose floor lies 1.19 m under its neighbours'
    had the upper storey's lowest floor 1.81 m over the lower's highest: the four floors counted as one storey."""
    from cadreg.site.regions import Region, Storeys

    sources = [_source("a", floor_z=0.06), _source("office", floor_z=-1.13)]
    config = LayoutConfig(site_id="s8", rooms=8, seed=4, storeys=2, storey_height_m=3.0)
    layout = generate_layout(sources, config)
    floors = np.array([np.asarray(r.T_building_room)[2, 3] + sources[k % 2].floor_z
                       for k, r in enumerate(layout.rooms)])
    lower, upper = floors[:4], floors[4:]
    assert upper.min() - lower.max() == pytest.approx(3.0)
    np.testing.assert_allclose(np.sort(upper) - np.sort(lower), 3.0 + 1.19)
    regions = [Region(f"r{k}", np.array([[0.0, 0.0, f], [3.5, 2.9, f + 2.5]]), (), (0, 0), (0, 0), float(f))
               for k, f in enumerate(floors)]
    assert Storeys.of(regions).region.tolist() == [0] * 4 + [1] * 4
    # rooms sharing one floor rise by the storey height alone
    alike = generate_layout([_source("a"), _source("b", size=(4.0, 2.5))], config)
    assert [np.asarray(r.T_building_room)[2, 3] for r in alike.rooms] == [0.0] * 4 + [3.0] * 4


def test_layout_refuses_a_room_and_a_corridor_of_one_name() -> None:
    room = RoomEntry(name="c00", bundle="rooms/a", T_building_room=np.eye(4).tolist())
    with pytest.raises(ValueError, match="room and corridor names must be distinct"):
        Layout(site_id="x", rooms=[room], corridors=[CorridorEntry(name="c00", T_building_corridor=np.eye(4).tolist(),
                                                                   length_m=5.0, width_m=1.5)])
    with pytest.raises(ValueError, match="rigid"):
        CorridorEntry(name="c", T_building_corridor=(2 * np.eye(4)).tolist(), length_m=5.0, width_m=1.5)


# --- panels ----------------------------------------------------------------------------------------------------


def test_a_corridor_cloud_lies_on_its_panels_facing_in() -> None:
    """Floor and four walls sampled every spacing: each point on one of the five planes inside the corridor's box,
    its normal facing the corridor's inside, about area / spacing² of them."""
    L, W, H, step = 4.0, 1.5, 2.5, 0.05
    cloud = corridor_cloud(L, W, H, step)
    p, n = cloud.points.astype(np.float64), cloud.normals.astype(np.float64)
    assert np.all(p >= [-1e-6, -W / 2 - 1e-6, -1e-6]) and np.all(p <= [L + 1e-6, W / 2 + 1e-6, H + 1e-6])
    on_floor = np.isclose(p[:, 2], 0.0, atol=1e-6)
    on_plane = (on_floor | np.isclose(np.abs(p[:, 1]), W / 2, atol=1e-6) | np.isclose(p[:, 0], 0.0, atol=1e-6)
                | np.isclose(p[:, 0], L, atol=1e-6))
    facing_up = n[:, 2] > 0.99
    assert on_plane.all() and np.all(on_floor[facing_up])
    assert facing_up.sum() == pytest.approx(L * W / step**2, rel=0.1)
    inward = np.array([L / 2, 0.0, H / 2]) - p
    assert np.all(np.einsum("ij,ij->i", n, inward) > 0)
    area = L * W + 2 * L * H + 2 * W * H
    assert len(p) == pytest.approx(area / step**2, rel=0.1)
    assert np.all(cloud.class_index == -1) and np.all(cloud.instance == -1)


def test_a_corridor_mesh_is_its_panels_labelled_floor_and_wall() -> None:
    from cadreg.render.building import corridor_mesh
    from cadreg.render.raycast import MeshRenderer

    entry = CorridorEntry(name="c", T_building_corridor=np.eye(4).tolist(), length_m=6.0, width_m=1.6, height_m=2.4)
    mesh = corridor_mesh(entry)
    assert set(np.unique(mesh.labels)) == {FLOOR_LABEL, WALL_LABEL} and mesh.n_instances == 0
    assert mesh.floor_height_m() == pytest.approx(0.0)
    assert np.allclose(mesh.vertices.min(axis=0), [0, -0.8, 0])
    assert np.allclose(mesh.vertices.max(axis=0), [6, 0.8, 2.4])
    # Rays from inside hit the wall, the floor and the end wall where the panels are.
    renderer = MeshRenderer(mesh)
    origin = np.array([[2.0, 0.0, 1.5]] * 3)
    dirs = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    assert np.allclose(renderer.cast_rays(origin, dirs), [0.8, 1.5, 4.0], atol=1e-5)


# --- bench -------------------------------------------------------------------------------------------------------


def test_bench_counts_corridor_views_apart() -> None:
    inf = math.inf
    outs = [
        FrameOutcome(0, "ok", 0.01, 1.0, 10.0, confidence=0.9, truth_in_hypotheses=True, repeated=False),
        FrameOutcome(1, "ambiguous", 0.02, 1.0, 10.0, confidence=0.4, truth_in_hypotheses=True, repeated=True),
        # corridor views: an ambiguous answer with the truth among its poses, one without, a wrong ok, none
        FrameOutcome(2, "ambiguous", 3.0, 0.5, 10.0, confidence=0.3, truth_in_hypotheses=True, repeated=False,
                     corridor=True),
        FrameOutcome(3, "ambiguous", 3.0, 0.5, 10.0, confidence=0.3, repeated=True, corridor=True),
        FrameOutcome(4, "ok", 6.0, 0.5, 10.0, confidence=0.8, repeated=False, corridor=True),
        FrameOutcome(5, "low_overlap", inf, inf, 10.0, confidence=0.1, repeated=False, corridor=True),
    ]
    s = summarize(outs)
    assert s["unique"]["frames"] == 1 and s["repeated"]["frames"] == 1  # corridor views in neither
    assert s["corridor"] == {"frames": 4, "ok": 1, "ok_wrong": 1, "ambiguous": 0.5, "ambiguous_with_truth": 0.25}
    assert s["per_frame"][2]["corridor"] is True and "corridor" not in s["per_frame"][0]
    table = format_table({"frames": 6, "skipped": [], "methods": {"cadreg": s}})
    assert "corridor views: 4, ok 1, ok wrong 1, ambiguous 50.0%" in table
    plain = format_table({"frames": 2, "skipped": [], "methods": {"cadreg": summarize(outs[:2])}})
    assert "corridor views" not in plain
    doc = {"rooms": {"a": {"T_building_room": np.eye(4).tolist()},
                     "c00": {"T_building_room": make_T(t=[0.0, 5.0, 0.0]).tolist(), "corridor": True}},
           "views": [{"index": 0, "room": "a", "repeated_in": [], "T_room_camera": np.eye(4).tolist()},
                     {"index": 1, "room": "c00", "repeated_in": [], "T_room_camera": np.eye(4).tolist()}]}
    truth = views_from_doc(doc)
    assert not truth[0].corridor and truth[1].corridor


# --- a composed building with a corridor (real scene0470) ---------------------------------------------------------


@pytest.fixture(scope="module")
def corridor_building(scene0470_site_dir: Path, tmp_path_factory: pytest.TempPathFactory):
    """Two scene0470 rooms side by side with a 1.6 m corridor along them (`site layout --corridor-m`), composed."""
    out = tmp_path_factory.mktemp("corridor")
    layout_path = out / "layout.json"
    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "2", "--seed", "1",
                 "--corridor-m", "1.6", "--site-id", "hall2", "--out", str(layout_path)]) == 0
    assert main(["site", "compose", str(layout_path), "--out", str(out / "site")]) == 0
    return layout_path, out / "site"


@pytest.mark.realdata
def test_a_composed_corridor_is_regions_of_points_and_the_building_states_its_up(corridor_building, capsys) -> None:
    from cadreg import Localizer
    from cadreg.site.bundle import Site
    from cadreg.site.compose import CORRIDOR_SEGMENT_M, read_layout

    layout_path, site_dir = corridor_building
    layout = read_layout(layout_path)
    assert '"corridors"' in layout_path.read_text() and len(layout.corridors) == 1
    corridor = layout.corridors[0]
    site = Site.load(site_dir)
    segments = math.ceil(corridor.length_m / CORRIDOR_SEGMENT_M)
    ids = [r.id for r in site.regions]
    assert ids == ["r000", "r001"] + [f"c00.{k}" for k in range(segments)]
    T = np.asarray(corridor.T_building_corridor)
    xs = []
    for region in site.regions[2:]:
        assert region.nodes == () and region.floor_m == pytest.approx(T[2, 3], abs=0.02)
        rows = site.map.points[slice(*region.map_range)].astype(np.float64) - T[:3, 3]
        assert np.all(np.abs(rows[:, 1]) <= corridor.width_m / 2 + 1e-4)
        assert rows[:, 2].max() == pytest.approx(corridor.height_m, abs=1e-4)
        xs.append((rows[:, 0].min(), rows[:, 0].max()))
    assert xs[0][0] == pytest.approx(0.0, abs=1e-4) and xs[-1][1] == pytest.approx(corridor.length_m, abs=1e-4)
    assert all(a[1] <= b[0] for a, b in zip(xs, xs[1:]))  # segments one after the other
    assert site.manifest["inputs"]["corridors"][0]["name"] == "c00"
    # Its walls outnumber its floor: the up is the building's as compose states it, not the map normals' guess.
    assert np.allclose(site.up, [0.0, 0.0, 1.0])
    assert np.allclose(Localizer.from_site(site).up, [0.0, 0.0, 1.0])
    capsys.readouterr()
    assert main(["site", "info", str(site_dir)]) == 0
    assert "c00.0" in capsys.readouterr().out


@pytest.mark.realdata
def test_views_in_a_corridor_are_rendered_and_never_answered_ok_wrongly(corridor_building, scene_parts,
                                                                         tmp_path: Path) -> None:
    """Views are drawn in rooms and corridor alike; a corridor view shows no object and its frame lies on the
    composed map at its pose. Localized: a room view is found (its pose among those reported), and the corridor's,
    which nothing places along a plain hallway, is not answered `ok`."""
    from cadreg.io.frames import RecordedFrames
    from cadreg import Localizer
    from cadreg.render.building import building_rooms, render_building_views
    from cadreg.site.bundle import Site
    from cadreg.site.compose import read_layout
    from cadreg.result import Status

    layout_path, site_dir = corridor_building
    layout = read_layout(layout_path)
    mesh, nodes = scene_parts
    rooms = building_rooms(layout, {layout.rooms[0].bundle: mesh}, {layout.rooms[0].bundle: nodes})
    assert [r.corridor for r in rooms] == [False, False, True] and rooms[2].bundle.startswith("corridor")
    views = render_building_views(rooms, tmp_path / "frames", 5, seed=4)
    hall = [v for v in views if v.corridor]
    room = [v for v in views if not v.corridor]
    assert hall and room and all(v.room == "c00" for v in hall)
    assert hall[0].to_dict()["corridor"] is True and room[0].to_dict()["corridor"] is False
    frames = RecordedFrames.open(tmp_path / "frames")
    loc = Localizer.from_site(Site.load(site_dir))
    for view in (hall[0], room[0]):
        frame, T_true = frames.load(view.index)
        assert np.allclose(T_true, view.T_building_camera, atol=1e-6)
        result = loc.localize(frame, top_k=10)
        reported = [h.T_map_camera for h in result.hypotheses]
        if result.T_map_camera is not None:
            reported.append(result.T_map_camera)
        if view.corridor:
            assert result.status != Status.OK, result.diagnostics.notes
        else:
            assert any(within_5cm_5deg(T, T_true) for T in reported), result.diagnostics.notes


@pytest.fixture(scope="module")
def long_corridor_building(scene0470_site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six scene0470 rooms along a 2.4 m corridor, composed: its corridor segments are its largest regions."""
    out = tmp_path_factory.mktemp("long-corridor")
    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "6", "--seed", "1",
                 "--corridor-m", "2.4", "--site-id", "hall6", "--out", str(out / "layout.json")]) == 0
    assert main(["site", "compose", str(out / "layout.json"), "--out", str(out / "site")]) == 0
    return out / "site"


@pytest.mark.realdata
def test_a_buildings_wall_directions_are_those_of_each_kind_of_region(long_corridor_building: Path) -> None:
    """The label-free search's wall directions of a building (`Localizer.pyramid`) are the mean of those of the
    largest region of each set of regions that repeat one another (`RoomTwins.one_of_each`), not those of its
    largest region: here a corridor segment, whose walls face across it four times as much as along it, while the
    rooms' face both ways alike."""
    from cadreg import Localizer
    from cadreg.localize.bbs import map_direction_histogram
    from cadreg.localize.regions import region_cloud
    from cadreg.site.bundle import Site

    site = Site.load(long_corridor_building)
    loc = Localizer.from_site(site)
    regions = site.regions
    chosen = loc.twins.one_of_each()
    copies = {k: {b for b, _ in loc.twins.of(k)} for k in chosen}
    assert all(any(r == k or r in copies[k] for k in chosen) for r in range(len(regions)))  # every region stood for
    assert [regions[k].id.startswith("r") for k in chosen].count(True) == 1  # the six rooms are copies of one
    pyr, walls, _ = loc.pyramid()

    def directions(region) -> np.ndarray:
        return map_direction_histogram(region_cloud(site, region, "both").normals.astype(np.float64)
                                       @ pyr.R_level_map.T)

    largest_of = [max([regions[k]] + [regions[b] for b in copies[k]], key=lambda r: r.points) for k in chosen]
    assert np.allclose(walls, np.mean([directions(r) for r in largest_of], axis=0))

    def along_over_across(hist: np.ndarray) -> float:  # the mass within 10° of x over that within 10° of y
        centres = (np.arange(len(hist)) + 0.5) * 180.0 / len(hist)
        near = lambda deg: hist[np.abs((centres - deg + 90.0) % 180.0 - 90.0) <= 10.0].sum()  # noqa: E731
        return float(near(0.0) / near(90.0))

    largest = max(regions, key=lambda r: r.points)
    assert largest.id.startswith("c")  # (what the wall directions were measured on before)
    assert along_over_across(directions(largest)) < 0.25  # (the corridor runs along x)
    assert along_over_across(walls) > 1.5 * along_over_across(directions(largest))
    # Quarter turns: the rooms and the corridor face the same ways (their peaks 4° apart), so the deeper search
    # tries the building's yaws only.
    assert not loc.rooms_face_their_own_ways()


@pytest.fixture(scope="module")
def scene_parts(scene0470_dir: Path, scene0470_site_dir: Path):
    from conftest import scene0470_mesh

    from cadreg.site.bundle import Site

    return scene0470_mesh(scene0470_dir), Site.load(scene0470_site_dir).graph.nodes


@pytest.mark.realdata
def test_compose_refuses_a_tilted_corridor_and_region_ids_that_repeat(scene0470_site_dir: Path) -> None:
    from cadreg.site.compose import compose_site

    room = RoomEntry(name="c.0", bundle=str(scene0470_site_dir), T_building_room=np.eye(4).tolist())
    far = make_T(t=[0.0, 10.0, 0.0])
    clash = Layout(site_id="x", rooms=[room], corridors=[
        CorridorEntry(name="c", T_building_corridor=far.tolist(), length_m=4.0, width_m=1.5)])
    with pytest.raises(ConfigError, match="region ids repeat"):
        compose_site(clash, "/")
    tilt = make_T(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]), [0.0, 10.0, 0.0])
    tilted = Layout(site_id="x", rooms=[room.model_copy(update={"name": "a"})], corridors=[
        CorridorEntry(name="c", T_building_corridor=tilt.tolist(), length_m=4.0, width_m=1.5)])
    with pytest.raises(ConfigError, match="corridor 'c': its up"):
        compose_site(tilted, "/")


@pytest.mark.realdata
def test_render_layout_and_bench_carry_the_corridors_through_the_cli(corridor_building, scene0470_dir: Path,
                                                                     tmp_path: Path, capsys) -> None:
    """`cadreg render --layout` of a layout with a corridor: views.json marks the corridor (and its views), the
    printout counts rooms, corridors and corridor views, and `cadreg bench` puts those views in its corridor
    figures."""
    layout_path, site_dir = corridor_building
    out = tmp_path / "frames"
    capsys.readouterr()
    assert main(["render", "--layout", str(layout_path), "--mesh", str(scene0470_dir / "scene0470_00_vh_clean_2.ply"),
                 "--labels", str(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"), "--out", str(out),
                 "--n", "5", "--seed", "4"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    doc = json.loads((out / "views.json").read_text())
    assert (printed["rooms"], printed["corridors"]) == (2, 1)
    assert doc["rooms"]["c00"]["corridor"] is True and "corridor" not in doc["rooms"]["r000"]
    hall = [v for v in doc["views"] if v["corridor"]]
    assert printed["corridor_views"] == len(hall) > 0 and all(v["room"] == "c00" for v in hall)
    report = tmp_path / "bench.json"
    assert main(["bench", "--site", str(site_dir), "--frames", str(out), "--json", str(report)]) == 0
    summary = json.loads(report.read_text())["methods"]["cadreg"]
    assert summary["corridor"]["frames"] == len(hall) and summary["corridor"]["ok_wrong"] == 0
    assert summary["unique"]["frames"] + summary["repeated"]["frames"] == 5 - len(hall)


@pytest.mark.realdata
def test_a_view_from_a_room_into_the_corridor_is_looked_at_in_the_copies_of_the_room(corridor_building) -> None:
    """`_copies_of_view`: a view's copies are those of the room it looks into (its ROI's centre) and, when the
    camera stands in another room, those of the camera's room too. A camera in room r000 looking out into the
    corridor has its view looked at in r001, r000's copy, wherever the corridor's segments repeat; a view inside
    the room has the room's copies only."""
    from cadreg import Localizer
    from cadreg.site.bundle import Site

    _, site_dir = corridor_building
    loc = Localizer.from_site(Site.load(site_dir))
    ids = [r.id for r in loc.maps.regions]
    room, other = ids.index("r000"), ids.index("r001")
    assert [b for b, _ in loc.twins.of(room)] == [other]  # the two rooms are copies
    box = lambda k: np.asarray(loc.maps.regions[k].bounds, dtype=np.float64)  # noqa: E731
    middle = lambda k: 0.5 * (box(k)[0] + box(k)[1])  # noqa: E731
    T = np.eye(4)
    T[:3, 3] = middle(room) + [0.0, 0.0, 0.5]
    segments = [k for k, i in enumerate(ids) if i.startswith("c00.")]
    hall = min(segments, key=lambda k: np.linalg.norm(middle(k)[:2] - T[:2, 3]))
    into_hall = middle(hall) - T[:3, 3]  # the ROI's centre, camera frame (the camera's axes are the map's)
    assert loc._roi_region(T, into_hall) == hall and int(loc.maps.indices_at(T[None, :3, 3])[0]) == room
    assert all(b != other for b, _ in loc.twins.of(hall))  # the corridor alone would not look there

    copies = loc._copies_of_view(T, into_hall)
    (T_ba,) = [T_ba for b, T_ba in copies if b == other]
    assert loc.region_of(T_ba @ T) == "r001"
    assert [b for b, _ in copies if b != other] == [b for b, _ in loc.twins.of(hall)]
    inside = np.array([0.0, 0.0, 0.3])
    assert loc._copies_of_view(T, inside) == loc.twins.of(room)


@pytest.mark.realdata
def test_the_deeper_search_tries_the_yaws_of_rooms_turned_by_odd_angles(scene0470_site_dir: Path,
                                                                       tmp_path: Path) -> None:
    """Six scene0470 rooms each turned by a random angle along a 2.4 m corridor (layout seed 2): the corridor's one
    axis rules the building's wall directions, and the yaws they allow for a label-free view of room r003's
    chairs (view 22 of `cadreg render --layout ... --n 60 --seed 7`) hold none within 11° of its own. The first
    search answers it weakly; the deeper search of a building whose rooms face their own ways also tries each
    room's own yaws (`FallbackStage._yaws`) and finds it. Without that second search it is answered 5.4 m off."""
    from dataclasses import replace

    from cadreg import Localizer
    from cadreg.io.frames import RecordedFrames
    from cadreg.render import LabelledMesh, render_frames
    from cadreg.result import Status
    from cadreg.site.bundle import Site

    assert main(["site", "layout", "--room", f"scene0470={scene0470_site_dir}", "--rooms", "6", "--seed", "2",
                 "--corridor-m", "2.4", "--any-turn", "--site-id", "t2", "--out", str(tmp_path / "t2.json")]) == 0
    assert main(["site", "compose", str(tmp_path / "t2.json"), "--out", str(tmp_path / "t2")]) == 0
    # the building's mesh alone, as the README writes it: no frames folder
    assert main(["render", "--layout", str(tmp_path / "t2.json"), "--mesh-out", str(tmp_path / "t2.ply"), "--n", "0"]) == 0
    T_map_camera = np.array([[-0.140655032752, -0.504402685515, 0.851935497914, 0.826878311245],
                             [-0.989927283716, 0.085667588727, -0.112716623422, 9.762783796896],
                             [-0.016128692302, -0.859208353711, -0.511371557869, 1.696305434483],
                             [0.0, 0.0, 0.0, 1.0]])
    mesh = LabelledMesh.from_ply(tmp_path / "t2.ply", tmp_path / "t2.ply")
    render_frames(mesh, tmp_path / "view", 0, poses=[T_map_camera], seed=0)
    frame, T_true = RecordedFrames.open(tmp_path / "view").load(0)
    frame = replace(frame, labels=None)
    site = Site.load(tmp_path / "t2")

    loc = Localizer.from_site(site)
    assert loc.rooms_face_their_own_ways()
    r = loc.localize(frame)
    searches = [n for n in r.diagnostics.notes if n.startswith("label-free search")]
    assert len(searches) == 3, r.diagnostics.notes  # the first, then the deeper one twice: the site's yaws, the rooms'
    assert r.status == Status.OK and within_5cm_5deg(r.T_map_camera, T_true), r.diagnostics.notes

    without = Localizer.from_site(site)
    without.rooms_face_their_own_ways = lambda: False
    r = without.localize(frame)
    assert not (r.status == Status.OK and within_5cm_5deg(r.T_map_camera, T_true)), r.diagnostics.notes
