"""Site bundle: exact round trip, content versions, integrity checks, label lookup; a site from labelled points."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from cadreg.errors import BundleIntegrityError, ConfigError, InvalidFileError, InvalidFrame
from cadreg.site.build import site_from_labelled_points
from cadreg.site.bundle import DATA_FILES, SETTLED_NS, FileCheck, Site

COLUMNS = ("points", "colors", "normals", "instance", "class_index", "source")


def labelled_room(seed: int = 0):
    """A 3 × 2 m floor (NYU40 2) with a chair-like blob (5) and a door-like panel (8); colours per part."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, 3.0, 0.03)
    fx, fy = np.meshgrid(g, g[g < 2.0])
    floor = np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], axis=1)
    cx, cy, cz = np.meshgrid(np.linspace(0.5, 1.0, 11), np.linspace(0.5, 1.0, 11), np.linspace(0.0, 0.9, 19))
    chair = np.stack([cx.ravel(), cy.ravel(), cz.ravel()], axis=1) + rng.normal(scale=0.003, size=(cx.size, 3))
    dy, dz = np.meshgrid(np.linspace(0.8, 1.7, 31), np.linspace(0.0, 2.0, 67))
    door = np.stack([np.full(dy.size, 2.9), dy.ravel(), dz.ravel()], axis=1)
    pts = np.vstack([floor, chair, door])
    labels = np.concatenate([np.full(len(floor), 2), np.full(len(chair), 5), np.full(len(door), 8)])
    colors = np.zeros((len(pts), 3), np.uint8)
    colors[labels == 2] = (120, 120, 120)
    colors[labels == 5] = (200, 30, 30)
    colors[labels == 8] = (150, 100, 50)
    return pts.astype(np.float32), colors, labels


@pytest.fixture(scope="module")
def small_site() -> Site:
    pts, colors, labels = labelled_room()
    return site_from_labelled_points(pts, colors, None, labels, site_id="room", inputs={"kind": "synthetic"})


def test_site_from_labelled_points_finds_the_objects(small_site):
    s = small_site
    by_cls = {n.cls: n for n in s.graph.nodes}
    assert sorted(by_cls) == ["chair", "door"] and all(n.source == "cluster" for n in s.graph.nodes)
    np.testing.assert_allclose(by_cls["chair"].centroid, [0.75, 0.75, 0.45], atol=0.03)
    np.testing.assert_allclose(by_cls["door"].centroid, [2.9, 1.25, 1.0], atol=0.03)
    assert s.graph.graph.number_of_edges() == 0  # 2.2 m apart > δ
    assert len(s.map.points) == len(s.raw.points) and np.all(s.map.source == 0)
    # points of a node carry its instance id; floor points carry none
    for i, n in enumerate(s.graph.nodes):
        assert (s.map.instance == i).sum() == n.points
    assert np.all(s.map.class_index[(s.map.points[:, 2] == 0) & (s.map.points[:, 0] < 0.45)] == -1)
    np.testing.assert_allclose(np.linalg.norm(s.map.normals, axis=1), 1.0, atol=1e-5)


def test_round_trip_is_bit_exact(small_site, tmp_path):
    small_site.save(tmp_path / "b")
    loaded = Site.load(tmp_path / "b")
    for cloud in ("map", "raw"):
        for name in COLUMNS:
            a, b = getattr(getattr(small_site, cloud), name), getattr(getattr(loaded, cloud), name)
            assert a.dtype == b.dtype and a.shape == b.shape, (cloud, name)
            assert a.tobytes() == b.tobytes(), (cloud, name)
    assert loaded.site_id == "room" and loaded.version == small_site.version and len(loaded.version) == 12
    assert loaded.graph.to_dict() == small_site.graph.to_dict()
    assert loaded.classes == small_site.classes and loaded.label_maps == small_site.label_maps
    meta = json.loads((tmp_path / "b" / "site.json").read_text())
    assert set(meta["files"]) == set(DATA_FILES) and meta["inputs"] == {"kind": "synthetic"}
    assert meta["build_config"]["graph"]["edge_max_m"] == 1.5 and meta["schema"] == "cadreg.site/1"
    # saving the loaded site again gives the same bytes for every data file
    loaded.save(tmp_path / "c")
    for name in DATA_FILES:
        assert (tmp_path / "b" / name).read_bytes() == (tmp_path / "c" / name).read_bytes()


