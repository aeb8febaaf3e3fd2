"""Shared fixtures: paths to the real data in ../shared/data and small helpers."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Keep the numeric libraries to one thread each: tests run beside other work on a 2-core machine.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
SCENE0470 = SHARED_DATA / "scannet-scene0470_00"
REDKITCHEN = SHARED_DATA / "7scenes-redkitchen" / "frames"
THREEDMATCH = SHARED_DATA / "3dmatch-sample" / "3dmatch" / "seq-01"


def scene0470_mesh(scene0470_dir: Path):
    """The real scene0470 mesh with its NYU40 labels, as the renderer takes it (`render_frames`)."""
    from cadreg.render.mesh import LabelledMesh

    return LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")


@pytest.fixture(scope="session")
def scene0470_dir() -> Path:
    assert SCENE0470.is_dir(), f"real data missing: {SCENE0470}"
    return SCENE0470


@pytest.fixture(scope="session")
def redkitchen_dir() -> Path:
    assert REDKITCHEN.is_dir(), f"real data missing: {REDKITCHEN}"
    return REDKITCHEN


@pytest.fixture(scope="session")
def threedmatch_dir() -> Path:
    assert THREEDMATCH.is_dir(), f"real data missing: {THREEDMATCH}"
    return THREEDMATCH


@pytest.fixture(scope="session")
def scene0470_site_dir(scene0470_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The scene0470 site bundle (scan + NYU40 labels + the 7 Scan2CAD CADs), built once per test session (~2 s)."""
    from cadreg.site.build import build_site

    out = tmp_path_factory.mktemp("sites") / "scene0470"
    site = build_site(
        scene0470_dir / "scene0470_00_vh_clean_2.ply",
        labels_ply=scene0470_dir / "scene0470_00_vh_clean_2.labels.ply",
        scan2cad_json=scene0470_dir / "scan2cad_annotation.json",
        cad_root=scene0470_dir / "shapenet",
        site_id="scene0470",
    )
    site.save(out)
    return out


@pytest.fixture(scope="session")
def twin_rooms_dir(scene0470_site_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two copies of the scene0470 room composed side by side, the second missing a chair and the bin
    (tests/tracking_rooms.py), built once per test session."""
    from tracking_rooms import twin_site

    return twin_site(scene0470_site_dir, tmp_path_factory.mktemp("twin-rooms"))


@pytest.fixture(scope="session")
def twin_shared_view(scene0470_dir: Path, tmp_path_factory: pytest.TempPathFactory):
    """(frame, T_map_camera in room "a") of a view both twin rooms show."""
    from tracking_rooms import shared_view

    return shared_view(scene0470_dir, tmp_path_factory.mktemp("twin-shared-view"))
