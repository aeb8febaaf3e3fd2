"""Map enhancement on a synthetic scene with a known CAD placement (rotation, anisotropic scale, translation)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cadreg.config import EnhanceConfig
from cadreg.geometry import make_T, quat_wxyz_to_R
from cadreg.labels import GRAPH_CLASSES
from cadreg.pointset import SOURCE_CAD, SOURCE_RAW, PointSet
from cadreg.site.enhance import CadPlacement, enhance_map, transfer_colors

CLASSES = list(GRAPH_CLASSES)
CHAIR, BAG = CLASSES.index("chair"), CLASSES.index("bag")
RED, BLUE, GREY = (200, 30, 30), (20, 40, 220), (120, 120, 120)


def _placement() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A_scan_cad for a unit cube CAD: scale (0.4, 0.6, 0.8), yaw 30°, centred at (1, 1, 0.4): it stands on z = 0."""
    yaw = np.radians(30)
    R = quat_wxyz_to_R([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
    A = make_T(R, [1.0, 1.0, 0.4]) @ np.diag([0.4, 0.6, 0.8, 1.0])
    return A, R, np.array([0.4, 0.6, 0.8])


def _scene(seed: int = 0) -> tuple[PointSet, np.ndarray]:
    """Floor grid (structure, grey) + the raw points of the placed box (chair, red, on the sides and top, with
    1 cm noise) + a small bag (blue) resting against the box + some unlabeled junk inside the box."""
    rng = np.random.default_rng(seed)
    A, R, size = _placement()
    g = np.arange(0.0, 2.0, 0.02)
    fx, fy = np.meshgrid(g, g)
    floor = np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], axis=1)
    box = trimesh.creation.box(extents=(1, 1, 1))
    box.apply_transform(A)
    obj, face = trimesh.sample.sample_surface(box, 3000, seed=1)
    keep = box.face_normals[face][:, 2] > -0.5  # no points under the box: the scanner never saw them
    obj = obj[keep] + rng.normal(scale=0.01, size=(keep.sum(), 3))
    junk = np.array([1.0, 1.0, 0.4]) + rng.normal(scale=0.02, size=(30, 3))
    bag = np.array([1.0, 1.0, 0.8]) + rng.uniform(-0.08, 0.08, size=(200, 3)) + [0, 0, 0.05]
    pts = np.vstack([floor, obj, junk, bag]).astype(np.float32)
    n_f, n_o, n_j, n_b = len(floor), len(obj), len(junk), len(bag)
    colors = np.vstack([np.tile(GREY, (n_f, 1)), np.tile(RED, (n_o, 1)), np.tile(GREY, (n_j, 1)),
                        np.tile(BLUE, (n_b, 1))]).astype(np.uint8)
    cls = np.concatenate([np.full(n_f, -1), np.full(n_o, CHAIR), np.full(n_j, -1), np.full(n_b, BAG)]).astype(np.int16)
    structure = np.concatenate([np.ones(n_f, bool), np.zeros(n_o + n_j + n_b, bool)])
    normals = np.tile([0, 0, 1], (len(pts), 1)).astype(np.float32)
    n = len(pts)
    raw = PointSet(pts, colors, normals, np.full(n, -1, np.int32), cls, np.zeros(n, np.uint8))
    return raw, structure


@pytest.fixture(scope="module")
def enhanced():
    raw, structure = _scene()
    A, _, _ = _placement()
    cad = trimesh.creation.box(extents=(1, 1, 1))
    cfg = EnhanceConfig(box_dilation_m=0.05, cad_sample_spacing_m=0.01, color_transfer_k=4)
    return raw, structure, enhance_map(raw, structure, [CadPlacement(cad, A, "chair", "03001627/box")], CLASSES, cfg)


