"""A building of several storeys: seen from above its rooms overlap, a room straight above its copy repeats it
with a shift along up, and a client naming a room is not answered in the room above or below it.

Two copies of the real scene0470 room, room "b" straight above room "a" (STOREY_M up), missing a chair and the bin
(tests/tracking_rooms.py); the frame is the first of the turning camera, a view both rooms show."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cadreg import Site
from cadreg.localize.localizer import Localizer
from cadreg.localize.twins import RoomTwins
from cadreg.result import Status
from cadreg.site.compose import compose_site, read_layout
from cadreg.site.regions import Region, SearchRegion, Storeys
from tracking_rooms import DROPPED, near

STOREY_M = 3.0
ROOM_B = np.eye(4)
ROOM_B[2, 3] = STOREY_M


def _region(rid: str, z0: float, floor_m: float | None) -> Region:
    return Region(rid, np.array([[0.0, 0.0, z0], [3.5, 2.9, z0 + 1.4]]), (), (0, 0), (0, 0), floor_m)


def test_rooms_whose_floors_lie_a_storey_apart_stand_on_two_storeys_and_a_step_does_not_make_one() -> None:
    storeys = Storeys.of([_region("a", 0.0, 0.05), _region("b", 3.0, 3.05), _region("c", 0.6, 0.65),
                          _region("old", 0.0, None)])
    assert storeys.several and storeys.region.tolist() == [0, 1, 0, -1]
    np.testing.assert_allclose(storeys.base, [0.05, 3.05])
    # a point belongs to the highest storey whose floor lies under it (BELOW_FLOOR_M under it still counts);
    # a region whose floor is not known stands on every storey
    elsewhere = storeys.elsewhere(np.array([1.5, 4.5, 2.9, -1.0]))
    assert elsewhere.tolist() == [[False, True, False, False], [True, False, True, False],
                                  [True, False, True, False], [False, True, False, False]]
    assert not Storeys.of([_region("a", 0.0, 0.0), _region("b", 1.0, 1.0)]).several  # a 1 m step: one storey


@pytest.fixture(scope="module")
def storeys_dir(scene0470_site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("storeys")
    layout = out / "LAYOUT.json"
    layout.write_text(json.dumps({"site_id": "storeys", "rooms": [
        {"name": "a", "bundle": str(scene0470_site_dir), "T_building_room": np.eye(4).tolist()},
        {"name": "b", "bundle": str(scene0470_site_dir), "T_building_room": ROOM_B.tolist(), "drop_objects": DROPPED},
    ]}))
    compose_site(read_layout(layout), out).save(out / "site")
    return out / "site"


@pytest.fixture(scope="module")
def localizer(storeys_dir: Path) -> Localizer:
    return Localizer.from_site(Site.load(storeys_dir))


@pytest.mark.realdata
def test_a_point_lies_in_the_room_of_its_own_storey(localizer: Localizer) -> None:
    a, b = localizer.maps.regions
    assert b.floor_m - a.floor_m == pytest.approx(STOREY_M, abs=0.01)
    above_a = np.array([1.7, 1.4, a.floor_m + 1.4])
    # seen from above both rooms hold both points; the old look-up gave both to the first room
    assert localizer.maps.region_at(above_a).id == "a"
    assert localizer.maps.region_at(above_a + [0.0, 0.0, STOREY_M]).id == "b"


@pytest.mark.realdata
def test_the_room_above_its_copy_repeats_it_with_the_storeys_rise(localizer: Localizer) -> None:
    (b, T_ba), = localizer.twins.of(0)
    assert b == 1
    np.testing.assert_allclose(T_ba, ROOM_B, atol=0.05)
    # without the floors (rooms of one floor keep their heights) they are no copies
    twins = localizer.twins
    flat = RoomTwins(localizer.graph, localizer.node_region, localizer.up, 2)
    assert flat.of(0) == [] and twins.of(1)[0][0] == 0


@pytest.mark.realdata
def test_a_view_both_storeys_show_is_ambiguous_with_both_rooms(localizer: Localizer, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    for labelled in (True, False):
        r = localizer.localize(frame if labelled else replace(frame, labels=None))
        assert r.status == Status.AMBIGUOUS
        assert any(h.region == "a" and near(h.T_map_camera, T_true) for h in r.hypotheses)
        assert any(h.region == "b" and near(h.T_map_camera, ROOM_B @ T_true) for h in r.hypotheses)


@pytest.mark.realdata
@pytest.mark.parametrize("room", ["a", "b"])
def test_the_room_given_by_id_answers_ok_there_not_on_the_other_storey(localizer: Localizer, twin_shared_view,
                                                                       room: str) -> None:
    frame, T_true = twin_shared_view
    named = SearchRegion(region_ids=(room,))
    cameras = np.array([T_true[:3, 3], (ROOM_B @ T_true)[:3, 3]])
    assert named.allows(cameras, localizer.maps.regions).tolist() == [room == "a", room == "b"]
    r = localizer.localize(replace(frame, search_region=named))
    assert r.status == Status.OK
    assert near(r.T_map_camera, T_true if room == "a" else ROOM_B @ T_true)
    assert {h.region for h in r.hypotheses} == {room}


@pytest.mark.realdata
def test_site_show_draws_one_panel_a_storey_with_its_own_points_and_rooms(storeys_dir: Path) -> None:
    from matplotlib.figure import Figure

    from cadreg.site.show import draw_site_top_view, render_site_png

    site = Site.load(storeys_dir)
    storeys = Storeys.of(site.regions)
    for storey, room in ((0, "a"), (1, "b")):
        ax = Figure().add_subplot(1, 1, 1)
        draw_site_top_view(ax, site, storey=storey, max_points=len(site.map), draw_graph=False)
        drawn = sum(len(c.get_offsets()) for c in ax.collections)
        assert drawn == np.count_nonzero(storeys.at(site.map.points[:, 2]) == storey) > 0
        assert [t.get_text() for t in ax.texts] == [room]  # its room's outline, named
    assert render_site_png(site)[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.realdata
def test_site_info_names_the_storeys(storeys_dir: Path, capsys) -> None:
    from cadreg.cli.main import main

    assert main(["site", "info", str(storeys_dir), "--json"]) == 0
    floors = json.loads(capsys.readouterr().out)["storeys"]
    assert len(floors) == 2 and floors[1] - floors[0] == pytest.approx(STOREY_M, abs=0.01)
    assert main(["site", "info", str(storeys_dir)]) == 0
    assert "2 region(s) on 2 storeys" in capsys.readouterr().out
