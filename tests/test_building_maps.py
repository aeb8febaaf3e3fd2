"""A building's maps (issue 10): the distance field is built room by room when the site is composed and stored
(field.npy, hashed like the other files), the clouds are memory-mapped at load (read-only, paged in as used),
each region's refinement map holds its neighbours' points within the halo, and rooms that tie with the best are
all verified or, beyond the budget, reported unverified and never answered `ok`. Two copies of the real scene0470
room (tests/tracking_rooms.py), the second missing a chair and the bin."""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cadreg.config import LabelFreeConfig, LocalizeConfig, MatchConfig, RegionConfig
from cadreg.errors import BundleIntegrityError, InvalidFileError
from cadreg.localize.localizer import Localizer
from cadreg.localize.regions import halo_cloud, region_cloud
from cadreg.localize.score import DistanceField, building_field
from cadreg.result import Status
from cadreg.site.bundle import Site
from cadreg.site.regions import SearchRegion

pytestmark = pytest.mark.realdata


def test_the_stored_field_is_the_whole_maps_field(twin_rooms_dir: Path) -> None:
    site = Site.load(twin_rooms_dir)
    assert site.field_grid is not None and site.field_grid.grid.dtype == np.uint8
    every = site.cloud("both").points.astype(np.float64)
    exact = DistanceField(every, max_cells=10**9)
    stored = DistanceField.from_grid(site.field_grid)
    assert stored.voxel_m == exact.voxel_m and np.allclose(stored.origin, exact.origin)
    rng = np.random.default_rng(0)
    lo, hi = every.min(axis=0) - 0.5, every.max(axis=0) + 0.5
    probes = np.concatenate([rng.uniform(lo, hi, size=(20000, 3)), every[rng.choice(len(every), 5000)]
                             + rng.normal(scale=0.05, size=(5000, 3))])
    # one byte a cell: within half a step (truncate / 255 / 2 ≈ 1 mm) of the exact transform, everywhere
    assert np.max(np.abs(stored.lookup(probes) - exact.lookup(probes))) <= stored.step_m / 2 + 1e-6


def test_building_field_over_separate_clouds_matches_one_transform() -> None:
    rng = np.random.default_rng(1)
    a = rng.uniform([0, 0, 0], [2, 2, 1], size=(3000, 3))
    b = rng.uniform([2.2, 0, 0], [4, 2, 1], size=(3000, 3))  # 0.2 m apart: their fields overlap
    grid = building_field([a, b], voxel_m=0.05)
    exact = DistanceField(np.concatenate([a, b]), voxel_m=0.05)
    probes = rng.uniform([-0.5, -0.5, -0.5], [4.5, 2.5, 1.5], size=(20000, 3))
    assert np.max(np.abs(DistanceField.from_grid(grid).lookup(probes) - exact.lookup(probes))) <= 0.5 / 255 / 2 + 1e-6


def test_a_building_is_memory_mapped_read_only_and_its_field_is_hashed(twin_rooms_dir: Path, tmp_path: Path) -> None:
    mapped, read = Site.load(twin_rooms_dir), Site.load(twin_rooms_dir, mapped=False)
    assert mapped.mapped_rows and not read.mapped_rows
    for a, b in ((mapped.map, read.map), (mapped.raw, read.raw)):
        assert np.array_equal(a.points, b.points) and np.array_equal(a.class_index, b.class_index)
        assert not a.points.flags.writeable
    mapped.release("map", slice(0, len(mapped.map)))  # pages handed back are read again on use
    assert np.array_equal(mapped.map.points, read.map.points)
    bad = tmp_path / "bad"
    shutil.copytree(twin_rooms_dir, bad)
    grid = np.load(bad / "field.npy")
    grid[5, 5, 5] ^= 1
    np.save(bad / "field.npy", grid)
    with pytest.raises(BundleIntegrityError, match="field.npy"):
        Site.load(bad)


