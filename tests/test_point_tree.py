"""The KD-tree of the refinement's maps (`cadreg/localize/point_tree.py`): its answers are SciPy's cKDTree's, for
points in its order and in any other."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cadreg.localize.point_tree import LEAF_SIZE, PointTree, tree_depth, tree_order


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # a room's surfaces: a floor, two walls and a box, as the maps are (points on planes, not a filled volume)
    u = rng.random((n, 2)) * [4.0, 3.0]
    which = rng.integers(0, 4, n)
    xyz = np.zeros((n, 3))
    xyz[which == 0] = np.column_stack([u[which == 0], np.zeros((which == 0).sum())])
    xyz[which == 1] = np.column_stack([u[which == 1, 0], np.zeros((which == 1).sum()), u[which == 1, 1]])
    xyz[which == 2] = np.column_stack([np.zeros((which == 2).sum()), u[which == 2]])
    xyz[which == 3] = 1.0 + 0.5 * rng.random(((which == 3).sum(), 3))
    return xyz


@pytest.mark.parametrize("n", [1, 2, LEAF_SIZE, LEAF_SIZE + 1, 1000, 20000])
@pytest.mark.parametrize("ordered", [True, False])
def test_queries_are_ckdtrees(n: int, ordered: bool) -> None:
    xyz = _cloud(n)
    tree = PointTree.sorted(xyz)[0] if ordered else PointTree(xyz)  # any order is a correct tree, only slower
    reference = cKDTree(tree.xyz)
    rng = np.random.default_rng(1)
    q = tree.xyz[rng.integers(0, n, 500)] + rng.normal(0.0, 0.05, (500, 3))
    for bound in (0.02, 0.1, np.inf):
        d, i = tree.query(q, k=1, distance_upper_bound=bound)
        d_ref, i_ref = reference.query(q, k=1, distance_upper_bound=bound)
        assert np.allclose(d, d_ref) and np.array_equal(i, i_ref)  # none found: inf and n, as cKDTree
    k = min(10, n)
    d, i = tree.query(q, k=k)
    d_ref, i_ref = reference.query(q, k=k)
    assert np.allclose(np.reshape(d, (500, -1)), np.reshape(d_ref, (500, -1)))
    assert np.array_equal(np.reshape(i, (500, -1)), np.reshape(i_ref, (500, -1)))
    for center in q[:20]:
        for r in (0.05, 0.5, 3.0):
            assert tree.count_within(center, r) == reference.query_ball_point(center, r, return_length=True)


def test_the_order_is_a_tree_of_small_leaves_and_the_tree_is_its_points() -> None:
    xyz = _cloud(5000)
    order = tree_order(xyz)
    assert np.array_equal(np.sort(order), np.arange(len(xyz)))
    tree = PointTree(xyz[order])
    assert tree.depth == tree_depth(5000) and 5000 / 2 ** tree.depth <= LEAF_SIZE < 5000 / 2 ** (tree.depth - 1)
    first_leaf = 2 ** tree.depth - 1
    sizes = tree.stop[first_leaf:] - tree.start[first_leaf:]
    assert sizes.min() >= 1 and sizes.max() <= LEAF_SIZE and sizes.sum() == 5000
    # in tree order, sibling leaves barely overlap; in the input's order each leaf's box spans the room
    span = lambda t: np.prod(t.hi[first_leaf:] - t.lo[first_leaf:] + 0.01, axis=1).mean()  # noqa: E731
    assert span(tree) < 0.01 * span(PointTree(xyz))


def test_an_empty_tree_and_a_nan_query_find_nothing() -> None:
    empty = PointTree(np.zeros((0, 3)))
    d, i = empty.query(np.zeros((2, 3)))
    assert np.all(np.isinf(d)) and np.all(i == 0) and empty.count_within(np.zeros(3), 1.0) == 0
    tree = PointTree.sorted(_cloud(300))[0]
    d, i = tree.query(np.array([[np.nan, 0.0, 0.0]]), k=3)
    assert np.all(np.isinf(d)) and np.all(i == 300)