def test_a_save_that_fails_leaves_the_bundle_as_it_was(small_site, tmp_path, monkeypatch):
    """`Site.save` writes each file as it is encoded (`BundleWriter`), and replaces the bundle's files only once every
    one is written: a failure part way leaves the folder's bundle as it was, loadable, with no stray file; a file
    where the folder should be is refused, naming it."""
    small_site.save(tmp_path / "b")
    before = {p.name: p.read_bytes() for p in (tmp_path / "b").iterdir()}
    encoded = Site._data_files

    def fails_after_the_clouds(site):
        for k, item in enumerate(encoded(site)):
            if k == 2:
                raise OSError("disk full")
            yield item

    monkeypatch.setattr(Site, "_data_files", fails_after_the_clouds)
    changed = Site.load(tmp_path / "b")
    changed.site_id = "other"
    with pytest.raises(OSError, match="disk full"):
        changed.save(tmp_path / "b")
    assert {p.name: p.read_bytes() for p in (tmp_path / "b").iterdir()} == before
    monkeypatch.undo()
    assert Site.load(tmp_path / "b").site_id == "room"
    (tmp_path / "f").write_text("not a folder")
    with pytest.raises(InvalidFileError, match="is a file"):
        small_site.save(tmp_path / "f")


def test_version_follows_content(small_site):
    pts, colors, labels = labelled_room()
    again = site_from_labelled_points(pts, colors, None, labels, site_id="room", inputs={})
    assert again.version == small_site.version  # same content, same version (build time is not content)
    # an unsaved site already describes itself as its site.json will
    assert set(again.manifest["files"]) == set(DATA_FILES) and again.manifest["version"] == again.version
    assert again.manifest["schema"] == "cadreg.site/1" and again.manifest["counts"]["nodes"] == 2
    colors2 = colors.copy()
    colors2[0] = (1, 2, 3)
    other = site_from_labelled_points(pts, colors2, None, labels, site_id="room", inputs={})
    assert other.version != small_site.version


def test_modified_file_is_refused_naming_it(small_site, tmp_path):
    small_site.save(tmp_path / "b")
    for name in DATA_FILES:
        d = tmp_path / name
        shutil.copytree(tmp_path / "b", d)
        blob = bytearray((d / name).read_bytes())
        blob[-1] ^= 0x01
        (d / name).write_bytes(bytes(blob))
        with pytest.raises(BundleIntegrityError, match=rf"{name}: sha256 does not match"):
            Site.load(d)
    d = tmp_path / "version"
    shutil.copytree(tmp_path / "b", d)
    meta = json.loads((d / "site.json").read_text())
    meta["version"] = "000000000000"
    (d / "site.json").write_text(json.dumps(meta))
    with pytest.raises(BundleIntegrityError, match="site.json.*version"):
        Site.load(d)


def test_missing_or_malformed_bundle_files(small_site, tmp_path):
    small_site.save(tmp_path / "b")
    d = tmp_path / "missing"
    shutil.copytree(tmp_path / "b", d)
    (d / "raw.ply").unlink()
    with pytest.raises(InvalidFileError, match="raw.ply: cannot read"):
        Site.load(d)
    with pytest.raises(InvalidFileError, match="site.json: cannot read"):
        Site.load(tmp_path / "nowhere")
    d = tmp_path / "badjson"
    shutil.copytree(tmp_path / "b", d)
    (d / "site.json").write_text("{")
    with pytest.raises(InvalidFileError, match="site.json: not valid JSON"):
        Site.load(d)
    (d / "site.json").write_text(json.dumps({"schema": "something/else"}))
    with pytest.raises(InvalidFileError, match="not a cadreg site"):
        Site.load(d)


