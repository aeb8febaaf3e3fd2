"""A new user's own scan, as it comes: in millimetres, with its winding reversed, y-up, labelled with ids of another
set, or with a Scan2CAD file of another frame. Each is refused with an error that says what to do, mended, or
built with a warning, where each built silently before (a site that never placed a frame, or `ok` answers 1 m off)
or ran the machine out of memory. Real scene0470 mesh, real `site build`."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from cadreg.cli.main import main
from cadreg.errors import InvalidFileError
from cadreg.io.ply import read_scan, scan_ply_bytes
from cadreg.site.build import build_site

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def scan(scene0470_dir: Path):
    """scene0470's mesh and labels as read (no normals: they come from the faces)."""
    return read_scan(scene0470_dir / "scene0470_00_vh_clean_2.ply", scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")


def _write(path: Path, points: np.ndarray, scan, *, faces: np.ndarray | None = None,
           labels: np.ndarray | None = None) -> Path:
    path.write_bytes(scan_ply_bytes(points.astype(np.float32), scan.colors, scan.faces if faces is None else faces,
                                    (scan.labels if labels is None else labels).astype(np.uint16)))
    return path


def test_a_scan_in_millimetres_is_refused_at_once_saying_so(scan, tmp_path: Path, capsys) -> None:
    mm = _write(tmp_path / "mm.ply", scan.points * 1000.0, scan)
    assert main(["site", "build", "--scan", str(mm), "--out", str(tmp_path / "site")]) == 2
    err = capsys.readouterr().err
    assert "mm.ply" in err and "3,492" in err and "millimetres" in err
    assert not (tmp_path / "site").exists()


def test_a_mesh_with_its_winding_reversed_builds_the_site_its_true_winding_builds(scan, tmp_path: Path,
                                                                                  caplog) -> None:
    """Normals from reversed faces face out of the room, and the localizer takes every surface seen from behind as
    no evidence: such a site placed no frame. Its normals are turned, with a warning: the same site."""
    right = build_site(_write(tmp_path / "right.ply", scan.points, scan))
    with caplog.at_level(logging.WARNING, logger="cadreg.site"):
        reversed_ = build_site(_write(tmp_path / "reversed.ply", scan.points, scan, faces=scan.faces[:, ::-1]))
    assert any("winding is reversed" in r.getMessage() for r in caplog.records)
    assert reversed_.version == right.version
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cadreg.site"):
        build_site(tmp_path / "right.ply")
    assert not caplog.records  # a scan as it should be is built without a word


def test_a_y_up_scan_is_warned_of_and_a_scan2cad_file_of_another_frame_refused(scan, scene0470_dir: Path,
                                                                               tmp_path: Path, caplog) -> None:
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z-up -> y-up
    yup = _write(tmp_path / "yup.ply", scan.points @ turn.T, scan)
    with caplog.at_level(logging.WARNING, logger="cadreg.site"):
        build_site(yup)
    assert any("not +z" in r.getMessage() and "(0.00, 1.00, 0.00)" in r.getMessage() for r in caplog.records)
    annotation = scene0470_dir / "scan2cad_annotation.json"
    with pytest.raises(InvalidFileError, match=r"scan2cad_annotation\.json.*7 of the 7 CAD models.*another frame"):
        build_site(yup, scan2cad_json=annotation, cad_root=scene0470_dir / "shapenet")
    # the same file on the scan it annotates passes (its CADs lie 2-5 cm from it)
    assert len(build_site(_write(tmp_path / "z.ply", scan.points, scan), scan2cad_json=annotation,
                          cad_root=scene0470_dir / "shapenet").graph.nodes) == 11


def test_labels_of_another_set_are_warned_of(scan, tmp_path: Path, caplog) -> None:
    raw_ids = _write(tmp_path / "raw.ply", scan.points, scan, labels=(scan.labels + 1000).astype(np.uint16))
    with caplog.at_level(logging.WARNING, logger="cadreg.site"):
        site = build_site(raw_ids)
    assert not site.graph.nodes
    assert any("is an NYU40 id" in r.getMessage() for r in caplog.records)
