"""Rooms that repeat one another: where else in a building the view of a pose may be seen again.

Buildings repeat rooms (offices along a corridor, hotel rooms, classrooms), and a view of one may be seen, the
same or nearly, in each copy. The graph match finds a copy only when the frame's objects rank it within the tie
margin, and a copy missing a chair the frame does not see, or with a different neighbour, may rank lower: then
the answer is `ok` in one room while another shows the same, or the room that shows it better is never looked
at. So the map is asked directly: two rooms whose objects (classes and positions) coincide under one turn about
up and a shift are copies, and the pose of a view in one room, moved by that transform, is the same view in the
other. What the other room really shows there is then a render away (`field_view.py`).

Written here: the object layouts are matched by a RANSAC over pairs of same-class objects (no library matches
small labelled point sets under a 4-DoF transform), a compiled loop over every pair's transform.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
from numba import njit
from scipy.spatial import ConvexHull, QhullError

from ..geometry import rotation_between
from .match import MapGraph
from .score import DistanceField, score_poses

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
# Rooms with fewer objects than that (a scan without labels or CAD models: a composed Replica office) are copies
# when their boxes agree, each taken along its own walls (the least-area rectangle about its points seen from
# above), one turned by a quarter turn of the other's, within BOX_TOLERANCE_M along each axis, and a sample of the
# first room's own points, so turned and shifted, lies on the building's surfaces (`score.score_poses` at least
# SHAPE_MIN_SCORE): a repeated room of bare walls is as repeatable as one with furniture (two copies of Replica
# office0 in a 4-room building had a view answered `ok` in the wrong one, 5.6 m off, confidence 0.94). Along its own
# walls, not the map's axes: in a building whose rooms are turned by any angle, six copies of office0 taken along
# the map's axes were no copies, and 22 of the 60 views they repeat were answered without the true room.
BOX_TOLERANCE_M = 0.1
SHAPE_POINTS = 2000
SHAPE_MIN_SCORE = 0.9
# Two rooms whose floors lie this far apart or more along up (a storey, or a step) are compared, and moved onto
# each other, with that shift along up; closer floors are one floor measured twice (a scan's floor placed in two
# rooms of one storey was measured 0.4 mm apart), and their rooms keep their heights.
FLOOR_STEP_M = 0.1


class RoomTwins:
    """For each region of a building, the other regions that repeat it and the transform between them.

    graph : the site's graph; node_region : (k,) region index of each node (-1 none); up : the map's unit up.
    floors : (r,) each region's floor height along up (NaN: not known), or None: rooms on another storey, or a step
    up or down (FLOOR_STEP_M), repeat a room with that shift along up (a room straight above its copy).
    `of(a)` : [(b, T_b_a)] with T_b_a (4, 4) moving region a's content onto region b's (map frame), made on first
    use, or by `warm`, and kept (a row of a 100-room building costs a few milliseconds).
    For rooms with too few objects to match (`shape`): field, the building's distance field; sample(r) -> (m, 3)
    points of region r's own (map frame), read on first use.
    """

    def __init__(self, graph: MapGraph, node_region: np.ndarray, up: np.ndarray, regions: int, *,
                 floors: np.ndarray | None = None, field: DistanceField | None = None,
                 sample: Callable[[int], np.ndarray] | None = None) -> None:
        R_level = rotation_between(np.asarray(up, dtype=np.float64), np.array([0.0, 0.0, 1.0]))
        self._R_level = R_level  # map -> level frame (z along up)
        self._level = graph.centroid @ R_level.T
        self._cls = graph.cls
        self._nodes = [np.flatnonzero(node_region == r) for r in range(regions)]
        # Each region's nodes in one row, -1 after them: the nodes of many copies are gathered at once (`carry_all`).
        self._rows = np.full((regions, max([len(n) for n in self._nodes], default=0)), -1, dtype=np.int64)
        for r, n in enumerate(self._nodes):
            self._rows[r, :len(n)] = n
        self._found: dict[int, list[tuple[int, np.ndarray]]] = {}
        self._floors = np.full(regions, np.nan) if floors is None else np.asarray(floors, dtype=np.float64)
        # Shapes are compared seen from above along z: only where up is z (a composed building).
        z_up = bool(np.dot(up, [0.0, 0.0, 1.0]) > 1.0 - 1e-6)
        self._field, self._sample = (field, sample) if z_up else (None, None)
        self._samples: dict[int, np.ndarray] = {}  # each region's sample, read once for all the rooms it is tried on
        self._boxes: dict[int, _WallBox | None] = {}  # and its box along its own walls

    def of(self, a: int) -> list[tuple[int, np.ndarray]]:
        if a not in self._found:
            self._found[a] = [(b, T) for b in range(len(self._nodes)) if b != a
                              for T in [self._pair(a, b)] if T is not None]
        return self._found[a]

    def warm(self, budget_s: float) -> int:
        """Make the rows of the regions, first to last, until budget_s seconds have passed (the row under way is
        finished); the others are made on first use as before. Returns how many rows are made by then. Each row is what
        `of` makes on first use: the answers are the same, and a worker's first frames do not pay for them (a
        100-room building's 100 rows take 0.3 s; made on use they were 2 ms a frame of its benchmark)."""
        start = time.perf_counter()
        for a in range(len(self._nodes)):
            if time.perf_counter() - start >= budget_s:
                break
            self.of(a)
        return len(self._found)

    def one_of_each(self) -> list[int]:
        """Regions that between them stand for every region, each region one of them or a copy of one (`of`),
        lowest index first. Greedy: the region with the most copies not yet stood for first, the lowest index among
        equals. Every region's row is made (`warm` makes most of them: 0.3 s at 100 rooms)."""
        copies = [{b for b, _ in self.of(a)} for a in range(len(self._nodes))]
        left, chosen = set(range(len(self._nodes))), []
        while left:
            a = max(left, key=lambda r: (len(left & copies[r]), -r))
            chosen.append(a)
            left -= {a} | copies[a]
        return sorted(chosen)

    def carry_all(self, nodes: np.ndarray, copies: list[tuple[int, np.ndarray]]) -> np.ndarray:
        """(len(copies), len(nodes)) graph node indices (-1: none) of `nodes` moved by each copy's T_ba onto their
        counterparts in its region b: the nearest node of b of the same class within MATCH_TOLERANCE_M, else -1 (an
        object that copy lacks). All copies at once: the twin check carries a pose's objects into every copy of its
        room (99 at 100 rooms)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        out = np.full((len(copies), len(nodes)), -1, dtype=np.int64)
        live = np.flatnonzero(nodes >= 0)
        if not len(copies) or not len(live) or self._rows.shape[1] == 0:
            return out
        T = np.array([T_ba for _, T_ba in copies], dtype=np.float64)
        L = self._R_level
        src = self._level[nodes[live]] @ L  # (k, 3) back in the map frame
        moved = (np.einsum("cij,kj->cki", T[:, :3, :3], src) + T[:, None, :3, 3]) @ L.T  # (c, k, 3) level frame
        rows = self._rows[[b for b, _ in copies]]  # (c, m) each copy's nodes, -1 after them
        d = np.linalg.norm(self._level[rows][:, None] - moved[:, :, None], axis=3)  # (c, k, m)
        d[(rows[:, None, :] < 0) | (self._cls[rows][:, None, :] != self._cls[nodes[live]][None, :, None])] = np.inf
        nearest = np.argmin(d, axis=2)  # (c, k)
        found = np.take_along_axis(d, nearest[..., None], axis=2)[..., 0] < MATCH_TOLERANCE_M
        out[:, live] = np.where(found, np.take_along_axis(rows, nearest, axis=1), -1)
        return out

    def _pair(self, a: int, b: int) -> np.ndarray | None:
        """T (4, 4, map frame) taking region a onto region b, or None when they are no copies: by their objects,
        or by their shapes when either has too few objects to tell."""
        na, nb = self._nodes[a], self._nodes[b]
        if min(len(na), len(nb)) >= MIN_SHARED:
            return self._transform(na, nb, self._rise(a, b))
        return self._shape_transform(a, b) if self._field is not None else None

    def _rise(self, a: int, b: int) -> float:
        """How far region b's floor lies above region a's along up: 0 when either is not known or they are less
        than FLOOR_STEP_M apart."""
        rise = float(self._floors[b] - self._floors[a])
        return rise if np.isfinite(rise) and abs(rise) >= FLOOR_STEP_M else 0.0

    def _shape_transform(self, a: int, b: int) -> np.ndarray | None:
        """T (4, 4, map frame): region a's box along its own walls turned about z onto region b's (within
        BOX_TOLERANCE_M an axis, by one of the four turns that lay a's walls on b's), a's centroid onto b's, the turn
        under which a's own points lie best on the building's surfaces, if they do (SHAPE_MIN_SCORE); else None."""
        box_a, box_b = self._wall_box(a), self._wall_box(b)
        if box_a is None or box_b is None:
            return None
        poses = []
        for k in range(4):
            if np.any(np.abs(box_a.size[[k % 2, 1 - k % 2, 2]] - box_b.size) > BOX_TOLERANCE_M):
                continue
            yaw = box_b.yaw - box_a.yaw + k * np.pi / 2
            T = np.eye(4)
            T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            T[:2, 3] = box_b.centroid[:2] - T[:2, :2] @ box_a.centroid[:2]
            T[2, 3] = self._rise(a, b)  # (z is up here)
            poses.append(T)
        if not poses:
            return None
        poses = np.array(poses)
        scores = score_poses(self._field, self._sample_of(a), poses[:, :3, :3], poses[:, :3, 3])
        best = int(np.argmax(scores))
        return poses[best] if scores[best] >= SHAPE_MIN_SCORE else None

    def _sample_of(self, r: int) -> np.ndarray:
        if r not in self._samples:
            self._samples[r] = self._sample(r)
        return self._samples[r]

    def _wall_box(self, r: int) -> "_WallBox | None":
        if r not in self._boxes:
            self._boxes[r] = _WallBox.of(self._sample_of(r))
        return self._boxes[r]

    def _transform(self, na: np.ndarray, nb: np.ndarray, rise: float) -> np.ndarray | None:
        """T (4, 4, map frame) taking the objects `na` onto the objects `nb` (at least MIN_SHARED each, `_pair`),
        whose room's floor lies `rise` above theirs, or None when they are no copies."""
        raised = self._level[na] + np.array([0.0, 0.0, rise])
        inliers, yaw, tx, ty = _best_turn(raised, self._level[nb], self._cls[na], self._cls[nb],
                                          MIN_PAIR_M, PAIR_TOLERANCE_M, MATCH_TOLERANCE_M)
        if inliers < max(MIN_SHARED, MIN_SHARED_SHARE * min(len(na), len(nb))):
            return None
        c, s = np.cos(yaw), np.sin(yaw)
        T_level = np.eye(4)
        T_level[:2, :2] = [[c, -s], [s, c]]
        T_level[:3, 3] = tx, ty, rise
        L = np.eye(4)
        L[:3, :3] = self._R_level
        return L.T @ T_level @ L  # level frame -> map frame


