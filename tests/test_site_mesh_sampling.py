"""A scan mesh decimated to large triangles gets points sampled on them, so that its map is as dense as a scan's;
a dense mesh (ScanNet's) is taken as it is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cadreg.io.ply import ScanPoints, read_scan, write_ply
from cadreg.site.build import build_site, sample_large_triangles


def _square(side_m: float) -> ScanPoints:
    """Two triangles over a side_m square at z = 0: corner colours black, red, green, blue; labels 1, 2, 3, 4."""
    points = np.array([[0, 0, 0], [side_m, 0, 0], [side_m, side_m, 0], [0, side_m, 0]], dtype=np.float32)
    colors = np.array([[0, 0, 0], [255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    normals = np.tile(np.array([0, 0, 1], dtype=np.float32), (4, 1))
    return ScanPoints(points, colors, normals, np.array([1, 2, 3, 4]), np.array([[0, 1, 2], [0, 2, 3]]))


def test_large_triangles_get_points_with_their_colour_normal_and_nearest_label() -> None:
    scan = _square(1.0)
    out = sample_large_triangles(scan, min_edge_m=0.1, spacing_m=0.02)
    added = out.points[4:]
    assert len(out.points) == len(out.colors) == len(out.normals) == len(out.labels)
    assert abs(len(added) - 1.0 / 0.02 ** 2) <= 2  # about one a spacing² of the area
    assert np.all(np.abs(added[:, 2]) < 1e-6) and added[:, :2].min() >= 0 and added[:, :2].max() <= 1.0 + 1e-6
    assert np.allclose(out.normals[4:], [0, 0, 1], atol=1e-6)
    # near a corner: that corner's label and (nearly) its colour
    near = np.linalg.norm(added[:, :2] - [1.0, 0.0], axis=1) < 0.05
    assert near.any() and np.all(out.labels[4:][near] == 2) and np.all(out.colors[4:][near][:, 0] > 200)
    # no gap wider than a few spacings is left on the square
    gaps, _ = cKDTree(added[:, :2]).query(np.random.default_rng(0).uniform(0, 1, (2000, 2)))
    assert gaps.max() < 0.06


def test_the_samples_are_bounded_whatever_the_triangles_area() -> None:
    huge = _square(1000.0)  # a square kilometre: 4.4 billion samples at 1.5 cm
    out = sample_large_triangles(huge, min_edge_m=0.1, spacing_m=0.015, max_samples=5000)
    assert len(out.points) == 4 + 5000


def test_a_mesh_of_small_triangles_comes_back_as_it_is() -> None:
    scan = _square(0.05)
    assert sample_large_triangles(scan, min_edge_m=0.1, spacing_m=0.02) is scan
    assert sample_large_triangles(_square(1.0), min_edge_m=0.0, spacing_m=0.02).points.shape == (4, 3)  # 0 = off


def test_a_site_built_from_a_decimated_mesh_has_a_dense_map(tmp_path: Path) -> None:
    # A 4 m x 3 m floor and two walls in a handful of large triangles.
    v = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0], [0, 0, 2.5], [4, 0, 2.5], [0, 3, 2.5]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 5], [0, 5, 4], [0, 3, 6], [0, 6, 4]])
    rgb = np.array([[200, 180, 160]] * 7, dtype=np.uint8)
    path = tmp_path / "coarse.ply"
    write_ply(path, {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]},
              faces)
    assert len(read_scan(path).points) == 7
    site = build_site(path)
    xyz = site.map.points.astype(np.float64)
    assert len(xyz) > 50_000  # 32 m² at 1.5 cm
    spacing, _ = cKDTree(xyz).query(xyz, k=2)
    assert np.median(spacing[:, 1]) < 0.02


@pytest.mark.realdata
def test_scannet_meshes_are_dense_enough_to_take_as_they_are(scene0470_dir: Path) -> None:
    scan = read_scan(scene0470_dir / "scene0470_00_vh_clean_2.ply")
    assert sample_large_triangles(scan, min_edge_m=0.1, spacing_m=0.015) is scan
