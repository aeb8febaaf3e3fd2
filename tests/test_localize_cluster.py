"""Class-wise Euclidean clustering (paper §2.3.1)."""

from __future__ import annotations

import numpy as np

from cadreg.localize.cluster import cluster_objects


def _blob(rng, centre, n=200, r=0.1):
    return centre + rng.uniform(-r, r, size=(n, 3))


def test_same_class_far_apart_are_two_objects_and_classes_never_merge() -> None:
    rng = np.random.default_rng(0)
    a = _blob(rng, np.array([0.0, 0, 0]))
    b = _blob(rng, np.array([1.0, 0, 0]))
    c = _blob(rng, np.array([0.0, 0, 0]), n=300)  # overlaps a, other class
    noise = _blob(rng, np.array([3.0, 0, 0]), n=5)
    xyz = np.vstack([a, b, c, noise])
    cls = np.concatenate([np.zeros(400, int), np.ones(300, int), np.zeros(5, int)])
    out = cluster_objects(xyz, cls, tolerance_m=0.05, min_points=30)
    assert sorted((o.cls, len(o.index)) for o in out) == [(0, 200), (0, 200), (1, 300)]
    for o in out:
        assert np.allclose(o.centroid, xyz[o.index].mean(axis=0))
        assert np.all(o.box_extent <= 0.2 + 1e-9)


def test_unlabelled_points_are_ignored_and_empty_input_works() -> None:
    rng = np.random.default_rng(1)
    xyz = _blob(rng, np.zeros(3))
    assert cluster_objects(xyz, np.full(len(xyz), -1)) == []
    assert cluster_objects(np.zeros((0, 3)), np.zeros(0, int)) == []


def test_chain_of_points_within_tolerance_is_one_object() -> None:
    x = np.arange(0, 2.0, 0.04)
    xyz = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    out = cluster_objects(xyz, np.zeros(len(x), int), tolerance_m=0.05, min_points=10)
    assert len(out) == 1 and len(out[0].index) == len(x)
    out = cluster_objects(xyz, np.zeros(len(x), int), tolerance_m=0.03, min_points=1)
    assert len(out) == len(x)


def test_components_are_numbered_as_scipy_numbers_them() -> None:
    """The compiled union-find labels the nodes as scipy's `connected_components` does: the same partition, each
    component numbered in the order of its lowest node (the clusters' order among objects of one size)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from cadreg.localize.cluster import components

    rng = np.random.default_rng(3)
    for n in (1, 2, 17, 300):
        for edges in (0, n // 2, 3 * n):
            pairs = rng.integers(0, n, size=(edges, 2))
            pairs = pairs[pairs[:, 0] != pairs[:, 1]]
            adjacency = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
            _, expected = connected_components(adjacency, directed=False)
            assert np.array_equal(components(np.ascontiguousarray(pairs, dtype=np.int64), n), expected)
