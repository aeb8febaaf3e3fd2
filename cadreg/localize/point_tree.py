"""A KD-tree whose nodes are implied by the order of its points: the search structure of a map the refinement
reads (`refine.RefineMap`: nearest map points for the fitness, the agreement and the GICP, neighbours for the
map's normals, the count of map points in a region of interest).

Written here, and why: a building's region maps are made from its stored region grids (`site compose`), and each
of the KD-trees a library builds (SciPy's cKDTree, small_gicp's, Open3D's) can only be built, not read: a worker
rebuilt a region's tree each time its cache took the region in (13-18 ms for a 100-room building's 150 k-point
region, more than a fifth of a frame's time at 100 rooms, since a frame looks into a room no recent frame did), and
no library tree can be stored in the bundle (cKDTree's state is private and unchecked, a pickle runs code). Here
the tree is the order of the points alone: `tree_order` sorts them once, when the site is composed, and the bundle
stores them in that order, so that a worker's tree is the stored rows plus their nodes' boxes (one pass over the
points, ~1 ms). Any order gives a correct tree (each node's box is measured from the points it holds), so a stored
order is never trusted for correctness, only for speed.

Shape: node 0 holds points [0, n); a node holding [a, b) splits at m = (a + b) // 2 into its children 2i + 1
([a, m)) and 2i + 2 ([m, b)), down to `depth` levels, the least for which no leaf holds more than `leaf_size`
points. `tree_order` puts the points of each node's lower half, along the axis of its box's largest extent, before
those of its upper half (a median split, as cKDTree's balanced trees). Queries are compiled loops (numba):
depth-first, the nearer child first, a node skipped once its box is farther than the best found.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

LEAF_SIZE = 32  # cKDTree's leaves of 32 points had been the fastest to build at the same query speed


def tree_depth(n: int, leaf_size: int = LEAF_SIZE) -> int:
    """The levels below the root of the tree of n points: the fewest for which no leaf holds more than leaf_size
    (every leaf then holds at least one point)."""
    return 0 if n <= leaf_size else int(math.ceil(math.log2(n / leaf_size)))


def tree_order(xyz: np.ndarray, leaf_size: int = LEAF_SIZE) -> np.ndarray:
    """(n,) int64 permutation that puts xyz ((n, 3)) in the order of its tree (`PointTree` over xyz[order])."""
    xyz = np.require(xyz, np.float64, ["C"])
    order = np.arange(len(xyz), dtype=np.int64)
    _sort_into_tree(xyz, order, tree_depth(len(xyz), leaf_size))
    return order


class PointTree:
    """The tree over xyz ((n, 3) map frame, metres), its points in `tree_order` (any order is correct; that one
    is fast). Queries as cKDTree's: a point with no neighbour found reads distance inf and index n."""

    def __init__(self, xyz: np.ndarray, leaf_size: int = LEAF_SIZE) -> None:
        self.xyz = np.require(xyz, np.float64, ["C"])
        self.n = len(self.xyz)
        self.depth = tree_depth(self.n, leaf_size)
        nodes = 2 ** (self.depth + 1) - 1
        self.start, self.stop = np.empty(nodes, dtype=np.int64), np.empty(nodes, dtype=np.int64)
        self.lo, self.hi = np.empty((nodes, 3)), np.empty((nodes, 3))
        _boxes(self.xyz, self.depth, self.start, self.stop, self.lo, self.hi)

    @classmethod
    def sorted(cls, xyz: np.ndarray, leaf_size: int = LEAF_SIZE) -> tuple["PointTree", np.ndarray]:
        """The tree over xyz put in tree order, and that order (tree.xyz = xyz[order])."""
        order = tree_order(xyz, leaf_size)
        return cls(np.asarray(xyz, dtype=np.float64)[order], leaf_size), order

    def _args(self) -> tuple:
        return self.xyz, self.start, self.stop, self.lo, self.hi, self.depth

    def query(self, q: np.ndarray, k: int = 1,
              distance_upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest points of each query point q ((m, 3)) closer than distance_upper_bound: distances and
        indices, (m,) for k = 1, else (m, k), nearest first."""
        q = np.require(np.asarray(q, dtype=np.float64).reshape(-1, 3), np.float64, ["C"])
        k = int(k)
        d2 = np.full((len(q), k), np.inf)
        index = np.full((len(q), k), self.n, dtype=np.int64)
        bound2 = float(distance_upper_bound) ** 2 if np.isfinite(distance_upper_bound) else np.inf
        if self.n and k > 0:
            _knn(*self._args(), q, bound2, d2, index)
        d = np.sqrt(d2)
        return (d[:, 0], index[:, 0]) if k == 1 else (d, index)

    def count_within(self, center: np.ndarray, radius_m: float) -> int:
        """How many points lie within radius_m of center ((3,))."""
        if not self.n:
            return 0
        return int(_count_within(*self._args(), np.asarray(center, dtype=np.float64).reshape(3),
                                 float(radius_m) ** 2))


def warm() -> None:
    """Compile (or load from numba's cache) the loops below (`localizer.compile_loops`)."""
    tree, _ = PointTree.sorted(np.random.default_rng(0).random((100, 3)), leaf_size=8)
    tree.query(tree.xyz[:3], k=1, distance_upper_bound=0.1)
    tree.query(tree.xyz[:3], k=3)
    tree.count_within(np.zeros(3), 0.5)


# --- compiled loops -----------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def _sort_into_tree(xyz, order, depth):
    # Top-down, node by node in heap order: the node's points (a slice of `order`) split at its middle position
    # along the axis of their largest extent, by selection (no full sort).
    n = len(order)
    nodes = 2 ** depth - 1  # the internal nodes
    start = np.empty(2 ** (depth + 1) - 1, dtype=np.int64)
    stop = np.empty_like(start)
    start[0], stop[0] = 0, n
    for i in range(nodes):
        a, b = start[i], stop[i]
        m = (a + b) // 2
        start[2 * i + 1], stop[2 * i + 1], start[2 * i + 2], stop[2 * i + 2] = a, m, m, b
        if b - a < 2:
            continue
        axis, widest = 0, -1.0
        for c in range(3):
            lo, hi = np.inf, -np.inf
            for j in range(a, b):
                v = xyz[order[j], c]
                lo, hi = min(lo, v), max(hi, v)
            if hi - lo > widest:
                axis, widest = c, hi - lo
        _select(xyz, order, a, b, m, axis)


@njit(cache=True, nogil=True)
def _select(xyz, order, a, b, kth, axis):
    # Hoare's selection on order[a:b] by xyz[order, axis]: afterwards no point before position kth lies above the
    # one at kth and none after it below.
    lo, hi = a, b - 1
    while lo < hi:
        mid = (lo + hi) // 2
        # the median of three as pivot
        x, y, z = xyz[order[lo], axis], xyz[order[mid], axis], xyz[order[hi], axis]
        pivot = max(min(x, y), min(max(x, y), z))
        i, j = lo, hi
        while i <= j:
            while xyz[order[i], axis] < pivot:
                i += 1
            while xyz[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            return


@njit(cache=True, nogil=True)
def _boxes(xyz, depth, start, stop, lo, hi):
    # Ranges top-down, then each leaf's box from its points and each inner node's from its children's.
    start[0], stop[0] = 0, len(xyz)
    first_leaf = 2 ** depth - 1
    for i in range(first_leaf):
        a, b = start[i], stop[i]
        m = (a + b) // 2
        start[2 * i + 1], stop[2 * i + 1], start[2 * i + 2], stop[2 * i + 2] = a, m, m, b
    for i in range(first_leaf, len(start)):
        for c in range(3):
            lo[i, c], hi[i, c] = np.inf, -np.inf
        for j in range(start[i], stop[i]):
            for c in range(3):
                lo[i, c] = min(lo[i, c], xyz[j, c])
                hi[i, c] = max(hi[i, c], xyz[j, c])
    for i in range(first_leaf - 1, -1, -1):
        for c in range(3):
            lo[i, c] = min(lo[2 * i + 1, c], lo[2 * i + 2, c])
            hi[i, c] = max(hi[2 * i + 1, c], hi[2 * i + 2, c])


@njit(cache=True, nogil=True, inline="always")
def _box_d2(lo, hi, i, x, y, z):
    # squared distance from (x, y, z) to node i's box (0 inside)
    dx = max(lo[i, 0] - x, 0.0, x - hi[i, 0])
    dy = max(lo[i, 1] - y, 0.0, y - hi[i, 1])
    dz = max(lo[i, 2] - z, 0.0, z - hi[i, 2])
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True)
def _knn(xyz, start, stop, lo, hi, depth, q, bound2, d2, index):
    # d2, index : (m, k), filled with (inf, n); each row kept sorted, nearest first. A NaN query finds nothing.
    k = d2.shape[1]
    first_leaf = 2 ** depth - 1
    stack = np.empty(depth + 2, dtype=np.int64)
    stack_d2 = np.empty(depth + 2)
    for p in range(len(q)):
        x, y, z = q[p, 0], q[p, 1], q[p, 2]
        worst = bound2  # the k-th best distance so far, or the bound
        top = 0
        stack[0], stack_d2[0] = 0, _box_d2(lo, hi, 0, x, y, z)
        while top >= 0:
            node, nd2 = stack[top], stack_d2[top]
            top -= 1
            if not nd2 < worst:
                continue
            if node >= first_leaf:
                for j in range(start[node], stop[node]):
                    dx, dy, dz = xyz[j, 0] - x, xyz[j, 1] - y, xyz[j, 2] - z
                    e = dx * dx + dy * dy + dz * dz
                    if e < worst:
                        # insert into the sorted row, dropping its last
                        s = k - 1
                        while s > 0 and d2[p, s - 1] > e:
                            d2[p, s], index[p, s] = d2[p, s - 1], index[p, s - 1]
                            s -= 1
                        d2[p, s], index[p, s] = e, j
                        if d2[p, k - 1] < bound2:
                            worst = d2[p, k - 1]
                continue
            a, b = 2 * node + 1, 2 * node + 2
            da, db = _box_d2(lo, hi, a, x, y, z), _box_d2(lo, hi, b, x, y, z)
            if da > db:  # the nearer child on top of the stack
                a, b, da, db = b, a, db, da
            if db < worst:
                top += 1
                stack[top], stack_d2[top] = b, db
            if da < worst:
                top += 1
                stack[top], stack_d2[top] = a, da


@njit(cache=True, nogil=True)
def _count_within(xyz, start, stop, lo, hi, depth, center, r2):
    first_leaf = 2 ** depth - 1
    x, y, z = center[0], center[1], center[2]
    stack = np.empty(depth + 2, dtype=np.int64)
    stack[0] = 0
    top, count = 0, 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if _box_d2(lo, hi, node, x, y, z) > r2:
            continue
        # the farthest corner of the box within the radius: all of its points count
        fx = max(abs(lo[node, 0] - x), abs(hi[node, 0] - x))
        fy = max(abs(lo[node, 1] - y), abs(hi[node, 1] - y))
        fz = max(abs(lo[node, 2] - z), abs(hi[node, 2] - z))
        if fx * fx + fy * fy + fz * fz <= r2:
            count += stop[node] - start[node]
        elif node >= first_leaf:
            for j in range(start[node], stop[node]):
                dx, dy, dz = xyz[j, 0] - x, xyz[j, 1] - y, xyz[j, 2] - z
                if dx * dx + dy * dy + dz * dz <= r2:
                    count += 1
        else:
            top += 1
            stack[top] = 2 * node + 1
            top += 1
            stack[top] = 2 * node + 2
    return count
