"""Class-wise Euclidean clustering of a frame's labelled points into scan objects (paper §2.3.1).

The paper grows regions from seed points over a KD-tree; the same partition is the connected components of the
graph "two points of one class closer than the tolerance", which scipy computes without a Python loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass
class ScanCluster:
    """One object instance seen in the frame, colour-camera frame, metres.

    cls : graph class index (into `Site.classes`).
    centroid : (3,) float64 mean of the cluster's points.
    box_center, box_extent : (3,) float64 axis-aligned box of the points (camera axes).
    index : (m,) int indices into the clustered point array.
    """

    cls: int
    centroid: np.ndarray
    box_center: np.ndarray
    box_extent: np.ndarray
    index: np.ndarray

    @property
    def size_m(self) -> float:
        """Longest box side, metres (rotation-dependent, so only used loosely)."""
        return float(self.box_extent.max())


def cluster_objects(xyz: np.ndarray, class_index: np.ndarray, *, tolerance_m: float = 0.05,
                    min_points: int = 30) -> list[ScanCluster]:
    """Cluster points class by class.

    xyz : (n, 3) float, any frame. class_index : (n,) int, -1 = no object class (skipped).
    Returns clusters with at least `min_points` points, largest first.
    """
    clusters: list[ScanCluster] = []
    for cls in np.unique(class_index):
        if cls < 0:
            continue
        idx = np.flatnonzero(class_index == cls)
        if len(idx) < min_points:
            continue
        pts = xyz[idx]
        pairs = cKDTree(pts).query_pairs(tolerance_m, output_type="ndarray")
        n = len(idx)
        adj = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        ncomp, comp = connected_components(adj, directed=False)
        counts = np.bincount(comp, minlength=ncomp)
        for c in np.flatnonzero(counts >= min_points):
            member = idx[comp == c]
            p = xyz[member]
            lo, hi = p.min(axis=0), p.max(axis=0)
            clusters.append(ScanCluster(int(cls), p.mean(axis=0), (lo + hi) / 2, hi - lo, member))
    clusters.sort(key=lambda c: -len(c.index))
    return clusters
