"""Automatic CAD alignment (issue 13) on the real scene0470 scan, labels and ShapeNet library, and on synthetic
swivel chairs with a known pose.

The full auto-CAD site is built once for the module (~30–40 s on 2 cores); the other builds use libraries of one
synset (symlinks into ../shared/data, made in tmp) so that only one instance gets fitted.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from cadreg.cli.main import main
from cadreg.config import AutoCadConfig
from cadreg.errors import InvalidFileError
from cadreg.io.scan2cad import read_scan2cad, write_scan2cad
from cadreg.site.autocad import (R_UPRIGHT_CAD, SYM_2, SYM_INF, SYM_NONE, Fit, InstanceResult, ModelFit,
                                  _cover_footprint, _Rz, fit_model, load_library, model_data, prefer_common_models,
                                  prepare_model)
from cadreg.site.autocad_check import compare_alignments
from cadreg.site.build import auto_cad_document, build_site
from cadreg.site.bundle import Site
from cadreg.site.show import auto_cad_ids, render_site_png

pytestmark = pytest.mark.realdata

SCAN = "scene0470_00_vh_clean_2.ply"
LABELS = "scene0470_00_vh_clean_2.labels.ply"
BIN, CHAIR, TABLE = "02747177", "03001627", "04379243"


def _library(tmp: Path, src: Path, synsets: list[str]) -> Path:
    """A CAD library in tmp made of symlinks to synset folders of the real one (nothing copied)."""
    tmp.mkdir(parents=True, exist_ok=True)
    for s in synsets:
        (tmp / s).symlink_to(src / s, target_is_directory=True)
    return tmp


def _cad_nodes(site: Site) -> list:
    return [n for n in site.graph.nodes if n.source == "cad"]


@pytest.fixture(scope="module")
def auto_site(scene0470_dir: Path, tmp_path_factory) -> tuple[Site, Path]:
    site = build_site(scene0470_dir / SCAN, labels_ply=scene0470_dir / LABELS, cad_root=scene0470_dir / "shapenet",
                      site_id="scene0470", auto_cad=AutoCadConfig())
    out = tmp_path_factory.mktemp("autocad") / "scene0470"
    site.save(out)
    doc_path = out / "auto_cad.scan2cad.json"
    write_scan2cad(doc_path, auto_cad_document(site))
    return site, doc_path


def test_library_symmetry_from_geometry(scene0470_dir: Path) -> None:
    lib = load_library(scene0470_dir / "shapenet")
    sym = {m.cad_id.split("/")[0]: m.sym for m in lib.models}
    # Scan2CAD's annotators gave the bin ROTATE_UP_2, the round table ROTATE_UP_INF, chairs NONE
    assert sym == {BIN: SYM_2, CHAIR: SYM_NONE, TABLE: SYM_INF}
    assert sorted(m.cls for m in lib.models) == ["chair"] * 4 + ["otherfurniture", "table"]


def test_auto_aligned_objects_against_the_annotation(auto_site, scene0470_dir: Path) -> None:
    site, doc_path = auto_site
    annotated = read_scan2cad(scene0470_dir / "scan2cad_annotation.json")[0]
    auto = read_scan2cad(doc_path)[0]
    rows = compare_alignments(annotated, auto)
    by_cls = {}
    for r in rows:
        by_cls.setdefault(r.cls, []).append(r)
    # every annotated object got an automatic CAD of its own class nearby, upright and at the right height
    assert all(r.auto_cad_id is not None and r.auto_cls == r.cls for r in rows), rows
    assert all(r.height_m <= 0.10 and r.horizontal_m <= 0.07 and r.yaw_deg <= 15.0 for r in rows), rows
    # the table and the bin (one library model each) within the tolerances, and the figure: at
    # least 6 of the 7 (the five chairs fitted with four candidate models; the table is in the README)
    assert by_cls["table"][0].ok and by_cls["otherfurniture"][0].ok, rows
    assert sum(r.ok for r in rows) >= 6, rows
    assert all(n.cls in {"chair", "table", "otherfurniture"} for n in _cad_nodes(site))
    assert sorted(n.cls for n in site.graph.nodes if n.source == "cluster") == ["bag", "door", "whiteboard",
                                                                                "window"]


def test_provenance_and_fit_in_manifest_info_and_show(auto_site, tmp_path: Path, capsys) -> None:
    site, doc_path = auto_site
    loaded = Site.load(doc_path.parent)
    cads = loaded.manifest["enhance"]["cads"]
    assert cads and all(f["origin"] == "auto" and 0 < f["auto_fit"]["median_scan_to_cad_m"] <= 0.04 for f in cads)
    assert auto_cad_ids(loaded) == {n.id for n in _cad_nodes(loaded)}
    assert main(["site", "info", str(doc_path.parent), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    cad_info = [n for n in info["nodes"] if n["source"] == "cad"]
    assert cad_info and all(n["origin"] == "auto" and "scan_coverage" in n["fit"] for n in cad_info)
    assert main(["site", "info", str(doc_path.parent)]) == 0
    text = capsys.readouterr().out
    assert " auto " in text and "coverage scan / CAD" in text
    assert render_site_png(loaded)[:8] == b"\x89PNG\r\n\x1a\n"


def test_scan2cad_round_trip_gives_the_same_cad_nodes(auto_site, scene0470_dir: Path) -> None:
    site, doc_path = auto_site
    records = json.loads(doc_path.read_text())
    assert records[0]["trs"]["rotation"] == [1.0, 0.0, 0.0, 0.0]
    for m in records[0]["aligned_models"]:
        assert {"trs", "catid_cad", "id_cad", "bbox", "center", "sym"} <= set(m)
    again = build_site(scene0470_dir / SCAN, labels_ply=scene0470_dir / LABELS, scan2cad_json=doc_path,
                       cad_root=scene0470_dir / "shapenet", site_id="scene0470")
    a, b = _cad_nodes(site), _cad_nodes(again)
    assert [(n.cls, n.cad_id) for n in a] == [(n.cls, n.cad_id) for n in b]
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.centroid, y.centroid, atol=1e-6)
        np.testing.assert_allclose(x.box_extent, y.box_extent, atol=1e-6)
        np.testing.assert_allclose(x.box_center, y.box_center, atol=1e-6)
    assert [n.cls for n in site.graph.nodes] == [n.cls for n in again.graph.nodes]
    # the file stores the very TRS each CAD was placed with: the same bundle, bit for bit
    assert again.version == site.version


def test_annotated_objects_kept_the_rest_auto_aligned(scene0470_dir: Path, tmp_path: Path) -> None:
    records = json.loads((scene0470_dir / "scan2cad_annotation.json").read_text())
    records[0]["aligned_models"] = [m for m in records[0]["aligned_models"] if m["catid_cad"] != BIN]
    partial = tmp_path / "without_bin.json"
    partial.write_text(json.dumps(records))
    kw = dict(labels_ply=scene0470_dir / LABELS, cad_root=scene0470_dir / "shapenet", site_id="s")
    annotated = build_site(scene0470_dir / SCAN, scan2cad_json=partial, **kw)
    both = build_site(scene0470_dir / SCAN, scan2cad_json=partial, auto_cad=AutoCadConfig(), **kw)
    origins = {f["id"]: f["origin"] for f in both.manifest["enhance"]["cads"]}
    cad_a, cad_b = _cad_nodes(annotated), _cad_nodes(both)
    # the 6 annotated ones first and exactly as given; the bin, which no annotation covers, auto-aligned
    assert len(cad_a) == 6 and len(cad_b) == 7
    for x, y in zip(cad_a, cad_b):
        assert (x.id, x.cad_id) == (y.id, y.cad_id) and origins[y.id] == "annotation"
        np.testing.assert_allclose(x.centroid, y.centroid, atol=1e-9)
    extra = cad_b[6]
    assert extra.cls == "otherfurniture" and origins[extra.id] == "auto"
    assert np.linalg.norm(extra.centroid[:2] - [3.26, 1.50]) < 0.05
    report = both.manifest["enhance"]["auto_cad"]
    assert report["annotated_instances"] == 6 and report["aligned"] == 1


def test_class_without_a_model_stays_a_cluster_node(scene0470_dir: Path, tmp_path: Path, capsys) -> None:
    lib = _library(tmp_path / "lib", scene0470_dir / "shapenet", [BIN])
    out = tmp_path / "site"
    rc = main(["site", "build", "--scan", str(scene0470_dir / SCAN), "--labels", str(scene0470_dir / LABELS),
               "--cad-root", str(lib), "--auto-cad", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "note: the CAD library has no model of these classes" in text and "chair (5)" in text
    assert "table (1)" in text
    site = Site.load(out)
    assert [n.cls for n in _cad_nodes(site)] == ["otherfurniture"]
    clusters = sorted(n.cls for n in site.graph.nodes if n.source == "cluster")
    assert clusters.count("chair") == 5 and "table" in clusters
    assert len(read_scan2cad(out / "auto_cad.scan2cad.json")[0].aligned_models) == 1


@pytest.mark.parametrize("make", ["missing", "empty"])
def test_missing_or_empty_library_fails_naming_it(scene0470_dir: Path, tmp_path: Path, capsys, make: str) -> None:
    lib = tmp_path / "library"
    if make == "empty":
        (lib / CHAIR).mkdir(parents=True)
    with pytest.raises(InvalidFileError, match="CAD library") as err:
        build_site(scene0470_dir / SCAN, labels_ply=scene0470_dir / LABELS, cad_root=lib, auto_cad=AutoCadConfig())
    assert err.value.path == str(lib)
    rc = main(["site", "build", "--scan", str(scene0470_dir / SCAN), "--labels", str(scene0470_dir / LABELS),
               "--cad-root", str(lib), "--auto-cad", "--out", str(tmp_path / "site")])
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert rc == 2 and len(lines) == 1 and str(lib) in lines[0]
    assert not (tmp_path / "site").exists()


def test_unreadable_model_is_skipped_with_a_warning(scene0470_dir: Path, tmp_path: Path, caplog) -> None:
    lib = _library(tmp_path / "lib", scene0470_dir / "shapenet", [BIN, TABLE])
    bad = lib / CHAIR / "0000garbage" / "models" / "model_normalized.obj"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"\x00\x01 this is no mesh\nf 1 2 3\n")
    with caplog.at_level(logging.WARNING, logger="cadreg.autocad"):
        library = load_library(lib)
    assert sorted(m.cad_id.split("/")[0] for m in library.models) == [BIN, TABLE]
    assert any(str(bad) in r.getMessage() for r in caplog.records)
    assert any(str(bad) in n for n in library.notes)


def test_auto_cad_needs_labels_and_a_library(scene0470_dir: Path, tmp_path: Path, capsys) -> None:
    with pytest.raises(ValueError, match="labels"):
        build_site(scene0470_dir / SCAN, cad_root=scene0470_dir / "shapenet", auto_cad=AutoCadConfig())
    with pytest.raises(SystemExit):
        main(["site", "build", "--scan", str(scene0470_dir / SCAN), "--auto-cad", "--out", str(tmp_path / "x")])
    assert "--auto-cad needs --cad-root" in capsys.readouterr().err


def test_fused_site_with_auto_cad(scene0470_dir: Path, tmp_path: Path, capsys) -> None:
    """`site fuse --auto-cad` on labelled frames rendered around the bin: the bin becomes an auto CAD node."""
    from cadreg.config import RenderConfig
    from cadreg.geometry import make_T
    from cadreg.render import LabelledMesh, render_frames

    mesh = LabelledMesh.from_ply(scene0470_dir / SCAN, scene0470_dir / LABELS)
    target = np.array([3.26, 1.50, 0.25])
    poses = []
    for k, yaw in enumerate(np.radians([150, 165, 180, 195, 210, 225, 240, 255])):
        eye = target + np.array([1.3 * np.cos(yaw), 1.3 * np.sin(yaw), 1.1 + 0.05 * (k % 3)])
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        poses.append(make_T(np.stack([x, np.cross(z, x), z], axis=1), eye))
    frames = tmp_path / "frames"
    render_frames(mesh, frames, len(poses), seed=1, noise=None, poses=poses,
                  config=RenderConfig(color_width=320, color_height=240))
    lib = _library(tmp_path / "lib", scene0470_dir / "shapenet", [BIN])
    out = tmp_path / "fused"
    assert main(["site", "fuse", "--frames", str(frames), "--out", str(out), "--auto-cad", "--cad-root",
                 str(lib)]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["auto_cad"]["cad_nodes"] == 1
    site = Site.load(out)
    (node,) = _cad_nodes(site)
    assert node.cls == "otherfurniture" and auto_cad_ids(site) == {node.id}
    assert np.linalg.norm(node.centroid[:2] - target[:2]) < 0.06
    assert (out / "auto_cad.scan2cad.json").is_file()


# --- synthetic swivel chairs (upright coordinates: z up, the seat's back edge towards -y) ------------------------


def _swivel_chair(base_deg: float, leg_m: float = 0.33, seat_depth_m: float = 0.45):
    """A seat, a back, a column and a five-legged star base turned by base_deg (upright coordinates, metres)."""
    import trimesh

    def box(extent, center, yaw_deg=0.0):
        T = trimesh.transformations.rotation_matrix(np.radians(yaw_deg), [0, 0, 1]) @ \
            trimesh.transformations.translation_matrix(center)
        return trimesh.creation.box(extent, T)

    parts = [box([0.45, seat_depth_m, 0.05], [0, 0, 0.445]),
             box([0.45, 0.04, 0.45], [0, -seat_depth_m / 2 + 0.02, 0.695]),
             box([0.05, 0.05, 0.37], [0, 0, 0.235])]
    parts += [box([leg_m, 0.05, 0.04], [leg_m / 2, 0, 0.03], base_deg + 72.0 * k) for k in range(5)]
    return trimesh.util.concatenate(parts)


def _model(mesh_up):
    """ModelData of an upright mesh, stored the ShapeNet way (y up) as a library model would be."""
    cad = mesh_up.copy()
    T = np.eye(4)
    T[:3, :3] = R_UPRIGHT_CAD.T
    cad.apply_transform(T)
    return model_data(prepare_model(cad, synset=CHAIR, model_id="synthetic", path="-"))


def _scan(mesh_up, yaw_deg: float, t: np.ndarray, n: int = 4000) -> np.ndarray:
    import trimesh

    pts = np.asarray(trimesh.sample.sample_surface(mesh_up, n, seed=3)[0])
    return pts @ _Rz(np.radians(yaw_deg)).T + t


def _yaw_error_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_fit_ignores_a_base_that_differs_from_the_model() -> None:
    """A library chair whose star base is half as wide again as the scanned one's, turned 36° on its swivel: fitted
    on all points, the base drags the yaw and shrinks the seat; fitted above the base, seat and back decide."""
    model = _model(_swivel_chair(0.0, leg_m=0.42))
    points = _scan(_swivel_chair(36.0, leg_m=0.28), 30.0, np.array([1.0, 2.0, 0.0]))
    c = AutoCadConfig(cover_footprint=False)
    fit = fit_model(points, 0.0, model, c)
    assert _yaw_error_deg(fit.yaw_deg, 30.0) < 10.0, fit.yaw_deg
    seat_m = 0.45 * fit.scale_up[:2]
    assert np.all(np.abs(seat_m - 0.45) < 0.045), seat_m
    assert np.linalg.norm(fit.A_map_cad[:2, 3] - [1.0, 2.0]) < 0.05
    # the scene is one where the base matters: with it in the fit, the yaw or the seat is far off
    whole = fit_model(points, 0.0, model, c.model_copy(update={"base_fraction": 0.0}))
    assert _yaw_error_deg(whole.yaw_deg, 30.0) > 15.0 or np.any(np.abs(0.45 * whole.scale_up[:2] - 0.45) > 0.07)


def test_box_covers_the_explained_points_not_label_bleed() -> None:
    """The box grows over the object's points that the CAD explains (star legs 4 cm longer than the model's), not
    over a strip of floor the labels bled onto 20 cm behind the chair (10 % of the instance's points)."""
    model = _model(_swivel_chair(0.0))
    chair = _scan(_swivel_chair(0.0, leg_m=0.37), 0.0, np.zeros(3))
    rng = np.random.default_rng(0)
    bleed = np.column_stack([rng.uniform(-0.2, 0.2, 400), rng.uniform(-0.55, -0.5, 400), np.full(400, 0.005)])
    x = np.zeros(7)  # the model where it was made: yaw 0, scale 1, its bottom centre where the mesh has it
    x[1:3] = model.bottom_up[:2]
    grown = _cover_footprint(x, np.vstack([chair, bleed]), model, AutoCadConfig().cover_explained_m)
    half = model.extent_up[:2] * np.exp(grown[4:6]) / 2.0
    lo, hi = grown[1:3] - half, grown[1:3] + half
    assert model.bottom_up[0] + model.extent_up[0] / 2.0 < 0.34   # the model's leg along +x ends at 0.33
    assert hi[0] >= 0.345, hi                               # grown towards the scan's, at 0.37 (a few points)
    assert lo[1] > -0.40, lo                                # the bleed is not (the legs reach -0.35)


def _instance(scores: dict[str, float], i: int = 0) -> InstanceResult:
    fits = [ModelFit(cad, np.eye(4), np.zeros((0, 3)), 0.0, np.ones(3), SYM_NONE, s, Fit(0.01, 0.9, 0.01, 0.9, s))
            for cad, s in sorted(scores.items(), key=lambda kv: kv[1])]
    return InstanceResult(i, "chair", 1000, np.zeros(3), fits, fits[0])


def test_instances_of_a_class_share_the_common_model_within_the_margin() -> None:
    c = AutoCadConfig()
    results = [_instance({"A": 0.060, "B": 0.066}), _instance({"A": 0.050, "B": 0.070}),
               _instance({"A": 0.063, "B": 0.060}),   # B better by 5 %: noise, takes the common A
               _instance({"A": 0.080, "B": 0.070})]   # B better by 14 %: another chair, keeps B
    prefer_common_models(results, [c] * len(results))
    assert [r.accepted.cad_id for r in results] == ["A", "A", "A", "B"]
    assert results[2].to_dict()["chosen"] == "A" and results[2].to_dict()["best"]["cad_id"] == "B"
    # margin 0: each instance its own best; a lone instance of a class is never changed
    results = [_instance({"A": 0.063, "B": 0.060}), _instance({"A": 0.050, "B": 0.070})]
    prefer_common_models(results, [c.model_copy(update={"same_model_margin": 0.0})] * 2)
    assert [r.accepted.cad_id for r in results] == ["B", "A"]
    lone = [_instance({"A": 0.063, "B": 0.060})]
    prefer_common_models(lone, [c])
    assert lone[0].accepted.cad_id == "B"
    # the common model must pass at the instance to be taken
    results = [_instance({"A": 0.050, "B": 0.070}), _instance({"A": 0.061, "B": 0.060})]
    results[1].fits[1].fit = Fit(0.2, 0.1, 0.2, 0.1, 0.061)
    prefer_common_models(results, [c] * 2)
    assert results[1].accepted.cad_id == "B"
