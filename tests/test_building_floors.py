"""A building's rooms need not share a floor (storeys; scans whose floors lie at other heights): compose stores
each room's floor height, and a frame that sees the floor is placed at its camera height over its own room's floor."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cadreg import Site
from cadreg.geometry import pose_errors
from cadreg.localize.localizer import Localizer
from cadreg.site.compose import compose_site, read_layout

RAISE_M = 1.0  # room "b" stands a storey's step above room "a"


@pytest.fixture(scope="module")
def raised_building(scene0470_site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """Two copies of scene0470, room "b" 6 m along x and RAISE_M up; returns (site dir, T_building_room of b)."""
    out = tmp_path_factory.mktemp("raised")
    T_b = np.eye(4)
    T_b[:3, 3] = [6.0, 0.0, RAISE_M]
    layout = out / "LAYOUT.json"
    layout.write_text(json.dumps({"site_id": "raised", "rooms": [
        {"name": "a", "bundle": str(scene0470_site_dir), "T_building_room": np.eye(4).tolist()},
        {"name": "b", "bundle": str(scene0470_site_dir), "T_building_room": T_b.tolist()},
    ]}))
    compose_site(read_layout(layout), out).save(out / "site")
    return out / "site", T_b


@pytest.mark.realdata
def test_each_room_keeps_its_floor_and_a_view_of_the_raised_room_is_placed_there(raised_building,
                                                                                 twin_shared_view) -> None:
    site_dir, T_b = raised_building
    site = Site.load(site_dir)
    floors = {r.id: r.floor_m for r in site.regions}
    assert abs(floors["a"]) < 0.1 and floors["b"] - floors["a"] == pytest.approx(RAISE_M, abs=0.01)
    frame, T_room_camera = twin_shared_view  # a view both rooms show, the floor in it
    result = Localizer.from_site(site).localize(frame)
    assert any("above floor" in n for n in result.diagnostics.notes)
    poses = [h.T_map_camera for h in result.hypotheses]
    # both rooms show it (ambiguous): the pose in the raised room is as right as the one in the other
    for T_true in (T_room_camera, T_b @ T_room_camera):
        assert min(pose_errors(T, T_true)[0] for T in poses) < 0.05
