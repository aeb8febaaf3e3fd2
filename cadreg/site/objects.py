"""Objects of the map that no CAD covers: class-wise Euclidean clustering of labelled points (paper §2.3.1 applied
to the map), and the boxes that describe objects."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass
class Cluster:
    """One cluster: `indices` (k,) int64 into the clustered point array; `class_index` its class."""

    class_index: int
    indices: np.ndarray


# Above this many points, euclidean_clusters works on voxel means (bounded memory) instead of the points themselves.
_DIRECT_CLUSTERING_MAX_POINTS = 60000
# Clusters of one class over one another are one object (`merge_stacked`) only when less than this apart in height:
# the parts a scan loses between a seat and its base are tens of centimetres, a storey is 2.4 m or more.
STACK_GAP_M = 1.0


def _components(points: np.ndarray, tolerance_m: float) -> np.ndarray:
    """(n,) int component label of each point in the graph joining points ≤ tolerance_m apart."""
    n = len(points)
    pairs = cKDTree(points).query_pairs(tolerance_m, output_type="ndarray")
    adj = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(adj, directed=False)[1]


def euclidean_clusters(points: np.ndarray, tolerance_m: float, min_points: int) -> list[np.ndarray]:
    """Connected components of the graph joining points ≤ tolerance_m apart (PCL's Euclidean clustering).

    points : (n, 3) float. Returns index arrays (int64) of the components with ≥ min_points points, largest first.
    """
    n = len(points)
    if n == 0:
        return []
    points = np.asarray(points, dtype=np.float64)
    if n > _DIRECT_CLUSTERING_MAX_POINTS:
        # Dense maps (TSDF, 1 cm) give ~100 neighbours per point within 5 cm: the pair list would take GBs. Cluster
        # voxel means at half the tolerance instead; points of one voxel are within ~0.9 tolerance of each other.
        keys = np.floor(points / (tolerance_m / 2.0)).astype(np.int64)
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.ravel()
        means = np.zeros((len(counts), 3))
        np.add.at(means, inverse, points)
        means /= counts[:, None]
        comp = _components(means, tolerance_m)[inverse]
    else:
        comp = _components(points, tolerance_m)
    order = np.argsort(comp, kind="stable")
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    groups = [g for g in np.split(order, bounds) if len(g) >= min_points]
    return sorted(groups, key=len, reverse=True)


def classwise_clusters(
    points: np.ndarray,
    class_index: np.ndarray,
    tolerance_m: float,
    min_points: int,
    progress: Callable[[int, int], None] | None = None,
) -> list[Cluster]:
    """Cluster the points of each class on its own.

    points : (n, 3) float, metres; class_index : (n,) int, -1 = not an object (skipped).
    Returns clusters ordered by class index, then size.
    """
    classes = [int(c) for c in np.unique(class_index) if c >= 0]
    out: list[Cluster] = []
    for k, c in enumerate(classes):
        idx = np.flatnonzero(class_index == c)
        for g in euclidean_clusters(points[idx], tolerance_m, min_points):
            out.append(Cluster(c, idx[g]))
        if progress is not None:
            progress(k + 1, len(classes))
    return out


def aabb_center(points: np.ndarray) -> np.ndarray:
    """(3,) float64 centre of the axis-aligned bounding box of (n, 3) points."""
    p = np.asarray(points, dtype=np.float64)
    return (p.min(axis=0) + p.max(axis=0)) / 2.0


def upright_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Oriented box with a vertical axis (maps are z-up): yaw from PCA of the horizontal spread.

    points : (n, 3) float, metres. Returns centre (3,), full extent (3,), R (3, 3) whose columns are the box axes.
    """
    p = np.asarray(points, dtype=np.float64)
    xy = p[:, :2] - p[:, :2].mean(axis=0)
    if len(p) >= 3 and np.linalg.matrix_rank(xy, tol=1e-9) == 2:
        _, vecs = np.linalg.eigh(xy.T @ xy)
        major = vecs[:, 1]
    else:
        major = np.array([1.0, 0.0])
    R = np.eye(3)
    R[:2, 0] = major
    R[:2, 1] = [-major[1], major[0]]
    local = p @ R
    lo, hi = local.min(axis=0), local.max(axis=0)
    return R @ ((lo + hi) / 2.0), hi - lo, R


def affine_box(A: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The oriented box that an affine map A (4×4, rotation·scale) makes of the local box [lo, hi].

    Returns centre (3,), full extent (3,), R (3, 3) rotation (columns = box axes), all float64.
    """
    L = A[:3, :3]
    norms = np.linalg.norm(L, axis=0)
    # With an anisotropic scale on the scan side the columns are not exactly orthogonal: take the nearest rotation.
    U, _, Vt = np.linalg.svd(L / norms)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    center = L @ ((lo + hi) / 2.0) + A[:3, 3]
    return center, (hi - lo) * norms, R


def points_in_box(points: np.ndarray, center: np.ndarray, extent: np.ndarray, R: np.ndarray,
                  margin_m: float = 0.0) -> np.ndarray:
    """(n,) bool: points inside the oriented box grown by margin_m on every side."""
    local = (np.asarray(points, dtype=np.float64) - center) @ R
    return np.all(np.abs(local) <= extent / 2.0 + margin_m, axis=1)


def merge_stacked(points: np.ndarray, clusters: list[Cluster], min_overlap: float) -> list[Cluster]:
    """Merge clusters of one class that stand over one another (same place in the horizontal plane).

    Scans lose thin vertical parts (the gas column of a swivel chair, table legs), so one piece of furniture falls
    apart into a seat and a base; maps are z-up, so "one above the other" is one object. Two clusters merge when the
    intersection of their horizontal bounding boxes covers at least `min_overlap` of the smaller one's area, and
    they lie less than STACK_GAP_M apart in height: a chair a storey above another is another chair (a scan of two
    storeys made one node of the two, half-way between its floors).
    points : (n, 3) float, the array the clusters index. Returns merged clusters ordered by class, then size.
    """
    boxes = [(points[c.indices, :2].min(axis=0), points[c.indices, :2].max(axis=0)) for c in clusters]
    heights = [(points[c.indices, 2].min(), points[c.indices, 2].max()) for c in clusters]
    parent = list(range(len(clusters)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(len(clusters)):
        for j in range(i + 1, len(clusters)):
            if clusters[i].class_index != clusters[j].class_index:
                continue
            if max(heights[i][0], heights[j][0]) - min(heights[i][1], heights[j][1]) >= STACK_GAP_M:
                continue
            (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
            inter = np.clip(np.minimum(hi_i, hi_j) - np.maximum(lo_i, lo_j), 0, None).prod()
            smaller = min(np.prod(np.maximum(hi_i - lo_i, 1e-6)), np.prod(np.maximum(hi_j - lo_j, 1e-6)))
            if inter >= min_overlap * smaller:
                parent[find(j)] = find(i)
    groups: dict[int, list[int]] = {}
    for i in range(len(clusters)):
        groups.setdefault(find(i), []).append(i)
    merged = [Cluster(clusters[g[0]].class_index, np.sort(np.concatenate([clusters[k].indices for k in g])))
              for g in groups.values()]
    return sorted(merged, key=lambda c: (c.class_index, -len(c.indices)))
