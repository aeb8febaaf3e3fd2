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


@pytest.mark.realdata
def test_a_room_stating_another_up_is_levelled_by_the_layout_and_refused_unlevelled(scene0470_site_dir: Path,
                                                                                    tmp_path: Path) -> None:
    """A fused room's frame is its first camera's: `site layout` turns a bundle whose stated up is not +z so that
    it is (its footprint measured level), and `site compose` refuses rooms whose ups disagree."""
    from scipy.spatial.transform import Rotation

    from cadreg.errors import ConfigError
    from cadreg.geometry import make_T
    from cadreg.site.compose import Layout, RoomEntry
    from cadreg.site.layout import LayoutConfig, RoomSource, generate_layout

    T_tilt = make_T(Rotation.from_euler("x", 90, degrees=True).as_matrix(), [0.0, 0.0, 0.0])
    one = Layout(site_id="tilted", rooms=[RoomEntry(name="t", bundle=str(scene0470_site_dir),
                                                    T_building_room=T_tilt.tolist())])
    tilted = compose_site(one, tmp_path)
    tilted.manifest["up"] = (T_tilt[:3, :3] @ [0.0, 0.0, 1.0]).tolist()  # as a fused site states it
    tilted.save(tmp_path / "tilted")
    sources = [RoomSource.from_site("s", str(scene0470_site_dir), Site.load(scene0470_site_dir)),
               RoomSource.from_site("t", str(tmp_path / "tilted"), Site.load(tmp_path / "tilted"))]
    assert np.allclose(sources[1].size, sources[0].size, atol=0.01)  # the same footprint, measured level
    layout = generate_layout(sources, LayoutConfig(rooms=2, seed=0, site_id="b"))
    T_b = np.array(layout.rooms[1].T_building_room)
    np.testing.assert_allclose(T_b[:3, :3] @ tilted.up, [0.0, 0.0, 1.0], atol=1e-9)
    building = compose_site(layout, tmp_path)
    np.testing.assert_allclose(building.up, [0.0, 0.0, 1.0], atol=1e-6)
    floors = [r.floor_m for r in building.regions]
    assert abs(floors[0] - floors[1]) < 0.02
    unlevelled = Layout(site_id="u", rooms=[layout.rooms[0], RoomEntry(name="t", bundle=str(tmp_path / "tilted"),
                                                                       T_building_room=np.eye(4).tolist())])
    with pytest.raises(ConfigError, match="level it with its T_building_room"):
        compose_site(unlevelled, tmp_path)


@pytest.mark.realdata
def test_views_are_drawn_level_in_a_room_whose_own_frame_is_not(scene0470_dir: Path, tmp_path: Path) -> None:
    """A fused room's frame is its first camera's and its `T_building_room` levels it: its views are drawn on its
    mesh turned level (`render.building._RoomSamplers`), standing at a camera's height over its floor, looking
    down a little, as in a room whose frame is level. Drawn on the mesh as it stands, with z across the floor, no
    position passed the sampler's height checks and the render stopped."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from cadreg.config import RenderConfig
    from cadreg.geometry import make_T
    from cadreg.render.building import BuildingRoom, render_building_views
    from conftest import scene0470_mesh

    level = scene0470_mesh(scene0470_dir)
    T_room_level = make_T(Rotation.from_euler("x", 90, degrees=True).as_matrix(), [0.0, 0.0, 0.0])
    tilted = dataclasses.replace(level, vertices=level.vertices @ T_room_level[:3, :3].T)  # z no longer up
    T_b = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [6.0, 0.0, 0.0]) @ np.linalg.inv(T_room_level)
    rooms = [BuildingRoom("a", "level", np.eye(4), level), BuildingRoom("t", "tilted", T_b, tilted)]
    config = RenderConfig()
    views = render_building_views(rooms, tmp_path / "frames", 12, seed=3, config=config)
    floor = level.floor_height_m()
    assert {v.room for v in views} == {"a", "t"}
    for v in views:
        T = v.T_building_camera
        assert config.height_min_m - 0.01 <= T[2, 3] - floor <= config.height_max_m + 0.01
        pitch_down = np.degrees(np.arcsin(-T[2, 2]))  # the optical axis below the horizon
        assert config.pitch_min_deg - 0.5 <= pitch_down <= config.pitch_max_deg + 0.5