def test_classes_for_labels(small_site):
    s = small_site
    idx = s.classes_for_labels("nyu40", np.array([[5, 2], [8, 39]], dtype=np.uint16))
    assert [[s.class_name(int(i)) for i in row] for row in idx] == [["chair", None], ["door", "otherfurniture"]]
    assert s.class_name(int(s.classes_for_labels("shapenet", np.array([2747177]))[0])) == "otherfurniture"
    with pytest.raises(InvalidFrame, match=r"no label map 'ade20k'; known label sets: \['nyu40', 'shapenet'\]"):
        s.classes_for_labels("ade20k", np.array([1]))


def test_bad_inputs_to_site_from_labelled_points():
    pts, colors, labels = labelled_room()
    with pytest.raises(ValueError, match="colors"):
        site_from_labelled_points(pts, colors[:-1], None, labels, site_id="x", inputs={})
    with pytest.raises(ValueError, match="labels"):
        site_from_labelled_points(pts, colors, None, labels[:-1], site_id="x", inputs={})
    unlabelled = site_from_labelled_points(pts, colors, None, None, site_id="x", inputs={})
    assert unlabelled.graph.nodes == [] and np.all(unlabelled.map.class_index == -1)


def test_cloud_picks_raw_enhanced_or_both(small_site):
    s = small_site
    assert s.cloud("raw") is s.raw and s.cloud("enhanced") is s.map
    both = s.cloud("both")
    assert len(both) == len(s.raw) + len(s.map)
    assert both.points[: len(s.raw)].tobytes() == s.raw.points.tobytes()  # raw first
    with pytest.raises(ConfigError, match="unknown map cloud 'all'"):
        s.cloud("all")


def test_delta_comes_from_the_build_parameters(small_site):
    assert small_site.edge_max_m == small_site.manifest["build_config"]["graph"]["edge_max_m"] == 1.5
    from cadreg.config import GraphConfig, SiteBuildConfig

    pts, colors, labels = labelled_room()
    wide = site_from_labelled_points(pts, colors, None, labels, site_id="room", inputs={},
                                     config=SiteBuildConfig(graph=GraphConfig(edge_max_m=3.0)))
    assert wide.edge_max_m == 3.0 and wide.graph.graph.number_of_edges() == 1  # 2.2 m apart < δ now


def test_read_manifest_checks_without_parsing(small_site, tmp_path, monkeypatch):
    small_site.save(tmp_path / "b")
    import cadreg.pointset as pointset

    def boom(*args, **kwargs):
        raise AssertionError("read_manifest parsed a PLY")

    monkeypatch.setattr(pointset.PointSet, "from_ply_bytes", classmethod(boom))
    manifest = Site.read_manifest(tmp_path / "b")
    assert manifest["version"] == small_site.version and manifest["counts"]["points"] == len(small_site.map)
    blob = bytearray((tmp_path / "b" / "raw.ply").read_bytes())
    blob[-1] ^= 0x01
    (tmp_path / "b" / "raw.ply").write_bytes(bytes(blob))
    with pytest.raises(BundleIntegrityError, match="raw.ply: sha256 does not match"):
        Site.read_manifest(tmp_path / "b")
    assert Site.read_manifest(tmp_path / "b", verify=False)["version"] == small_site.version