class _WallBox:
    """A room's points seen from above (z up), in the box along its own walls: the least-area rectangle about them.

    yaw : the turn about z (radians, in [0, π/2)) of the rectangle's first side from the map's x axis; size : (3,)
    its sides along that side, across it, and the points' spread in z; centroid : (3,) the points' mean (map frame).
    The least-area rectangle has a side on an edge of the points' convex hull (Freeman and Shapira 1975), so each
    edge's direction is tried (written here: scipy gives the hull, and no library at hand the rectangle).
    """

    def __init__(self, yaw: float, size: np.ndarray, centroid: np.ndarray) -> None:
        self.yaw, self.size, self.centroid = yaw, size, centroid

    @classmethod
    def of(cls, xyz: np.ndarray) -> "_WallBox | None":
        """The box of (m, 3) points, or None when they cover no area seen from above."""
        try:
            flat = xyz[ConvexHull(xyz[:, :2]).vertices, :2]
        except (QhullError, ValueError):  # fewer than three points, or all on one line
            return None
        edges = np.roll(flat, -1, axis=0) - flat
        yaws = np.arctan2(edges[:, 1], edges[:, 0]) % (np.pi / 2)
        along = flat @ np.stack([np.cos(yaws), np.sin(yaws)])  # (v, e): each hull vertex along each edge's direction
        across = flat @ np.stack([-np.sin(yaws), np.cos(yaws)])
        best = int(np.argmin(np.ptp(along, axis=0) * np.ptp(across, axis=0)))
        size = np.array([np.ptp(along[:, best]), np.ptp(across[:, best]), np.ptp(xyz[:, 2])])
        return cls(float(yaws[best]), size, xyz.mean(axis=0))