def test_a_worker_maps_the_stored_pyramid_when_its_settings_are_those_it_was_built_with(twin_rooms_dir: Path,
                                                                                         tmp_path: Path) -> None:
    site = Site.load(twin_rooms_dir)
    assert site.pyramid is not None and not site.pyramid.grids.flags.writeable
    mapped = Localizer.from_site(site).pyramid()[0]
    assert np.shares_memory(mapped.grids[0], site.pyramid.grids)
    unstored = Site.load(twin_rooms_dir)
    unstored.pyramid = None  # a bundle composed before pyramids were stored: the worker builds its own
    built = Localizer.from_site(unstored).pyramid()[0]
    assert not np.shares_memory(built.grids[0], site.pyramid.grids)
    assert all(np.array_equal(a, b) for a, b in zip(mapped.grids, built.grids)) and len(mapped.grids) == len(built.grids)
    assert mapped.to_stored().to_manifest() == built.to_stored().to_manifest()
    # other settings, or another up: the stored pyramid is not theirs, and it is left alone
    other = Localizer.from_site(site, LocalizeConfig(label_free=LabelFreeConfig(tau_m=0.2))).pyramid()[0]
    assert not np.shares_memory(other.grids[0], site.pyramid.grids) and other.built_with["tau_m"] == 0.2
    tilted = Site.load(twin_rooms_dir)
    tilted.pyramid = replace(tilted.pyramid, built_with={**tilted.pyramid.built_with, "up": [0.0, 0.01, 1.0]})
    assert not np.shares_memory(Localizer.from_site(tilted).pyramid()[0].grids[0], site.pyramid.grids)
    # the grids are hashed like every file, and site.json's layout is checked
    bad = tmp_path / "bad"
    shutil.copytree(twin_rooms_dir, bad)
    grids = np.load(bad / "pyramid.npy")
    grids[0, 7] ^= 1
    np.save(bad / "pyramid.npy", grids)
    with pytest.raises(BundleIntegrityError, match="pyramid.npy"):
        Site.load(bad)
    shutil.copy(twin_rooms_dir / "pyramid.npy", bad / "pyramid.npy")
    meta = json.loads((bad / "site.json").read_text())
    del meta["pyramid"]["map_lo_level"]
    (bad / "site.json").write_text(json.dumps(meta))
    with pytest.raises(InvalidFileError, match="site.json: malformed 'pyramid'.*map_lo_level"):
        Site.load(bad)


def test_a_regions_map_holds_its_neighbours_within_the_halo(twin_rooms_dir: Path) -> None:
    site = Site.load(twin_rooms_dir)
    a, b = site.regions
    own = region_cloud(site, a, "raw")
    gap = b.bounds[0][0] - a.bounds[1][0]
    assert len(halo_cloud(site, site.regions, a, "raw", halo_m=gap / 2)) == len(own)  # the halo stops short of b
    halo = halo_cloud(site, site.regions, a, "raw", halo_m=gap + 1.0)
    borrowed = halo.points[len(own):].astype(float)
    assert len(borrowed) > 0 and np.all(borrowed[:, 0] >= b.bounds[0][0] - 1e-4)
    assert np.all(borrowed[:, 0] <= a.bounds[1][0] + gap + 1.0 + 1e-4)


def test_the_stored_region_grids_are_each_regions_halo_on_the_fitness_grid(twin_rooms_dir: Path, tmp_path: Path) -> None:
    from cadreg.localize.point_tree import LEAF_SIZE, tree_order
    from cadreg.localize.points import voxel_indices
    from cadreg.localize.refine import FITNESS_VOXEL_M

    site = Site.load(twin_rooms_dir)
    grids = site.region_grids
    lc = LocalizeConfig()
    assert grids is not None and grids.matches(cloud=lc.refine.map_points, halo_m=lc.regions.halo_m,
                                               voxel_m=FITNESS_VOXEL_M)
    assert not grids.points.flags.writeable  # memory-mapped, like the clouds
    assert grids.tree_leaf == LEAF_SIZE
    for k, region in enumerate(site.regions):
        halo = halo_cloud(site, site.regions, region, grids.cloud, grids.halo_m)
        keep = voxel_indices(halo.points.astype(np.float64), grids.voxel_m)
        keep = keep[tree_order(halo.points[keep])]  # stored in the order of the region's KD-tree
        rows = grids.rows(k)
        assert np.array_equal(rows["xyz"], halo.points[keep]) and np.array_equal(rows["rgb"], halo.colors[keep])
        assert np.array_equal(rows["cls"], halo.class_index[keep])
        grids.release(k)  # pages handed back are read again on use
        assert np.array_equal(grids.rows(k)["xyz"], halo.points[keep])
    bad = tmp_path / "bad"
    shutil.copytree(twin_rooms_dir, bad)
    rows = np.load(bad / "regions.npy")
    rows["xyz"][7, 0] += 0.5
    np.save(bad / "regions.npy", rows)
    with pytest.raises(BundleIntegrityError, match="regions.npy"):
        Site.load(bad)


