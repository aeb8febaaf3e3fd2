"""PLY reader/writer: binary (both endians) and ASCII, extra vertex properties, faces, malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from cadreg.errors import InvalidFileError
from cadreg.io.ply import parse_ply, ply_bytes, read_ply, read_scan, write_ply

HEADER_XYZRGB = "property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"


def _cloud(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n).astype(np.float32),
        "z": rng.normal(size=n).astype(np.float32),
        "red": rng.integers(0, 256, n).astype(np.uint8),
        "green": rng.integers(0, 256, n).astype(np.uint8),
        "blue": rng.integers(0, 256, n).astype(np.uint8),
        "label": rng.integers(0, 41, n).astype(np.uint16),
        "instance": rng.integers(-1, 9, n).astype(np.int32),
        "class": rng.integers(-1, 30, n).astype(np.int16),
        "w": rng.normal(size=n),
    }


def test_write_read_round_trip_keeps_every_property_and_dtype(tmp_path):
    v = _cloud(500)
    faces = np.random.default_rng(1).integers(0, 500, (300, 3))
    write_ply(tmp_path / "c.ply", v, faces)
    ply = read_ply(tmp_path / "c.ply")
    assert ply.format == "binary_little_endian"
    for k, a in v.items():
        assert ply.vertex[k].dtype == a.dtype, k
        np.testing.assert_array_equal(ply.vertex[k], a)
    np.testing.assert_array_equal(ply.elements["face"]["vertex_indices"], faces)


def test_big_endian_binary(tmp_path):
    n = 4
    pts = np.arange(12, dtype=">f4").reshape(n, 3)
    table = np.empty(n, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1"), ("green", "u1"),
                               ("blue", "u1"), ("label", ">u2")])
    table["x"], table["y"], table["z"] = pts.T
    table["red"], table["green"], table["blue"] = 10, 20, 30
    table["label"] = [5, 7, 300, 2]
    head = f"ply\nformat binary_big_endian 1.0\nelement vertex {n}\n{HEADER_XYZRGB}property ushort label\nend_header\n"
    (tmp_path / "be.ply").write_bytes(head.encode() + table.tobytes())
    scan = read_scan(tmp_path / "be.ply")
    np.testing.assert_array_equal(scan.points, pts.astype(np.float32))
    np.testing.assert_array_equal(scan.labels, [5, 7, 300, 2])
    assert scan.colors.tolist() == [[10, 20, 30]] * n
    assert scan.normals is None and scan.faces is None


def test_ascii_with_quads_is_fan_triangulated_and_gets_normals(tmp_path):
    text = (
        "ply\nformat ascii 1.0\ncomment a unit square as one quad, plus a triangle\nelement vertex 5\n"
        + HEADER_XYZRGB
        + "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 255 0 0\n1 0 0 0 255 0\n1 1 0 0 0 255\n0 1 0 9 9 9\n0 0 1 1 2 3\n"
        "4 0 1 2 3\n3 0 1 4\n"
    )
    (tmp_path / "a.ply").write_text(text)
    scan = read_scan(tmp_path / "a.ply")
    assert scan.points.shape == (5, 3) and scan.colors[3].tolist() == [9, 9, 9]
    assert scan.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    # vertex 2 and 3 only touch the quad in the z = 0 plane: their normal is ±z
    assert abs(abs(scan.normals[2, 2]) - 1.0) < 1e-6 and abs(abs(scan.normals[3, 2]) - 1.0) < 1e-6


def test_real_scene0470_scan_and_labels(scene0470_dir):
    scan = read_scan(scene0470_dir / "scene0470_00_vh_clean_2.ply", scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    assert scan.points.shape == (67465, 3) and scan.faces.shape == (127003, 3)
    assert scan.colors.dtype == np.uint8 and scan.colors.std() > 10
    lo, hi = scan.points.min(axis=0), scan.points.max(axis=0)
    np.testing.assert_allclose(lo, [0, 0, 0], atol=0.02)
    np.testing.assert_allclose(hi, [3.49, 2.85, 1.37], atol=0.02)
    assert set(np.unique(scan.labels).tolist()) == {0, 1, 2, 5, 7, 8, 9, 30, 37, 39}
    np.testing.assert_allclose(np.linalg.norm(scan.normals, axis=1), 1.0, atol=1e-4)


def _write_xyz_only(path, n=3):
    head = f"ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_text(head + "".join(f"{i} 0 0\n" for i in range(n)))


def test_ply_without_colours_is_refused_naming_the_file(tmp_path):
    _write_xyz_only(tmp_path / "nocolour.ply")
    with pytest.raises(InvalidFileError, match="nocolour.ply.*colour"):
        read_scan(tmp_path / "nocolour.ply")


def test_vertex_count_disagreeing_with_the_data_is_refused(tmp_path):
    v = _cloud(10)
    blob = ply_bytes(v)
    (tmp_path / "short.ply").write_bytes(blob[:-7])
    with pytest.raises(InvalidFileError, match=r"short\.ply.*declares 10"):
        read_ply(tmp_path / "short.ply")
    text = f"ply\nformat ascii 1.0\nelement vertex 5\n{HEADER_XYZRGB}end_header\n0 0 0 1 2 3\n1 1 1 1 2 3\n"
    (tmp_path / "few.ply").write_text(text)
    with pytest.raises(InvalidFileError, match=r"few\.ply.*declares 5"):
        read_ply(tmp_path / "few.ply")


def test_labels_ply_of_another_mesh_is_refused(tmp_path):
    v = _cloud(20)
    write_ply(tmp_path / "scan.ply", v)
    other = {k: a[:19] for k, a in v.items()}
    write_ply(tmp_path / "labels.ply", other)
    with pytest.raises(InvalidFileError, match=r"labels\.ply.*19 vertices.*20"):
        read_scan(tmp_path / "scan.ply", tmp_path / "labels.ply")
    moved = dict(v, x=v["x"] + 1.0)
    write_ply(tmp_path / "moved.ply", moved)
    with pytest.raises(InvalidFileError, match=r"moved\.ply.*vertices differ"):
        read_scan(tmp_path / "scan.ply", tmp_path / "moved.ply")


def test_not_a_ply_and_missing_file(tmp_path):
    (tmp_path / "junk.ply").write_bytes(b"hello world")
    with pytest.raises(InvalidFileError, match="junk.ply.*magic"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(InvalidFileError, match="absent.ply"):
        read_ply(tmp_path / "absent.ply")
    with pytest.raises(InvalidFileError, match="format"):
        parse_ply(b"ply\nformat binary_weird 1.0\nend_header\n", "x.ply")


def test_binary_faces_of_mixed_lengths(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]], dtype="<f4")
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex 5\n{HEADER_XYZRGB}" \
           "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    verts = b"".join(p.tobytes() + bytes([7, 8, 9]) for p in pts)
    faces = bytes([4]) + np.array([0, 1, 2, 3], "<i4").tobytes() + bytes([3]) + np.array([0, 1, 4], "<i4").tobytes()
    (tmp_path / "m.ply").write_bytes(head.encode() + verts + faces)
    scan = read_scan(tmp_path / "m.ply")
    assert scan.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    assert scan.colors.tolist() == [[7, 8, 9]] * 5
    (tmp_path / "bad.ply").write_bytes(head.encode() + verts + faces[:-3])
    with pytest.raises(InvalidFileError, match="bad.ply.*face.*truncated"):
        read_ply(tmp_path / "bad.ply")


def test_a_meshs_unused_vertices_are_dropped_with_their_labels(tmp_path):
    """`read_scan` keeps the vertices some face uses (stray ones 2 km away stretched a build over 2 km), their
    colours, normals and labels with them, and renumbers the faces."""
    from cadreg.io.ply import scan_ply_bytes

    v = np.array([[0, 0, 0], [9, 9, 9], [1, 0, 0], [0, 1, 0], [2000, 2000, 0], [1, 1, 0]], np.float32)
    c = np.arange(18, dtype=np.uint8).reshape(6, 3)
    f = np.array([[0, 2, 3], [2, 5, 3]])
    (tmp_path / "m.ply").write_bytes(scan_ply_bytes(v, c, f, np.array([1, 7, 2, 3, 9, 5], np.uint16)))
    scan = read_scan(tmp_path / "m.ply")
    used = [0, 2, 3, 5]
    assert np.array_equal(scan.points, v[used]) and np.array_equal(scan.colors, c[used])
    assert np.array_equal(scan.labels, [1, 2, 3, 5]) and len(scan.normals) == 4
    assert np.array_equal(scan.points[scan.faces], v[f])  # the same triangles


def test_coordinates_the_maps_floats_cannot_keep_are_refused_with_the_shift_to_apply(tmp_path):
    """A georeferenced scan (UTM: 4,100 km from the origin, where 32-bit floats keep 25-50 cm) is refused, naming
    the shift that brings it near the origin; 1 km from it is kept to well under a millimetre."""
    from cadreg.io.ply import scan_ply_bytes

    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    colours = np.full((3, 3), 200, np.uint8)
    (tmp_path / "near.ply").write_bytes(scan_ply_bytes((tri + [1000, -500, 20]).astype(np.float32), colours))
    assert np.allclose(read_scan(tmp_path / "near.ply").points, tri + [1000, -500, 20])
    (tmp_path / "utm.ply").write_bytes(scan_ply_bytes(tri + [500000.0, 4100000.0, 20.0], colours))
    with pytest.raises(InvalidFileError, match=r"utm\.ply.*subtract \(500000, 4100000, 20\)"):
        read_scan(tmp_path / "utm.ply")