def warm() -> None:
    """Compile (or load from numba's cache) the RANSAC's loop (`field_kernels.warm`)."""
    p, c = np.zeros((1, 3)), np.zeros(1, dtype=np.int64)
    _best_turn(p, p, c, c, MIN_PAIR_M, PAIR_TOLERANCE_M, MATCH_TOLERANCE_M)


@njit(cache=True, nogil=True)
def _best_turn(pa, pb, ca, cb, min_pair_m, pair_tolerance_m, match_tolerance_m):
    """The RANSAC: each pair of a's objects at least min_pair_m apart, put on each ordered pair of b's objects of
    the same classes whose length agrees within pair_tolerance_m, fixes a turn about up (level frame, z up) and a
    level shift. -> (inliers, yaw, tx, ty): the most of a's objects any of them brings within match_tolerance_m of
    one of b's of their class (-1 when no pair fits: what tells copies), and the transform that lays a's objects
    closest onto b's: the largest sum over them of max(0, 1 − (d / (match_tolerance_m / 2))²), d the distance to
    the nearest of b's of their class (then the first). A copy with a chair pushed aside or a table turned keeps
    its other objects where they were: a transform through them lays those exactly and the moved one nowhere, and
    one tilted a few degrees between them all brings every object within match_tolerance_m (the most inliers:
    copies placed 8 cm and 3.5° off in a building with moved furniture). Compiled: a room's row of a 100-room
    building is 99 of these, and as numpy passes over small arrays each cost 0.2 ms (23 ms of a 100-room frame
    that comes to a new room)."""
    best_inliers, best_fit = -1, -1.0
    best_yaw = best_tx = best_ty = 0.0
    tight = match_tolerance_m / 2.0
    for i in range(len(pa)):
        for j in range(i + 1, len(pa)):
            ax, ay = pa[j, 0] - pa[i, 0], pa[j, 1] - pa[i, 1]
            da = math.sqrt(ax * ax + ay * ay)
            if da < min_pair_m:
                continue
            for k in range(len(pb)):
                if cb[k] != ca[i]:
                    continue
                for m in range(len(pb)):
                    if m == k or cb[m] != ca[j]:
                        continue
                    bx, by = pb[m, 0] - pb[k, 0], pb[m, 1] - pb[k, 1]
                    if abs(da - math.sqrt(bx * bx + by * by)) >= pair_tolerance_m:
                        continue
                    yaw = math.atan2(by, bx) - math.atan2(ay, ax)
                    c, s = math.cos(yaw), math.sin(yaw)
                    tx = pb[k, 0] - (c * pa[i, 0] - s * pa[i, 1])
                    ty = pb[k, 1] - (s * pa[i, 0] + c * pa[i, 1])
                    inliers, fit = 0, 0.0
                    for u in range(len(pa)):
                        mx, my = c * pa[u, 0] - s * pa[u, 1] + tx, s * pa[u, 0] + c * pa[u, 1] + ty
                        near = np.inf
                        for v in range(len(pb)):
                            if cb[v] == ca[u]:
                                near = min(near, math.sqrt((mx - pb[v, 0]) ** 2 + (my - pb[v, 1]) ** 2
                                                           + (pa[u, 2] - pb[v, 2]) ** 2))
                        if near < match_tolerance_m:
                            inliers += 1
                        if near < tight:
                            fit += 1.0 - (near / tight) ** 2
                    best_inliers = max(best_inliers, inliers)
                    if fit > best_fit:
                        best_fit, best_yaw, best_tx, best_ty = fit, yaw, tx, ty
    return best_inliers, best_yaw, best_tx, best_ty