def test_region_maps_from_the_stored_grids_answer_as_the_maps_built_on_use(twin_rooms_dir: Path,
                                                                            twin_shared_view) -> None:
    frame, T_true = twin_shared_view
    stored_site, built_site, unordered_site = (Site.load(twin_rooms_dir) for _ in range(3))
    built_site.region_grids = None  # a bundle composed before the grids were stored
    # one composed before they were stored in the order of their trees
    unordered_site.region_grids = replace(unordered_site.region_grids, tree_leaf=0)
    in_a = replace(frame, search_region=SearchRegion(region_ids=("a",)))
    stored, built, unordered = (Localizer.from_site(s) for s in (stored_site, built_site, unordered_site))
    a, b, c = stored.localize(in_a), built.localize(in_a), unordered.localize(in_a)
    assert a.status == b.status == c.status == Status.OK
    assert np.linalg.norm(a.T_map_camera[:3, 3] - T_true[:3, 3]) < 0.05
    made, on_use, ordered_on_use = (loc.maps.index(loc.maps.regions[0]) for loc in (stored, built, unordered))
    # the stored grid is the map built on use (the region's halo, one point per fitness voxel, in tree order): the
    # same points, and the same answer
    assert np.array_equal(made.refine_map.fit_xyz, on_use.refine_map.fit_xyz)
    assert np.array_equal(made.refine_map.fit_cls, on_use.refine_map.fit_cls)
    # a stored grid in another order is put in tree order on use: the same points (within a leaf, in another order)
    def rows(refine_map) -> np.ndarray:
        table = np.column_stack([refine_map.fit_xyz, refine_map.fit_cls])
        return table[np.lexsort(table.T)]

    assert np.array_equal(rows(made.refine_map), rows(ordered_on_use.refine_map))
    assert made.refine_map.fit_xyz.base is made.refine_map.xyz  # read in order: not copied, not sorted
    assert np.allclose(a.T_map_camera, b.T_map_camera, atol=1e-9) and np.allclose(a.T_map_camera, c.T_map_camera,
                                                                                atol=1e-9)
    # settings the grids were not made with: the localizer builds its own
    other = Localizer.from_site(stored_site, LocalizeConfig(regions=RegionConfig(halo_m=1.0)))
    assert len(other.maps.index(other.maps.regions[0]).refine_map.xyz) != len(made.refine_map.xyz)


def test_tied_rooms_beyond_the_budget_are_reported_unverified_and_the_answer_is_not_ok(twin_rooms_dir: Path,
                                                                                         twin_shared_view) -> None:
    frame, _ = twin_shared_view
    site = Site.load(twin_rooms_dir)
    both = Localizer.from_site(site).localize(frame)
    assert both.status == Status.AMBIGUOUS
    # the other room comes in through the graph or as the answer's view moved into the room that repeats it
    assert {h.region for h in both.hypotheses if h.source in ("graph", "twin")} == {"a", "b"}
    one = Localizer.from_site(site, LocalizeConfig(regions=RegionConfig(max_verified=1))).localize(frame)
    assert one.status == Status.AMBIGUOUS
    unverified = [h for h in one.hypotheses if h.source == "graph:unverified"]
    assert len(unverified) == 1 and unverified[0].region in ("a", "b")
    assert any("not verified" in n for n in one.diagnostics.notes)


