"""Scan2CAD annotations and CAD library: the transform chain on the real alignment, and malformed inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from cadreg.errors import InvalidFileError
from cadreg.geometry import quat_wxyz_to_R
from cadreg.io.cad import cad_model_path, load_cad_mesh
from cadreg.io.scan2cad import TRS, read_scan2cad, select_scan

# README of the data: centre of the axis-aligned box of each transformed CAD, mesh frame, in file order
README_CENTRES = {
    "02747177": [(3.26, 1.50, 0.25)],
    "03001627": [(0.97, 2.17, 0.53), (0.62, 0.62, 0.59), (2.29, 0.56, 0.59), (3.03, 0.62, 0.59), (0.31, 2.02, 0.59)],
    "04379243": [(1.45, 0.53, 0.42)],
}


def test_trs_matrix_is_T_R_S():
    trs = TRS(np.array([1.0, 2.0, 3.0]), np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)]), np.array([2.0, 3.0, 4.0]))
    M = trs.matrix()
    p = np.array([0.5, -1.0, 2.0])
    expected = quat_wxyz_to_R(trs.rotation_wxyz) @ (np.array([2.0, 3.0, 4.0]) * p) + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(M[:3, :3] @ p + M[:3, 3], expected)


def test_real_alignment_lands_cads_on_the_readme_centres(scene0470_dir):
    scans = read_scan2cad(scene0470_dir / "scan2cad_annotation.json")
    assert len(scans) == 1
    rec = select_scan(scans, "scene0470_00_vh_clean_2.ply")
    assert rec.id_scan == "scene0470_00" and len(rec.aligned_models) == 7
    todo = {k: list(v) for k, v in README_CENTRES.items()}
    for m in rec.aligned_models:
        mesh = load_cad_mesh(cad_model_path(scene0470_dir / "shapenet", m.catid_cad, m.id_cad))
        A = rec.A_scan_cad(m)
        v = mesh.vertices @ A[:3, :3].T + A[:3, 3]
        centre = (v.min(axis=0) + v.max(axis=0)) / 2
        expected = np.array(todo[m.catid_cad].pop(0))
        np.testing.assert_allclose(centre, expected, atol=0.006)
    assert all(not v for v in todo.values())


def _record(id_scan: str, **model_overrides) -> dict:
    model = {"catid_cad": "03001627", "id_cad": "abc",
             "trs": {"translation": [0, 0, 0], "rotation": [1, 0, 0, 0], "scale": [1, 1, 1]},
             "bbox": [1, 1, 1], "center": [0, 0, 0], "sym": "__SYM_NONE"}
    model.update(model_overrides)
    return {"id_scan": id_scan, "trs": {"translation": [0, 0, 0], "rotation": [1, 0, 0, 0], "scale": [1, 1, 1]},
            "aligned_models": [model]}


def test_select_scan_by_file_name(tmp_path):
    p = tmp_path / "a.json"
    p.write_text(json.dumps([_record("scene0001_00"), _record("scene0002_00")]))
    scans = read_scan2cad(p)
    assert select_scan(scans, "scene0002_00_vh_clean_2.ply").id_scan == "scene0002_00"
    with pytest.raises(InvalidFileError, match="0 records match"):
        select_scan(scans, "scene0003_00.ply", p)


@pytest.mark.parametrize(
    "content, reason",
    [
        ("{not json", "not valid JSON"),
        ("[]", "non-empty list"),
        (json.dumps([{"id_scan": "x"}]), "needs 'trs'"),
        (json.dumps([_record("s", trs={"translation": [0, 0], "rotation": [1, 0, 0, 0], "scale": [1, 1, 1]})]),
         "translation must be 3 numbers"),
        (json.dumps([_record("s", trs={"translation": [0, 0, 0], "rotation": [1, 0, 0, 0], "scale": [1, 0, 1]})]),
         "scale must be positive"),
        (json.dumps([_record("s", trs={"translation": [0, 0, 0], "rotation": [0, 0, 0, 0], "scale": [1, 1, 1]})]),
         "zero quaternion"),
        (json.dumps([{"trs": {}, "aligned_models": [{"id_cad": "a"}]}]), "needs catid_cad"),
    ],
)
def test_malformed_annotation_names_the_file(tmp_path, content, reason):
    p = tmp_path / "bad_annotation.json"
    p.write_text(content)
    with pytest.raises(InvalidFileError, match=f"bad_annotation.json.*{reason}"):
        read_scan2cad(p)


def test_missing_and_broken_cad_files(tmp_path):
    with pytest.raises(InvalidFileError, match=r"03001627/nothere/models/model_normalized\.obj.*not found"):
        cad_model_path(tmp_path, "03001627", "nothere")
    broken = tmp_path / "03001627" / "broken" / "models" / "model_normalized.obj"
    broken.parent.mkdir(parents=True)
    broken.write_text("this is not an obj file\n")
    with pytest.raises(InvalidFileError, match="model_normalized.obj"):
        load_cad_mesh(cad_model_path(tmp_path, "03001627", "broken"))


def test_other_trimesh_formats_are_found(tmp_path):
    (tmp_path / "04379243").mkdir()
    trimesh.creation.box(extents=(1, 2, 3)).export(tmp_path / "04379243" / "tbl.ply")
    mesh = load_cad_mesh(cad_model_path(tmp_path, "04379243", "tbl"))
    np.testing.assert_allclose(mesh.extents, [1, 2, 3])