def test_files_another_process_checked_are_not_hashed_again_unless_they_changed(small_site, tmp_path, monkeypatch):
    import cadreg.site.bundle as bundle

    small_site.save(tmp_path / "b")
    time.sleep(SETTLED_NS / 1e9 + 0.1)  # a file written less than that before its check gets no stamp (below)
    meta, checked = Site.check_files(tmp_path / "b")
    assert meta["version"] == small_site.version and set(checked) == set(DATA_FILES)
    hashed: list[str] = []
    real = bundle.sha256_file
    monkeypatch.setattr(bundle, "sha256_file", lambda path: hashed.append(Path(path).name) or real(path))
    # mapped: the clouds are streamed, not read whole (a building's load), so only the graph's bytes are hashed
    site = Site.load(tmp_path / "b", mapped=True, checked=checked)
    assert hashed == [] and site.version == small_site.version and len(site.map) == len(small_site.map)
    # without the check's findings, or with a hash site.json does not list, every streamed file is hashed again
    Site.load(tmp_path / "b", mapped=True)
    assert sorted(hashed) == ["map.ply", "raw.ply"]
    hashed.clear()
    Site.load(tmp_path / "b", mapped=True, checked={**checked, "raw.ply": FileCheck("0" * 64, checked["raw.ply"].stamp)})
    assert hashed == ["raw.ply"]
    # a file written since the check is hashed again, and refused when its bytes differ (same size, one bit)
    original = (tmp_path / "b" / "raw.ply").read_bytes()
    blob = bytearray(original)
    blob[-1] ^= 0x01
    (tmp_path / "b" / "raw.ply").write_bytes(bytes(blob))
    hashed.clear()
    with pytest.raises(BundleIntegrityError, match="raw.ply: sha256 does not match"):
        Site.load(tmp_path / "b", mapped=True, checked=checked)
    assert hashed == ["raw.ply"]
    # written back as it was, it is hashed again (its stamp moved) and passes
    (tmp_path / "b" / "raw.ply").write_bytes(original)
    # other bytes of the same size with the modification time set back: the change time still tells
    stamp = checked["map.ply"].stamp
    blob = bytearray((tmp_path / "b" / "map.ply").read_bytes())
    blob[-1] ^= 0x01
    (tmp_path / "b" / "map.ply").write_bytes(bytes(blob))
    os.utime(tmp_path / "b" / "map.ply", ns=(stamp.mtime_ns, stamp.mtime_ns))
    hashed.clear()
    with pytest.raises(BundleIntegrityError, match="map.ply: sha256 does not match"):
        Site.load(tmp_path / "b", mapped=True, checked=checked)
    assert sorted(hashed) == ["map.ply", "raw.ply"]
    # written back as they were: they pass, but a check right after the writes gives them no stamp to trust
    blob[-1] ^= 0x01
    (tmp_path / "b" / "map.ply").write_bytes(bytes(blob))
    _, fresh = Site.check_files(tmp_path / "b")
    assert set(fresh) == set(DATA_FILES) - {"raw.ply", "map.ply"}


def test_a_file_written_while_it_was_hashed_gets_no_stamp(small_site, tmp_path, monkeypatch):
    import cadreg.site.bundle as bundle

    small_site.save(tmp_path / "b")
    time.sleep(SETTLED_NS / 1e9 + 0.1)
    real = bundle.file_stamp
    seen: dict[str, int] = {}

    def moving(path):  # raw.ply's second stamp (after its hash) differs: something wrote it meanwhile
        name = Path(path).name
        seen[name] = seen.get(name, 0) + 1
        stamp = real(path)
        return stamp._replace(ctime_ns=stamp.ctime_ns + 1) if name == "raw.ply" and seen[name] > 1 else stamp

    monkeypatch.setattr(bundle, "file_stamp", moving)
    _, checked = Site.check_files(tmp_path / "b")
    assert set(checked) == set(DATA_FILES) - {"raw.ply"}


def test_a_stated_up_is_read_back_and_a_malformed_one_refused(small_site, tmp_path):
    assert small_site.up is None  # a site built from a scan leaves its up to the localizer
    small_site.manifest["up"] = [0.0, 2.0, 0.0]
    small_site.save(tmp_path / "b")
    np.testing.assert_allclose(Site.load(tmp_path / "b").up, [0.0, 1.0, 0.0])
    for bad in ([0.0, 0.0], [0.0, 0.0, 0.0], "up", [1.0, float("nan"), 0.0]):
        d = tmp_path / f"bad{len(list(tmp_path.iterdir()))}"
        shutil.copytree(tmp_path / "b", d)
        meta = json.loads((d / "site.json").read_text())
        meta["up"] = bad
        (d / "site.json").write_text(json.dumps(meta))
        with pytest.raises(InvalidFileError, match="site.json.*'up'"):
            Site.load(d)
    small_site.manifest.pop("up")