def test_an_uncertain_answer_lists_its_close_rivals_beyond_top_k(twin_rooms_dir: Path, twin_shared_view) -> None:
    # The view both rooms show, without labels: the label-free pose and the copy of its view in the other room tie.
    # Held to a pose spread no pose meets, the answer is `uncertain` (it lies nowhere in particular, nor does its
    # rival), and the rival room stays listed, as an `ambiguous` answer lists it, even past top_k = 1.
    frame, _ = twin_shared_view
    site = Site.load(twin_rooms_dir)
    loose = Localizer.from_site(site, LocalizeConfig(match=MatchConfig(max_pose_std_m=1e-5)))
    r = loose.localize(replace(frame, labels=None), top_k=1)
    assert r.status == Status.UNCERTAIN and r.T_map_camera is None, r.diagnostics.notes
    assert {h.region for h in r.hypotheses} == {"a", "b"}, [(h.region, h.source) for h in r.hypotheses]
    assert r.hypotheses[0].T_map_camera is not None
    # the same frame held to the usual spread: `ambiguous`, the same two rooms
    tied = Localizer.from_site(site).localize(replace(frame, labels=None), top_k=1)
    assert tied.status == Status.AMBIGUOUS and {h.region for h in tied.hypotheses} == {"a", "b"}


def test_region_structures_are_bounded_by_the_cache(twin_rooms_dir: Path, twin_shared_view) -> None:
    frame, _ = twin_shared_view
    loc = Localizer.from_site(Site.load(twin_rooms_dir), LocalizeConfig(regions=RegionConfig(max_cached=1)))
    # each answer is refined in its own room (the other is compared along the frame's rays, no map built)
    for room in ("a", "b"):
        out = loc.localize(replace(frame, search_region=SearchRegion(region_ids=(room,))))
        assert out.status == Status.OK and out.hypotheses[0].region == room
    assert loc.maps.cached() == ["b"] and loc.maps.built == 2  # both rooms were built, one is kept
    out = loc.localize(replace(frame, labels=None))
    assert out.status in (Status.AMBIGUOUS, Status.UNCERTAIN, Status.OK, Status.LOW_OVERLAP)
    assert len(loc.maps.cached()) == 1


def test_a_rooms_refinement_reads_its_region_map_and_keeps_what_it_made(twin_rooms_dir: Path, twin_shared_view) -> None:
    frame, _ = twin_shared_view
    loc = Localizer.from_site(Site.load(twin_rooms_dir))
    in_a = replace(frame, search_region=SearchRegion(region_ids=("a",)))
    first = loc.localize(in_a)
    a = loc.maps.index(loc.maps.regions[0])
    # the GICP paired the frame with the region's fitness grid: no small_gicp target, normals made where it paired
    assert first.diagnostics.refinement.method == "grid_gicp" and a.refine_map._sg_fine is None
    made = a.refine_map.normals.known
    assert 0 < made < len(a.refine_map.fit_xyz)
    second = loc.localize(in_a)
    assert a.refine_map.normals.known == made  # the same frame again pairs with the same points: nothing new made
    assert first.status == second.status == Status.OK
    assert np.allclose(first.T_map_camera, second.T_map_camera, atol=1e-9)


def test_a_buildings_label_free_search_keeps_the_regions_node_budget(twin_rooms_dir: Path, twin_shared_view) -> None:
    frame, _ = twin_shared_view
    site = Site.load(twin_rooms_dir)

    def search_note(label_free_nodes: int, building_nodes: int, per_region: int = 0, room: str | None = None) -> str:
        config = LocalizeConfig(label_free=LabelFreeConfig(max_nodes=label_free_nodes),
                                regions=RegionConfig(search_max_nodes=building_nodes,
                                                     search_nodes_per_region=per_region))
        search = None if room is None else SearchRegion(region_ids=(room,))
        notes = Localizer.from_site(site, config).localize(replace(frame, labels=None,
                                                                   search_region=search)).diagnostics.notes
        return next(n for n in notes if n.startswith("label-free search"))

    # the building's budget (regions.search_max_nodes) bounds the search, not the one-room one (label_free.max_nodes)
    assert "node cap reached" in search_note(100_000, 10)
    assert "node cap reached" not in search_note(10, 100_000)
    # ... or, when more, regions.search_nodes_per_region for each of the regions the search box covers (both here)
    assert "node cap reached" in search_note(10, 10, per_region=100)
    assert "node cap reached" not in search_note(10, 10, per_region=50_000)
    # a box of one room (here the one the client names; a weak graph answer's rooms alike) keeps a room's budget
    assert "node cap reached" in search_note(10, 100_000, per_region=50_000, room="a")
    assert "node cap reached" not in search_note(100_000, 10, room="a")


