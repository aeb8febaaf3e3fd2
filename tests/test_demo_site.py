"""The bundled demo site: real input files, the CAD path of build_site, nodes, renderability, determinism."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadreg.io.cad import cad_model_path, load_cad_mesh
from cadreg.io.frames import RecordedFrames
from cadreg.io.ply import read_scan
from cadreg.io.scan2cad import read_scan2cad
from cadreg.render import LabelledMesh, MeshRenderer, render_frames
from cadreg.site.bundle import Site
from cadreg.site.demo import LAYOUT, PANELS, build_demo_site, furniture_mesh, write_demo_inputs


@pytest.fixture(scope="session")
def demo_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    build_demo_site(out)
    return out


def test_inputs_are_real_files(demo_dir: Path) -> None:
    inputs = demo_dir / "inputs"
    scan = read_scan(inputs / "demo_room_vh_clean.ply")
    assert scan.faces is not None and scan.labels is not None and len(scan.points) > 50_000
    lo, hi = scan.points.min(0), scan.points.max(0)
    np.testing.assert_allclose(lo, [0, 0, 0], atol=0.02)
    np.testing.assert_allclose(hi, [6.0, 5.0, 2.6], atol=0.02)
    assert {1, 2, 3, 5, 6, 7, 8, 9, 10, 22, 30, 39} <= set(np.unique(scan.labels).tolist())
    assert len(np.unique(scan.colors, axis=0)) > 1000  # textured, not flat colours
    (record,) = read_scan2cad(inputs / "scan2cad_demo.json")
    assert len(record.aligned_models) == sum(p.cad for p in LAYOUT)
    # Every aligned CAD, carried through Scan2CAD's chain, lands on the scan's points of its object.
    from scipy.spatial import cKDTree

    tree = cKDTree(scan.points)
    for model in record.aligned_models:
        mesh = load_cad_mesh(cad_model_path(inputs / "cad", model.catid_cad, model.id_cad))
        A = record.A_scan_cad(model)
        p = mesh.vertices @ A[:3, :3].T + A[:3, 3]
        d, idx = tree.query(p)
        assert np.median(d) < 0.02
        assert np.bincount(scan.labels[idx]).argmax() not in (1, 2, 22)  # on furniture, not on walls or floor


def test_demo_site_nodes_and_cad_path(demo_dir: Path) -> None:
    site = Site.load(demo_dir / "site")
    nodes = site.graph.nodes
    cad = [n for n in nodes if n.source == "cad"]
    cluster = [n for n in nodes if n.source == "cluster"]
    assert len(cad) == sum(p.cad for p in LAYOUT)
    assert sorted(n.cls for n in cluster) == sorted(["chair", "sofa", "door", "window", "whiteboard"])
    assert sum(n.cls == "chair" for n in nodes) == 6  # the row of three identical chairs among them
    # CAD nodes sit where the layout put the furniture.
    for p in (q for q in LAYOUT if q.cad):
        d = min(np.linalg.norm(np.asarray(n.centroid[:2]) - p.xy) for n in cad)
        assert d < 0.1
    assert np.count_nonzero(site.map.source == 1) > 10_000  # CAD points put into the map
    assert site.manifest["inputs"]["scan2cad"]["id_scan"] == "demo_room"
    assert len(site.manifest["inputs"]["cad_models"]) == len({p.model for p in LAYOUT if p.cad})
    assert len(PANELS) == 3


def test_demo_inputs_are_deterministic(demo_dir: Path, tmp_path: Path) -> None:
    again = write_demo_inputs(tmp_path)
    for name in ("demo_room_vh_clean.ply", "scan2cad_demo.json"):
        assert (demo_dir / "inputs" / name).read_bytes() == (tmp_path / name).read_bytes()
    assert again.cad_root.is_dir()


def test_demo_scan_renders(demo_dir: Path, tmp_path: Path) -> None:
    mesh = LabelledMesh.from_ply(demo_dir / "inputs" / "demo_room_vh_clean.ply")
    assert abs(mesh.floor_height_m()) < 0.01
    rendered = render_frames(mesh, tmp_path / "f", 4, seed=1)
    frames = RecordedFrames.open(tmp_path / "f")
    assert len(frames) == 4 and all(r.visible_objects >= 1 for r in rendered)
    frame, T = frames.load(0)
    # Depth back-projected at the pose stays inside the room.
    z = frame.depth.astype(float) / 1000.0
    v, u = np.nonzero(z > 0)
    K = frame.depth_intrinsics
    p = np.stack([(u - K.cx) / K.fx * z[v, u], (v - K.cy) / K.fy * z[v, u], z[v, u]], 1) @ T[:3, :3].T + T[:3, 3]
    assert np.all(p > -0.1) and np.all(p < [6.1, 5.1, 2.7])
    assert MeshRenderer(mesh).distance_to_surface(T[None, :3, 3])[0] >= 0.3


def test_furniture_models_differ() -> None:
    a, b = furniture_mesh("chair_a"), furniture_mesh("chair_b")
    assert not np.allclose(a.extents, b.extents)
    with pytest.raises(ValueError):
        furniture_mesh("piano")


def test_cli_render_from_site(demo_dir: Path, tmp_path: Path, capsys) -> None:
    from cadreg.cli.main import main

    assert main(["render", "--site", str(demo_dir / "site"), "--out", str(tmp_path / "f"), "--n", "2", "--seed", "3",
                 "--min-visible-objects", "2"]) == 0
    assert "demo_room_vh_clean.ply" in capsys.readouterr().out
    frames = RecordedFrames.open(tmp_path / "f")
    assert len(frames) == 2 and frames.has_labels()
    labels = frames.load(frames.indices[0])[0].labels
    assert len(set(np.unique(labels).tolist()) - {0, 1, 2, 22}) >= 1
    # A bundle whose scan mesh is not at hand renders a Poisson mesh of its points instead.
    import shutil

    fake = tmp_path / "nomesh"
    shutil.copytree(demo_dir / "site", fake)
    (fake / "site.json").write_text((fake / "site.json").read_text().replace("demo_room_vh_clean.ply", "gone.ply"))
    assert main(["render", "--site", str(fake), "--out", str(tmp_path / "g"), "--n", "2", "--seed", "4",
                 "--no-noise"]) == 0
    assert "poisson mesh" in capsys.readouterr().out
    g = RecordedFrames.open(tmp_path / "g")
    frame, T = g.load(g.indices[0])
    assert frame.labels is not None and len(set(np.unique(frame.labels).tolist()) - {0}) >= 1
    # Its depth lies near the real scan's surface at the same pose.
    real = MeshRenderer(LabelledMesh.from_ply(demo_dir / "inputs" / "demo_room_vh_clean.ply"))
    z = frame.depth.astype(float) / 1000.0
    v, u = np.nonzero(z > 0)
    K = frame.depth_intrinsics
    p = np.stack([(u - K.cx) / K.fx * z[v, u], (v - K.cy) / K.fy * z[v, u], z[v, u]], 1) @ T[:3, :3].T + T[:3, 3]
    assert np.median(real.distance_to_surface(p)) < 0.02


def test_a_weak_graph_pose_that_renders_as_measured_skips_the_fallbacks(demo_dir: Path, tmp_path: Path) -> None:
    """The demo's frame 6 (`cadreg demo`, seed 0): the graph's best coarse pose is 1 cm off but scores 0.79 (the
    map's CAD chairs are not the rendered ones), under min_graph_fitness; its depth agrees with the map in 96 % of
    the view, so the label-free search is not run, and the answer is the same as with it."""
    from dataclasses import replace

    from cadreg.config import FallbackConfig, LocalizeConfig
    from cadreg.geometry import pose_errors
    from cadreg.localize import Localizer
    from cadreg.result import Status
    from cadreg.site.demo import SCAN_NAME

    site = Site.load(demo_dir / "site")
    render_frames(LabelledMesh.from_ply(demo_dir / "inputs" / SCAN_NAME), tmp_path / "f", 7, seed=0)
    frame, T_true = RecordedFrames.open(tmp_path / "f").load(6)
    skipped = Localizer.from_site(site).localize(frame)
    always = LocalizeConfig(fallback=FallbackConfig(skip_agreement=1.01))
    searched = Localizer.from_site(site, always).localize(frame)
    assert skipped.status == searched.status == Status.OK
    assert any(n.startswith("fallbacks not run") for n in skipped.diagnostics.notes)
    assert "fallback" not in skipped.diagnostics.stage_ms and "fallback" in searched.diagnostics.stage_ms
    assert pose_errors(skipped.T_map_camera, T_true)[0] < 0.05
    assert np.allclose(skipped.T_map_camera, searched.T_map_camera, atol=1e-6)
    # without labels there is no graph pose to agree: the label-free search runs
    bare = Localizer.from_site(site).localize(replace(frame, labels=None))
    assert "fallback" in bare.diagnostics.stage_ms
