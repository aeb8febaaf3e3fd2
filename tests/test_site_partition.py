"""A building scanned in one piece is cut into its rooms (`cadreg/site/partition.py`): the floor plan's rooms split
at doorways, a hall too wide for one region cut into tiles, and `site build` of a scan holding three copies of the
real scene0470 room (one mesh, as a scan of a whole floor comes) gives three regions, searched as a composed
building's rooms are: a view all three show is `ambiguous`, with each room's pose among its hypotheses."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cadreg import Site
from cadreg.config import PartitionConfig
from cadreg.io.ply import read_ply, write_ply
from cadreg.localize.localizer import Localizer
from cadreg.result import Status
from cadreg.site.partition import FloorPlan, partitioned, rooms_of, storey_floors
from tracking_rooms import CAMERA_M, LOOK_FROM_M, look_at, near

COPY_PITCH_M = 4.1  # the room is 3.5 m wide: copies 0.6 m apart along x
COPIES = 3
STOREY_M = 3.0


def test_free_floor_splits_into_rooms_at_a_doorway_and_every_cell_gets_a_room() -> None:
    # 10 m x 5 m of free floor at 0.1 m cells, a wall across it at x = 5 m with a 0.8 m doorway
    free = np.ones((100, 50), dtype=bool)
    free[[0, -1], :] = free[:, [0, -1]] = False
    free[50, :] = False
    free[50, 20:28] = True
    rooms = rooms_of(free, PartitionConfig())
    assert rooms.min() >= 1 and set(np.unique(rooms)) == {1, 2}
    assert len(set(rooms[:50].ravel())) == 1 and len(set(rooms[51:].ravel())) == 1
    assert rooms[10, 25] != rooms[90, 25]
    # a wider opening (1.6 m) does not part them
    free[50, 15:31] = True
    assert set(np.unique(rooms_of(free, PartitionConfig()))) == {1}
    # nor does anything part a map of narrow floor only: one room
    assert set(np.unique(rooms_of(np.eye(30, dtype=bool), PartitionConfig()))) == {1}


def _floor_and_walls(x_m: float, y_m: float, spacing_m: float = 0.05) -> np.ndarray:
    """(n, 3) points of a bare rectangular room: its floor at z 0 and its walls up to 2.5 m."""
    x, y = np.meshgrid(np.arange(0, x_m, spacing_m), np.arange(0, y_m, spacing_m), indexing="ij")
    floor = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    z = np.arange(0, 2.5, spacing_m)
    walls = []
    for a, b in (((0, 0), (x_m, 0)), ((0, y_m), (x_m, y_m)), ((0, 0), (0, y_m)), ((x_m, 0), (x_m, y_m))):
        t = np.arange(0, 1, spacing_m / max(abs(b[0] - a[0]), abs(b[1] - a[1])))
        xs, zs = np.meshgrid(t, z, indexing="ij")
        walls.append(np.stack([a[0] + xs.ravel() * (b[0] - a[0]), a[1] + xs.ravel() * (b[1] - a[1]), zs.ravel()],
                              axis=1))
    return np.concatenate([floor] + walls)


def test_a_hall_or_a_corridor_longer_than_tile_m_is_cut_into_equal_tiles_and_a_room_is_not() -> None:
    hall = FloorPlan(_floor_and_walls(20.0, 4.0), 0.0, PartitionConfig())
    assert hall.region_names() == ["room0.0.0", "room0.1.0", "room0.2.0", "room0.3.0"]
    # the tiles run along the hall, 5 m each
    xs = np.array([[2.5, 2.0, 0.0], [7.5, 2.0, 0.0], [12.5, 2.0, 0.0], [17.5, 2.0, 0.0]])
    assert hall.region_at(xs).tolist() == [0, 1, 2, 3]
    # a 7 m corridor: two halves, cut at its middle (copies of each other, as `site compose` cuts a corridor)
    corridor = FloorPlan(_floor_and_walls(7.0, 2.4), 0.0, PartitionConfig())
    assert corridor.region_names() == ["room0.0.0", "room0.1.0"]
    assert corridor.region_at(np.array([[3.45, 1.2, 0.0], [3.55, 1.2, 0.0]])).tolist() == [0, 1]
    room = FloorPlan(_floor_and_walls(6.0, 4.0), 0.0, PartitionConfig())
    assert room.region_names() == ["room0"]


def test_a_room_sized_map_and_a_map_whose_up_is_not_z_stay_one_region(scene0470_site_dir: Path,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    site = Site.load(scene0470_site_dir)
    assert partitioned(site) is site  # 3.5 m x 2.9 m
    tilted = Site(site.site_id, "", dict(site.manifest) | {"up": [0.0, 1.0, 0.0]}, site.map, site.raw, site.graph,
                  site.classes, site.label_maps)
    with caplog.at_level("INFO", logger="cadreg.site"):
        assert partitioned(tilted, PartitionConfig(above_m=1.0)) is tilted
    assert "kept as one region: its up is not its z" in caplog.text
    # and with the limit below its size, the one room is one region all the same (no second core)
    assert partitioned(site, PartitionConfig(above_m=1.0)) is site


def _scan_of_copies(scene0470_dir: Path, offsets: list[tuple[float, float, float]], out: Path) -> Path:
    """One scan PLY (mesh, colours, NYU40 labels) of copies of the real scene0470 room, each moved by an offset."""
    mesh = read_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply")
    labels = read_ply(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply").vertex["label"]
    vertex, faces = mesh.vertex, np.asarray(mesh.elements["face"]["vertex_indices"])
    n = len(vertex["x"])
    merged = {k: np.concatenate([np.asarray(v) + (offset["xyz".index(k)] if k in ("x", "y", "z") else 0)
                                 for offset in offsets]).astype(np.asarray(v).dtype) for k, v in vertex.items()}
    merged["label"] = np.tile(np.asarray(labels), len(offsets))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, merged, np.concatenate([faces + c * n for c in range(len(offsets))]))
    return out


def _build(scan: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cadreg.cli.main", "site", "build", "--scan", str(scan),
                           "--out", str(out), *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def floor_scan(scene0470_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """COPIES copies of the room in a row along x, as one scan."""
    return _scan_of_copies(scene0470_dir, [(COPY_PITCH_M * c, 0.0, 0.0) for c in range(COPIES)],
                           tmp_path_factory.mktemp("floor-scan") / "floor.ply")


@pytest.fixture(scope="module")
def floor_site(floor_scan: Path) -> Path:
    out = floor_scan.parent / "site"
    run = _build(floor_scan, out)
    assert run.returncode == 0, run.stderr
    assert f"{COPIES} regions" in run.stdout
    return out


def test_site_build_of_a_floor_scan_gives_one_region_a_room_with_its_objects_and_the_stored_field(
        floor_site: Path) -> None:
    manifest = json.loads((floor_site / "site.json").read_text())
    assert {"field.npy", "regions.npy"} <= set(manifest["files"]) and manifest["up"] == [0.0, 0.0, 1.0]
    site = Site.load(floor_site)
    regions = sorted(site.regions, key=lambda r: r.bounds[0, 0])
    assert [r.id for r in regions] == [f"room{k}" for k in range(COPIES)]
    for k, region in enumerate(regions):
        # each region is its copy of the room: its box, its points, its objects
        np.testing.assert_allclose(region.bounds[:, 0], [COPY_PITCH_M * k, COPY_PITCH_M * k + 3.5], atol=0.15)
        rows = site.map.points[slice(*region.map_range)]
        assert np.all((rows[:, 0] >= COPY_PITCH_M * k - 0.1) & (rows[:, 0] <= COPY_PITCH_M * k + 3.6))
        centroids = np.array([n.centroid for n in site.graph.nodes if n.id in region.nodes])
        assert len(region.nodes) == len(site.graph.nodes) // COPIES
        assert np.all(np.abs(centroids[:, 0] - (COPY_PITCH_M * k + 1.75)) < 1.9)


def test_a_view_the_scanned_copies_all_show_is_ambiguous_with_each_rooms_pose(
        floor_site: Path, floor_scan: Path, tmp_path: Path) -> None:
    from cadreg.io.frames import RecordedFrames
    from cadreg.render import LabelledMesh, render_frames

    T_true = look_at(CAMERA_M, LOOK_FROM_M)  # the table's corner, in the first copy
    render_frames(LabelledMesh.from_ply(floor_scan, floor_scan), tmp_path, 0, poses=[T_true], seed=0)
    frame, _ = RecordedFrames.open(tmp_path).load(0)
    result = Localizer.from_site(Site.load(floor_site)).localize(frame)
    assert result.status == Status.AMBIGUOUS, result.diagnostics.notes
    # ranked as a building's poses are: along the frame's rays through the stored field (one region: by fit)
    assert any("view agreement" in note for note in result.diagnostics.notes), result.diagnostics.notes
    for k in range(COPIES):
        T = T_true.copy()
        T[0, 3] += COPY_PITCH_M * k
        found = [h for h in [result] + result.hypotheses if near(h.T_map_camera, T)]
        assert found, f"no pose in room{k}"
    assert {h.region for h in result.hypotheses} >= {f"room{k}" for k in range(COPIES)}


def test_site_build_keeps_one_region_when_told_and_names_a_bad_limit(floor_scan: Path, tmp_path: Path) -> None:
    run = _build(floor_scan, tmp_path / "one", "--rooms-above-m", "0")
    assert run.returncode == 0, run.stderr
    manifest = json.loads((tmp_path / "one" / "site.json").read_text())
    assert len(manifest["regions"]) == 1 and "field.npy" not in manifest["files"]
    bad = _build(floor_scan, tmp_path / "bad", "--rooms-above-m", "-1")
    assert bad.returncode == 2 and "--rooms-above-m" in bad.stderr and not (tmp_path / "bad").exists()


def test_storeys_floors_are_the_wide_surfaces_facing_up_a_storey_apart() -> None:
    lower, upper = _floor_and_walls(10.0, 5.0), _floor_and_walls(10.0, 5.0) + [0.0, 0.0, 3.0]
    # a table top 0.75 m up, 2 m x 1 m, and a cabinet's top 2.1 m up, 1 m x 0.5 m: no storey
    x, y = np.meshgrid(np.arange(1, 3, 0.05), np.arange(1, 2, 0.05))
    table = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.75)], axis=1)
    cabinet = table[(table[:, 0] < 2) & (table[:, 1] < 1.5)] + [5.0, 0.0, 1.35]

    def floors(*parts: np.ndarray) -> np.ndarray:
        xyz = np.concatenate(parts)
        normals = np.zeros_like(xyz)
        normals[:, 2] = np.isin(xyz[:, 2], [0.0, 0.75, 2.1, 3.0])  # floors and tops face up, walls across
        return storey_floors(xyz, normals, 0.0, PartitionConfig())

    np.testing.assert_allclose(floors(lower, upper, table, cabinet), [0.0, 3.0], atol=0.05)
    np.testing.assert_allclose(floors(lower, table, cabinet), [0.0])


def test_a_scan_of_two_storeys_is_cut_by_storey_and_a_view_of_the_upper_room_is_found_there(
        scene0470_dir: Path, tmp_path: Path) -> None:
    from cadreg.io.frames import RecordedFrames
    from cadreg.render import LabelledMesh, render_frames

    # three copies on the ground, a fourth straight above the middle one, a storey up
    offsets = [(COPY_PITCH_M * c, 0.0, 0.0) for c in range(COPIES)] + [(COPY_PITCH_M, 0.0, STOREY_M)]
    scan = _scan_of_copies(scene0470_dir, offsets, tmp_path / "storeys.ply")
    run = _build(scan, tmp_path / "site")
    assert run.returncode == 0, run.stderr
    site = Site.load(tmp_path / "site")
    floors = {r.id: r.floor_m for r in site.regions}
    assert sorted(floors) == ["s0.room0", "s0.room1", "s0.room2", "s1.room0"]
    ground = floors["s0.room0"]
    assert all(f == pytest.approx(ground) for k, f in floors.items() if k.startswith("s0."))
    assert floors["s1.room0"] == pytest.approx(ground + STOREY_M, abs=0.05)
    upper = next(r for r in site.regions if r.id == "s1.room0")
    assert len(upper.nodes) == len(site.graph.nodes) // len(offsets)
    # a view of the upper room: its pose there is among the answers, named by its storey's room
    T_true = look_at(CAMERA_M, LOOK_FROM_M)
    T_true[:3, 3] += offsets[-1]
    render_frames(LabelledMesh.from_ply(scan, scan), tmp_path / "frames", 0, poses=[T_true], seed=0)
    frame, _ = RecordedFrames.open(tmp_path / "frames").load(0)
    result = Localizer.from_site(site).localize(frame)
    found = [h.region for h in result.hypotheses if near(h.T_map_camera, T_true)]
    assert found == ["s1.room0"], (result.status, result.diagnostics.notes)


def test_render_layout_writes_a_building_as_one_scan_that_site_build_cuts_into_its_rooms(
        scene0470_site_dir: Path, tmp_path: Path) -> None:
    from cadreg.io.ply import read_scan
    from tracking_rooms import DROPPED

    rooms = []
    for k in range(COPIES):
        T = np.eye(4)
        T[0, 3] = COPY_PITCH_M * k
        rooms.append({"name": f"r{k}", "bundle": str(scene0470_site_dir), "T_building_room": T.tolist()}
                     | ({"drop_objects": DROPPED} if k == COPIES - 1 else {}))
    layout = tmp_path / "LAYOUT.json"
    layout.write_text(json.dumps({"site_id": "row", "rooms": rooms}))
    scan = tmp_path / "row.ply"
    run = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "render", "--layout", str(layout), "--mesh-out",
                          str(scan), "--n", "0", "--out", str(tmp_path / "frames")], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    mesh = read_scan(scan)
    # the scan holds what its faces do: none of the vertices the last copy's missing chair and bin had
    assert np.array_equal(np.unique(mesh.faces), np.arange(len(mesh.points)))
    assert mesh.labels is not None
    built = _build(scan, tmp_path / "site")
    assert built.returncode == 0 and f"{COPIES} regions" in built.stdout, built.stderr
    regions = sorted(Site.load(tmp_path / "site").regions, key=lambda r: r.bounds[0, 0])
    assert [r.id for r in regions] == [f"room{k}" for k in range(COPIES)]
    assert len(regions[-1].nodes) < len(regions[0].nodes) == len(regions[1].nodes)
    assert regions[-1].points < regions[0].points
