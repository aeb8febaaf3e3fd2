"""Rooms that repeat one another: where else in a building the view of a pose may be seen again.

Buildings repeat rooms (offices along a corridor, hotel rooms, classrooms), and a view of one may be seen, the
same or nearly, in each copy. The graph match finds a copy only when the frame's objects rank it within the tie
margin, and a copy missing a chair the frame does not see, or with a different neighbour, may rank lower: then
the answer is `ok` in one room while another shows the same, or the room that shows it better is never looked
at. So the map is asked directly: two rooms whose objects (classes and positions) coincide under one turn about
up and a shift are copies, and the pose of a view in one room, moved by that transform, is the same view in the
other. What the other room really shows there is then a render away (`field_view.py`).

Written here: the object layouts are matched by a RANSAC over pairs of same-class objects (no library matches
small labelled point sets under a 4-DoF transform); numpy scores every pair's transform at once.
"""

from __future__ import annotations

import numpy as np

from ..geometry import rotation_between
from .match import MapGraph

# Objects of two rooms correspond when, after the transform, one lies within this of the other (same class):
# a CAD model's centre in a scan placed twice agrees to centimetres; partly scanned furniture to a few decimetres.
MATCH_TOLERANCE_M = 0.3
# A pair of objects fixes a transform only when its two objects are this far apart (a close pair fixes the turn
# poorly) and its length agrees with the other room's pair within PAIR_TOLERANCE_M.
MIN_PAIR_M = 0.5
PAIR_TOLERANCE_M = 0.15
# Copies: at least this many objects, and this share of the smaller room's objects, correspond. Copies of one
# room each missing a few objects share few of them (two copies of an 11-object room missing three different
# ones each share 5 of 8): three objects of the same classes in the same layout are already no chance.
MIN_SHARED = 3
MIN_SHARED_SHARE = 0.4


class RoomTwins:
    """For each region of a building, the other regions that repeat it and the transform between them.

    graph : the site's graph; node_region : (k,) region index of each node (-1 none); up : the map's unit up.
    `of(a)` : [(b, T_b_a)] with T_b_a (4, 4) moving region a's content onto region b's (map frame), made on first
    use and kept (a row of a 100-room building costs a few milliseconds a region).
    """

    def __init__(self, graph: MapGraph, node_region: np.ndarray, up: np.ndarray, regions: int) -> None:
        R_level = rotation_between(np.asarray(up, dtype=np.float64), np.array([0.0, 0.0, 1.0]))
        self._R_level = R_level  # map -> level frame (z along up)
        self._level = graph.centroid @ R_level.T
        self._cls = graph.cls
        self._nodes = [np.flatnonzero(node_region == r) for r in range(regions)]
        self._found: dict[int, list[tuple[int, np.ndarray]]] = {}

    def of(self, a: int) -> list[tuple[int, np.ndarray]]:
        if a not in self._found:
            self._found[a] = [(b, T) for b in range(len(self._nodes)) if b != a
                              for T in [self._transform(self._nodes[a], self._nodes[b])] if T is not None]
        return self._found[a]

    def carry(self, nodes: np.ndarray, b: int, T_ba: np.ndarray) -> np.ndarray:
        """Graph node indices (-1: none) moved by T_ba onto their counterparts in region b: the nearest node of b of
        the same class within MATCH_TOLERANCE_M, else -1 (an object that copy lacks)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        out = np.full(len(nodes), -1, dtype=np.int64)
        nb = self._nodes[b]
        L = self._R_level
        for k, n in enumerate(nodes):
            if n < 0 or not len(nb):
                continue
            moved = L @ (T_ba[:3, :3] @ (L.T @ self._level[n]) + T_ba[:3, 3])
            d = np.linalg.norm(self._level[nb] - moved, axis=1)
            d[self._cls[nb] != self._cls[n]] = np.inf
            if d.min() < MATCH_TOLERANCE_M:
                out[k] = nb[int(np.argmin(d))]
        return out

    def _transform(self, na: np.ndarray, nb: np.ndarray) -> np.ndarray | None:
        """T (4, 4, map frame) taking the objects `na` onto the objects `nb`, or None when they are no copies."""
        if min(len(na), len(nb)) < MIN_SHARED:
            return None
        pa, pb, ca, cb = self._level[na], self._level[nb], self._cls[na], self._cls[nb]
        i, j = np.triu_indices(len(na), 1)
        k, m = np.nonzero(~np.eye(len(nb), dtype=bool))  # ordered pairs of b's objects
        da = np.linalg.norm(pa[j, :2] - pa[i, :2], axis=1)
        db = np.linalg.norm(pb[m, :2] - pb[k, :2], axis=1)
        ok = ((ca[i][:, None] == cb[k][None]) & (ca[j][:, None] == cb[m][None])
              & (np.abs(da[:, None] - db[None]) < PAIR_TOLERANCE_M) & (da[:, None] >= MIN_PAIR_M))
        p, q = np.nonzero(ok)
        if not len(p):
            return None
        va, vb = pa[j[p], :2] - pa[i[p], :2], pb[m[q], :2] - pb[k[q], :2]
        yaw = np.arctan2(vb[:, 1], vb[:, 0]) - np.arctan2(va[:, 1], va[:, 0])
        c, s = np.cos(yaw), np.sin(yaw)
        Rz = np.zeros((len(yaw), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        t = pb[k[q]] - np.einsum("hij,hj->hi", Rz, pa[i[p]])
        t[:, 2] = 0.0  # rooms of one floor: heights stay
        moved = np.einsum("hij,nj->hni", Rz, pa) + t[:, None, :]  # (h, |a|, 3)
        d = np.linalg.norm(moved[:, :, None, :] - pb[None, None], axis=3)  # (h, |a|, |b|)
        d = np.where(ca[:, None] == cb[None, :], d, np.inf)
        near = d.min(axis=2)
        inliers = (near < MATCH_TOLERANCE_M).sum(axis=1)
        residual = np.where(near < MATCH_TOLERANCE_M, near, 0.0).sum(axis=1)
        best = int(np.lexsort((residual, -inliers))[0])
        if inliers[best] < max(MIN_SHARED, MIN_SHARED_SHARE * min(len(na), len(nb))):
            return None
        T_level = np.eye(4)
        T_level[:3, :3], T_level[:3, 3] = Rz[best], t[best]
        L = np.eye(4)
        L[:3, :3] = self._R_level
        return L.T @ T_level @ L  # level frame -> map frame
