"""Regions and `search_region` (issue 10): a composed building's rooms are regions (site.json, `site info`,
`GET /v1/sites/{id}`), every hypothesis names its region, and a client that says which room it is in gets a
repeated view answered `ok` in that room — through the library, over HTTP (real uvicorn on 127.0.0.1) and over
zenoh (a real peer on loopback, scouting off). Two copies of the real scene0470 room, the second missing a chair
and the bin; the frame is the first of the turning camera of tests/tracking_rooms.py, a view both rooms show."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from cadreg.errors import InvalidFileError, InvalidFrame
from cadreg.localize.localizer import Localizer
from cadreg.result import Status
from cadreg.site.bundle import Site
from cadreg.site.regions import SearchRegion
from service import codec
from service.schemas import SearchRegionIn
from service.settings import Settings
from service.zenoh_server import zenoh_config
from test_service_support import LiveServer, free_ports, multipart
from tracking_rooms import ROOM_B_OFFSET_M, near

pytestmark = pytest.mark.realdata
SITE = "twin-rooms"
ROOM_B = np.eye(4)
ROOM_B[0, 3] = ROOM_B_OFFSET_M


@pytest.fixture(scope="module")
def localizer(twin_rooms_dir: Path) -> Localizer:
    return Localizer.from_site(Site.load(twin_rooms_dir))


# --- regions in the bundle ---------------------------------------------------------------------------------------

def test_composed_rooms_are_regions_with_their_nodes_and_points(scene0470_site_dir: Path, twin_rooms_dir: Path) -> None:
    room, twin = Site.load(scene0470_site_dir), Site.load(twin_rooms_dir)
    a, b = twin.regions
    assert (a.id, b.id) == ("a", "b")
    assert set(a.nodes) == {f"a/{n.id}" for n in room.graph.nodes} and all(n.startswith("b/") for n in b.nodes)
    assert set(a.nodes) | set(b.nodes) == {n.id for n in twin.graph.nodes}
    # each region is its room's slice of the clouds, and its box holds those points
    assert a.map_range == (0, len(room.map)) and b.map_range[1] == len(twin.map)
    assert a.raw_range[0] == 0 and a.raw_range[1] == b.raw_range[0] and b.raw_range[1] == len(twin.raw)
    xb = twin.map.points[slice(*b.map_range)].astype(float)
    assert np.allclose(b.bounds[0], xb.min(axis=0), atol=1e-4) and np.allclose(b.bounds[1], xb.max(axis=0), atol=1e-4)
    assert np.isclose(b.bounds[0][0] - a.bounds[0][0], ROOM_B_OFFSET_M, atol=0.05)
    # a one-room site is one region named after it
    (only,) = room.regions
    assert only.id == room.site_id and only.map_range == (0, len(room.map)) and len(only.nodes) == len(room.graph.nodes)


def test_a_region_range_outside_the_map_is_refused_at_load(twin_rooms_dir: Path, tmp_path: Path) -> None:
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(twin_rooms_dir, bad)
    meta = json.loads((bad / "site.json").read_text())
    meta["regions"][1]["map_range"][1] += 10
    (bad / "site.json").write_text(json.dumps(meta))
    with pytest.raises(InvalidFileError, match="point ranges outside the map"):
        Site.load(bad)


def test_site_info_lists_regions(twin_rooms_dir: Path, capsys) -> None:
    from cadreg.cli.main import main

    assert main(["site", "info", str(twin_rooms_dir), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [r["id"] for r in info["regions"]] == ["a", "b"]
    assert all(r["objects"] > 0 and r["points"] > 0 and len(r["bounds"]) == 2 for r in info["regions"])
    assert all(abs(r["floor_m"]) < 0.1 for r in info["regions"])  # both copies stand on the scan's own floor
    assert main(["site", "info", str(twin_rooms_dir)]) == 0
    assert "2 region(s)" in capsys.readouterr().out


# --- the localizer ---------------------------------------------------------------------------------------------

def test_search_region_forms_are_checked() -> None:
    with pytest.raises(InvalidFrame, match="either"):
        SearchRegion()
    with pytest.raises(InvalidFrame, match="either"):
        SearchRegion(center=np.zeros(3), radius_m=1.0, region_ids=("a",))
    with pytest.raises(InvalidFrame, match="radius_m"):
        SearchRegion(center=np.zeros(3), radius_m=-1.0)
    with pytest.raises(InvalidFrame, match="center"):
        SearchRegion(center=np.array([0.0, np.nan, 0.0]), radius_m=1.0)
    ball = SearchRegion(center=np.array([1.0, 1.0, 1.0]), radius_m=2.0)
    assert ball.allows(np.array([[1.0, 2.0, 1.0], [4.0, 1.0, 1.0]]), []).tolist() == [True, False]


def test_a_repeated_view_is_ambiguous_and_each_hypothesis_names_its_room(localizer: Localizer, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    r = localizer.localize(frame)
    assert r.status == Status.AMBIGUOUS
    assert {"a", "b"} <= {h.region for h in r.hypotheses}
    assert any(h.region == "a" and near(h.T_map_camera, T_true) for h in r.hypotheses)
    assert any(h.region == "b" and near(h.T_map_camera, ROOM_B @ T_true) for h in r.hypotheses)
    assert r.to_dict()["hypotheses"][0]["region"] in ("a", "b")


@pytest.mark.parametrize("room", ["a", "b"])
def test_the_room_given_by_id_answers_the_repeated_view_ok_there(localizer: Localizer, twin_shared_view, room: str) -> None:
    frame, T_true = twin_shared_view
    r = localizer.localize(replace(frame, search_region=SearchRegion(region_ids=(room,))))
    assert r.status == Status.OK
    assert near(r.T_map_camera, T_true if room == "a" else ROOM_B @ T_true)
    assert {h.region for h in r.hypotheses} == {room}


def test_a_ball_around_the_camera_answers_ok_in_its_room(localizer: Localizer, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    centre = (ROOM_B @ T_true)[:3, 3]
    r = localizer.localize(replace(frame, search_region=SearchRegion(center=centre, radius_m=1.0)))
    assert r.status == Status.OK and near(r.T_map_camera, ROOM_B @ T_true)


def test_an_unknown_region_id_is_an_invalid_frame_naming_it(localizer: Localizer, twin_shared_view) -> None:
    frame, _ = twin_shared_view
    with pytest.raises(InvalidFrame, match="nowhere"):
        localizer.localize(replace(frame, search_region=SearchRegion(region_ids=("a", "nowhere"))))


def test_the_label_free_search_stays_in_the_region(localizer: Localizer, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    r = localizer.localize(replace(frame, labels=None, search_region=SearchRegion(region_ids=("b",))))
    assert r.hypotheses and all(h.region == "b" for h in r.hypotheses)
    if r.status == Status.OK:
        assert near(r.T_map_camera, ROOM_B @ T_true)


def test_the_label_free_search_box_counts_the_regions_it_covers(localizer: Localizer, twin_shared_view) -> None:
    """A building's label-free search keeps more nodes a level the more regions its box covers
    (`regions.search_nodes_per_region`): the whole building, a named region, a ball in one room or over both."""
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics

    frame, T_true = twin_shared_view
    R_level_map = localizer.pyramid()[0].R_level_map

    def covered(search_region, rooms=()):
        diag = Diagnostics(site_id="s", bundle_version="v")
        scan = localizer._scan(replace(frame, search_region=search_region), diag, StageTimer(diag.stage_ms))
        return [c for _, _, c in localizer._search_boxes(scan, R_level_map, list(rooms))]

    a, b = localizer.maps.regions
    assert covered(None) == [2]
    assert covered(None, [a, b]) == [1, 1]
    assert covered(SearchRegion(region_ids=("b",))) == [1]
    assert covered(SearchRegion(center=(ROOM_B @ T_true)[:3, 3], radius_m=0.5)) == [1]
    between = 0.5 * (a.bounds.mean(axis=0) + b.bounds.mean(axis=0))
    assert covered(SearchRegion(center=between, radius_m=float(np.linalg.norm(b.bounds[1] - a.bounds[0])))) == [2]


# --- over the wire ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def server(twin_rooms_dir: Path):
    port, zport = free_ports(2)
    settings = Settings(sites_dir=twin_rooms_dir.parent, port=port, workers=1, queue_depth=2, request_timeout_s=60,
                        zenoh_listen=[f"tcp/127.0.0.1:{zport}"])
    live = LiveServer(settings)
    live.zenoh_endpoint = f"tcp/127.0.0.1:{zport}"
    yield live
    live.stop()


def test_http_reports_regions_and_honours_search_region(server, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    info = httpx.get(f"{server.url}/v1/sites/{SITE}", timeout=10).json()
    assert [r["id"] for r in info["regions"]] == ["a", "b"] and all(r["objects"] > 0 for r in info["regions"])
    url = f"{server.url}/v1/sites/{SITE}/localize"
    files, data = multipart(frame, meta_override={"search_region": {"region_ids": ["b"]}})
    body = httpx.post(url, files=files, data=data, timeout=60).json()
    assert body["status"] == "ok" and near(np.array(body["T_map_camera"]), ROOM_B @ T_true)
    assert {h["region"] for h in body["hypotheses"]} == {"b"}
    for bad, why in (({"region_ids": ["nowhere"]}, "nowhere"), ({"center": [0, 0, 0]}, "radius_m"),
                     ({"center": [0, 0, 0], "radius_m": 1, "region_ids": ["a"]}, "either"),
                     ({"region_ids": ["a b"]}, "region_ids")):
        files, data = multipart(frame, meta_override={"search_region": bad})
        r = httpx.post(url, files=files, data=data, timeout=60)
        assert r.status_code == 422 and r.json()["code"] in ("invalid_frame", "invalid_input"), r.text
        assert why in r.text


def test_zenoh_query_honours_search_region(server, twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    config = zenoh_config(Settings(zenoh_mode="peer", zenoh_listen=[], zenoh_connect=[server.zenoh_endpoint]))
    session = zenoh.open(config)
    try:
        time.sleep(0.5)  # let the peers meet
        parts, meta = codec.encode_frame_parts(frame)
        meta = meta.model_copy(update={"search_region": SearchRegionIn(region_ids=["a"])})
        replies = list(session.get(f"cadreg/{SITE}/localize", payload=codec.pack_envelope(parts, meta), timeout=60))
        assert len(replies) == 1 and replies[0].ok is not None
        result = codec.decode_result(replies[0].ok.payload.to_bytes())
        assert result["status"] == "ok" and near(np.array(result["T_map_camera"]), T_true)
    finally:
        session.close()
