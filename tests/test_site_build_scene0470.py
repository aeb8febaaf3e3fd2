"""The scene0470 site built from the real scan, labels, Scan2CAD alignment and ShapeNet CADs (acceptance figures).

The bundle comes from the session fixture `scene0470_site_dir` (tests/conftest.py), built once.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from cadreg.errors import InvalidFileError
from cadreg.io.ply import read_scan
from cadreg.site.build import build_site
from cadreg.site.bundle import Site

pytestmark = pytest.mark.realdata

# README: centres of the aligned CADs (axis-aligned box of the transformed CAD vertices), mesh frame
README_CAD_CENTRES = [
    ("otherfurniture", (3.26, 1.50, 0.25)),
    ("chair", (0.97, 2.17, 0.53)),
    ("chair", (0.62, 0.62, 0.59)),
    ("chair", (2.29, 0.56, 0.59)),
    ("chair", (3.03, 0.62, 0.59)),
    ("table", (1.45, 0.53, 0.42)),
    ("chair", (0.31, 2.02, 0.59)),
]


@pytest.fixture(scope="module")
def site(scene0470_site_dir) -> Site:
    return Site.load(scene0470_site_dir)


@pytest.fixture(scope="module")
def scan(scene0470_dir):
    return read_scan(scene0470_dir / "scene0470_00_vh_clean_2.ply")


def test_seven_cad_nodes_at_the_readme_centres(site):
    cad = [n for n in site.graph.nodes if n.source == "cad"]
    assert len(cad) == 7
    assert sorted(n.cls for n in cad) == ["chair"] * 5 + ["otherfurniture", "table"]
    for cls, centre in README_CAD_CENTRES:
        best = min((n for n in cad if n.cls == cls), key=lambda n: np.linalg.norm(n.centroid - centre))
        assert np.linalg.norm(best.centroid[:2] - centre[:2]) <= 0.05, (cls, centre, best.centroid)
        assert abs(best.centroid[2] - centre[2]) <= 0.10, (cls, centre, best.centroid)
        assert best.cad_id.split("/")[0] in {"03001627", "04379243", "02747177"}


def test_cad_points_sit_on_the_scanned_mesh(site, scan):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(scan.points), o3d.core.Tensor(scan.faces.astype(np.uint32)))
    for i, node in enumerate(site.graph.nodes):
        if node.source != "cad":
            continue
        mine = (site.map.instance == i) & (site.map.source == 1)
        assert mine.sum() == node.points > 5000  # dense: ~1 cm spacing on surfaces of 0.5–5 m²
        d = scene.compute_distance(o3d.core.Tensor(site.map.points[mine])).numpy()
        assert np.median(d) <= 0.07, (node.id, float(np.median(d)))
    # the build records the same check against the raw points (an upper bound of the surface distance)
    fits = {f["id"]: f for f in site.manifest["enhance"]["cads"]}
    assert sorted(fits) == sorted(n.id for n in site.graph.nodes if n.source == "cad")
    for f in fits.values():
        assert 0 < f["median_distance_to_scan_m"] <= 0.07 and f["raw_points_replaced"] > 100, f


def test_cad_colours_come_from_the_scan(site, scan):
    tree = cKDTree(scan.points)
    for i, node in enumerate(site.graph.nodes):
        if node.source != "cad":
            continue
        mine = (site.map.instance == i) & (site.map.source == 1)
        c = site.map.colors[mine].astype(float)
        assert c.std(axis=0).min() > 5, node.id  # not one flat colour
        _, j = tree.query(site.map.points[mine])
        diff = np.abs(c - scan.colors[j]).mean()
        assert diff < 30, (node.id, diff)  # close to the raw colours they replace (0–255 scale)


def test_unannotated_objects_become_cluster_nodes(site):
    clusters = [n for n in site.graph.nodes if n.source == "cluster"]
    classes = {n.cls for n in clusters}
    assert {"door", "window", "whiteboard"} <= classes
    assert not classes & {"wall", "floor", "ceiling", "unlabeled"}
    door = next(n for n in clusters if n.cls == "door")
    np.testing.assert_allclose(door.centroid, [3.26, 2.27, 0.68], atol=0.1)
    assert all(n.points >= 50 for n in clusters)
    # no cluster node is a leftover of a CAD object of the same class
    cad = [n for n in site.graph.nodes if n.source == "cad"]
    for n in clusters:
        for m in cad:
            if m.cls == n.cls:
                assert np.linalg.norm(n.centroid - m.centroid) > 0.3


def test_graph_edges_are_the_pairs_within_delta(site):
    nodes = site.graph.nodes
    c = site.graph.centroids()
    for a in range(len(nodes)):
        for b in range(a + 1, len(nodes)):
            d = float(np.linalg.norm(c[a] - c[b]))
            assert site.graph.graph.has_edge(nodes[a].id, nodes[b].id) == (d <= 1.5)
    assert site.graph.graph.number_of_edges() >= 10


def test_map_keeps_the_room_and_raw_scan(site, scan):
    assert len(site.raw.points) > 0.9 * len(scan.points)
    raw_kept = site.map.source == 0
    # raw walls and floor are all still in the enhanced map
    assert raw_kept.sum() > 0.6 * len(site.raw.points)
    assert len(site.map.points) > len(site.raw.points)
    assert site.manifest["inputs"]["scan2cad"]["id_scan"] == "scene0470_00"
    assert len(site.manifest["inputs"]["scan"]["sha256"]) == 64


def test_labels_only_build_makes_every_node_a_cluster(scene0470_dir):
    s = build_site(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                   labels_ply=scene0470_dir / "scene0470_00_vh_clean_2.labels.ply", site_id="labels-only")
    classes = [n.cls for n in s.graph.nodes]
    assert all(n.source == "cluster" for n in s.graph.nodes)
    # the five labelled chairs (seats and bases, which the scan splits, merged), the table and the bin
    assert classes.count("chair") == 5 and classes.count("table") == 1 and classes.count("otherfurniture") == 1
    chairs = np.array([n.centroid for n in s.graph.nodes if n.cls == "chair"])
    for cls, centre in README_CAD_CENTRES:
        if cls == "chair":
            assert np.min(np.linalg.norm(chairs[:, :2] - centre[:2], axis=1)) < 0.1
    assert np.all(s.map.source == 0) and len(s.map.points) == len(s.raw.points)


def test_missing_cad_file_names_it(scene0470_dir, tmp_path):
    cad_root = tmp_path / "shapenet"
    shutil.copytree(scene0470_dir / "shapenet", cad_root)
    gone = cad_root / "04379243" / "142060f848466cad97ef9a13efb5e3f7" / "models" / "model_normalized.obj"
    gone.unlink()
    with pytest.raises(InvalidFileError, match=r"142060f848466cad97ef9a13efb5e3f7/models/model_normalized\.obj"):
        build_site(scene0470_dir / "scene0470_00_vh_clean_2.ply", scan2cad_json=scene0470_dir / "scan2cad_annotation.json",
                   cad_root=cad_root)


def test_bad_annotation_json_names_it(scene0470_dir, tmp_path):
    bad = tmp_path / "annotation.json"
    text = (scene0470_dir / "scan2cad_annotation.json").read_text()
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(InvalidFileError, match="annotation.json: not valid JSON"):
        build_site(scene0470_dir / "scene0470_00_vh_clean_2.ply", scan2cad_json=bad, cad_root=scene0470_dir / "shapenet")
    assert json.loads(text)  # the real one is fine