def test_site_json_describes_the_field(twin_rooms_dir: Path) -> None:
    meta = json.loads((twin_rooms_dir / "site.json").read_text())
    assert "field.npy" in meta["files"] and meta["field"]["shape"] == list(np.load(twin_rooms_dir / "field.npy").shape)


def test_fpfh_in_a_building_searches_one_room_never_the_whole_building(twin_rooms_dir: Path, twin_shared_view) -> None:
    """The last resort (FPFH + RANSAC) over a whole building would cost seconds a room and a copy of the building:
    it runs on the map of one room (the one the client names, or the graph's best), else not at all."""
    frame, _ = twin_shared_view
    site = Site.load(twin_rooms_dir)
    loc = Localizer.from_site(site, LocalizeConfig(label_free=LabelFreeConfig(enabled=False)))
    bare = replace(frame, labels=None)  # no objects: the graph has nothing, the fallback is all there is
    nowhere = loc.localize(bare)
    assert nowhere.T_map_camera is None and nowhere.status != Status.OK
    assert any("fpfh-ransac skipped" in n for n in nowhere.diagnostics.notes), nowhere.diagnostics.notes
    a = next(r for r in site.regions if r.id == "a")
    assert loc.maps.index(a).fpfh is None
    named = loc.localize(replace(bare, search_region=SearchRegion(region_ids=("a",))))
    assert not any("fpfh-ransac skipped" in n for n in named.diagnostics.notes)
    assert loc.maps.index(a).fpfh is not None and loc._fpfh is None  # one room's features, not the building's
    assert len(loc.maps.index(a).fpfh.target.points) < len(site.cloud("raw").points)
    # the room's own box, not its refinement map's halo of the neighbour's points
    from cadreg.localize.fallback_stage import ROOM_MARGIN_M
    target = np.asarray(loc.maps.index(a).fpfh.target.points)
    assert np.all(target >= a.bounds[0] - ROOM_MARGIN_M - 1e-6) and np.all(target <= a.bounds[1] + ROOM_MARGIN_M + 1e-6)
    halo = loc.maps.index(a).refine_map.xyz
    assert not np.all((halo >= a.bounds[0] - ROOM_MARGIN_M) & (halo <= a.bounds[1] + ROOM_MARGIN_M))
    assert all(h.region == "a" for h in named.hypotheses if h.T_map_camera is not None)


# Run in a fresh process: compiled signatures pile up across the tests of one, and would hide a kind of grid or an
# array layout that `Localizer.warm` left out.
_COMPILES_ON_FRAMES = """
import json, pickle, sys
from dataclasses import replace
from numba.core.registry import CPUDispatcher
from cadreg.localize import Localizer, cluster, field_kernels, gravity, grid_gicp, match, point_tree, points, twins
from cadreg.localize import view_kernels
from cadreg.site.bundle import Site

def signatures():
    return {f"{m.__name__}.{name}": sorted(map(str, f.signatures))
            for m in (cluster, field_kernels, gravity, grid_gicp, match, point_tree, points, twins, view_kernels)
            for name, f in vars(m).items() if isinstance(f, CPUDispatcher)}

loc = Localizer.from_site(Site.load(sys.argv[1])).warm()
warmed = signatures()
frame = pickle.loads(open(sys.argv[2], "rb").read())
methods = [loc.localize(f).diagnostics.refinement.method for f in (frame, replace(frame, labels=None))]
new = {k: [s for s in v if s not in warmed.get(k, [])] for k, v in signatures().items()}
print(json.dumps({"methods": methods, "compiled": {k: v for k, v in new.items() if v}}))
"""