def test_raw_object_points_are_replaced_and_the_rest_kept(enhanced):
    raw, structure, out = enhanced
    m = out.map
    kept_raw = m.source == SOURCE_RAW
    # every floor point survives (the box stands on the floor: dilation must not punch a hole)
    assert (m.points[kept_raw][:, 2] == 0).sum() == structure.sum()
    # no red (chair) raw point and no unlabeled junk is left; the bag on top, another object, stays whole
    assert not np.any((m.class_index[kept_raw] == CHAIR))
    assert (m.class_index[kept_raw] == BAG).sum() == (raw.class_index == BAG).sum()
    assert out.removed_raw == (raw.class_index == CHAIR).sum() + 30
    assert len(m) == len(raw) - out.removed_raw + (m.source == SOURCE_CAD).sum()


def test_cad_points_lie_on_the_placed_surface_with_density_normals_and_tags(enhanced):
    _, _, out = enhanced
    A, R, size = _placement()
    m = out.map
    cad = m.source == SOURCE_CAD
    p = m.points[cad].astype(np.float64)
    local = (p - A[:3, 3]) @ R  # box frame, half sizes = size / 2
    # distance to the box surface: on a face, |local| reaches the half size on one axis and stays within on others
    d = np.abs(np.abs(local) - size / 2).min(axis=1)
    assert np.all(np.abs(local) <= size / 2 + 1e-4) and d.max() < 1e-4
    area = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    assert abs(cad.sum() - area / 0.01**2) < 2
    assert np.all(m.instance[cad] == 0) and np.all(m.class_index[cad] == CHAIR)
    assert np.all(m.instance[~cad] == -1)
    # normals point out of the box
    n = m.normals[cad].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", n, p - A[:3, 3]) > 0)
    node = out.cad_nodes[0]
    assert node.id == "cad-0" and node.source == "cad" and node.cls == "chair" and node.points == cad.sum()
    np.testing.assert_allclose(node.centroid, [1.0, 1.0, 0.4], atol=1e-6)
    np.testing.assert_allclose(node.box_extent, size, atol=1e-9)
    np.testing.assert_allclose(node.box_R, R, atol=1e-9)


def test_colours_come_from_the_replaced_points(enhanced):
    _, _, out = enhanced
    m = out.map
    cad = m.source == SOURCE_CAD
    top = cad & (m.points[:, 2] > 0.79)
    side = cad & (m.points[:, 2] > 0.1) & (m.points[:, 2] < 0.7)
    # sides were red in the scan; the top is red with grey from the junk in the box centre far away
    assert np.abs(m.colors[side].astype(int) - RED).max() <= 1
    assert np.median(np.abs(m.colors[top].astype(int) - RED).sum(axis=1)) <= 3


def test_transfer_colors_weights_by_distance():
    src = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    cols = np.array([[0, 0, 0], [200, 100, 50]], dtype=np.uint8)
    out = transfer_colors(np.array([[0.25, 0, 0], [1.0, 0, 0]]), src, cols, k=2)
    np.testing.assert_array_equal(out[0], np.round(np.array([200, 100, 50]) * (1 / 0.75) / (1 / 0.25 + 1 / 0.75)))
    np.testing.assert_array_equal(out[1], [200, 100, 50])
    np.testing.assert_array_equal(transfer_colors(np.zeros((2, 3)), src[:1], cols[:1], k=4), [[0, 0, 0]] * 2)


def test_without_labels_everything_in_the_box_goes(enhanced):
    raw, _, _ = enhanced
    A, _, _ = _placement()
    bare = PointSet(raw.points, raw.colors, raw.normals, raw.instance, np.full(len(raw), -1, np.int16), raw.source)
    out = enhance_map(bare, np.zeros(len(raw), bool), [CadPlacement(trimesh.creation.box(extents=(1, 1, 1)), A,
                      "chair", "x/y")], CLASSES, EnhanceConfig(cad_sample_spacing_m=0.03))
    kept = out.map.points[out.map.source == SOURCE_RAW].astype(np.float64)
    _, R, size = _placement()
    local = (kept - A[:3, 3]) @ R
    assert not np.any(np.all(np.abs(local) <= size / 2 + 0.05 - 1e-6, axis=1))