@pytest.mark.parametrize("kind", ["building", "room"])
def test_a_warmed_localizer_compiles_nothing_on_its_first_frames(kind: str, twin_rooms_dir: Path,
                                                                 scene0470_site_dir: Path, twin_shared_view,
                                                                 tmp_path: Path) -> None:
    # A loop called with an array layout or a kind of grid that `compile_loops` did not warm compiles again on a
    # worker's first frame (seconds): small_gicp's column-major points did, in the grid GICP; a room's float field
    # would, now that a localizer warms the loops for its own field's kind only.
    frame, _ = twin_shared_view
    (tmp_path / "frame.pkl").write_bytes(pickle.dumps(frame))
    site_dir = twin_rooms_dir if kind == "building" else scene0470_site_dir
    run = subprocess.run([sys.executable, "-c", _COMPILES_ON_FRAMES, str(site_dir), str(tmp_path / "frame.pkl")],
                         capture_output=True, text=True, timeout=600, cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(run.stdout.splitlines()[-1])
    assert report["methods"] == (["grid_gicp"] * 2 if kind == "building" else ["small_gicp"] * 2)
    assert report["compiled"] == {}


def test_an_uncertain_answer_lists_its_pose_once(twin_rooms_dir: Path, twin_shared_view) -> None:
    # Uncertain: the refined pose goes first among the hypotheses, and the candidates at it (the winner's coarse
    # pose) are not listed again beside it.
    from cadreg.localize.match import distinct_pairs

    frame, T_true = twin_shared_view
    loc = Localizer.from_site(Site.load(twin_rooms_dir), LocalizeConfig(match=MatchConfig(min_ok_confidence=1.0)))
    for f in (frame, replace(frame, labels=None)):
        r = loc.localize(replace(f, search_region=SearchRegion(region_ids=("a",))))
        assert r.status == Status.UNCERTAIN and r.T_map_camera is None
        assert np.linalg.norm(r.hypotheses[0].T_map_camera[:3, 3] - T_true[:3, 3]) < 0.05
        poses = np.array([h.T_map_camera for h in r.hypotheses])
        assert distinct_pairs(poses, poses)[np.triu_indices(len(poses), 1)].all()


def test_a_buildings_answer_on_one_object_is_held_to_the_higher_view_bar(twin_rooms_dir: Path,
                                                                         twin_shared_view) -> None:
    # One matched object pins a pose less than several: below RegionConfig.min_one_object_view_agreement the
    # fallbacks join. A bar of 1.0 for one-object answers, the usual one for the others: the frame with only its
    # largest object labelled searches without labels too, the frame with all its objects does not.
    frame, T_true = twin_shared_view
    site = Site.load(twin_rooms_dir)
    classes = site.classes_for_labels(frame.label_set, frame.labels)
    ids, counts = np.unique(frame.labels[classes >= 0], return_counts=True)
    only_largest = np.where(frame.labels == ids[np.argmax(counts)], frame.labels, 0).astype(frame.labels.dtype)
    one = replace(frame, labels=only_largest, search_region=SearchRegion(region_ids=("a",)))
    loc = Localizer.from_site(site, LocalizeConfig(regions=RegionConfig(min_one_object_view_agreement=1.0)))

    def searched(f) -> tuple[bool, int]:
        r = loc.localize(f)
        assert np.linalg.norm((r.T_map_camera if r.T_map_camera is not None else r.hypotheses[0].T_map_camera)[:3, 3]
                              - T_true[:3, 3]) < 0.05
        return any(n.startswith("label-free search") for n in r.diagnostics.notes), len(r.diagnostics.scan_objects)

    assert searched(one) == (True, 1)
    full_searched, objects = searched(replace(frame, search_region=SearchRegion(region_ids=("a",))))
    assert objects > 1 and not full_searched
