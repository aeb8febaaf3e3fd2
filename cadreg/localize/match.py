"""Coarse graph matching (paper §2.4, eq. 5–9), done so that edge directions are only compared under a rotation.

Hypotheses come from rotation-invariant evidence (classes, centroid distances): with a known up direction a pair
of scan objects matched to a pair of map nodes fixes yaw and translation, a single object gives a yaw sweep; with
no up direction, triples of objects give a 6-DoF pose by Kabsch (eq. 9). Every hypothesis is then scored by the
paper's Sim = α·S_V + β·S_E (eq. 6–8) with scan edge directions rotated into the map by the hypothesis, and by a
geometric check of the frame points against the map's distance field (`score.py`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations, permutations
from typing import TYPE_CHECKING

import numpy as np
from numba import njit
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry import kabsch_many
from . import field_kernels

# Node pairs this far apart at most are indexed by distance (`MapGraph.pairs_of_classes`); a frame's objects
# farther apart than this (less the pair tolerance) are matched against every node pair of their classes.
PAIR_REACH_M = 8.0

if TYPE_CHECKING:  # the site bundle pulls in the whole site build; the localizer is handed a loaded Site
    from ..site.bundle import Site


@dataclass
class MapGraph:
    """The site's semantic graph as arrays, map frame.

    ids : node ids (str). cls : (k,) int class index (into Site.classes). centroid : (k, 3) float64, metres.
    extent : (k, 3) float64 box extent (its own axes), metres; zeros when unknown. box_center : (k, 3) and box_R :
    (k, 3, 3) (columns the box axes) of those boxes, map frame; empty when unknown (then no point is in a box).
    """

    ids: list[str]
    cls: np.ndarray
    centroid: np.ndarray
    extent: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    top: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (k,) highest point of the box along up, metres
    box_center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    box_R: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    _by_class: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _near: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _pairs: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def pairs_of_classes(self, cls_a: int, cls_b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ordered pairs (a, b) of distinct nodes of classes cls_a and cls_b at most PAIR_REACH_M apart, by
        distance: (a, b, distance) arrays, made on first use. A frame's pair of objects of those classes at d is
        matched by the slice within the tolerance of d (`gravity_hypotheses`): comparing d with every node pair of
        the two classes (250 k for a 100-room building's chairs) took 3 ms a pair of objects, 150 ms for a frame
        of 17 objects. Made from the node pairs within the reach (a KD-tree's), not from all pairs of the
        classes: those grow with the square of the building (a 1000-room building's chairs: 25 M)."""
        key = (int(cls_a), int(cls_b))
        if key not in self._pairs:
            if self._near is None:
                self._near = (cKDTree(self.centroid).query_pairs(PAIR_REACH_M, output_type="ndarray")
                              if len(self.ids) > 1 else np.zeros((0, 2), dtype=np.int64))
            i, j = self._near[:, 0], self._near[:, 1]
            forward = (self.cls[i] == cls_a) & (self.cls[j] == cls_b)
            backward = (self.cls[j] == cls_a) & (self.cls[i] == cls_b)
            a = np.concatenate([i[forward], j[backward]]).astype(np.int64)
            b = np.concatenate([j[forward], i[backward]]).astype(np.int64)
            d = np.linalg.norm(self.centroid[a] - self.centroid[b], axis=-1)
            order = np.argsort(d, kind="stable")
            self._pairs[key] = (a[order], b[order], d[order])
        return self._pairs[key]

    def pairs_at(self, cls_a: int, cls_b: int, d: float, tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The ordered pairs (a, b) of distinct nodes of classes cls_a and cls_b whose distance is within
        tolerance_m of d (strictly), row-major over (a, b): for objects farther apart than the index reaches
        (`pairs_of_classes`), from a ball query of cls_b's KD-tree around each node of cls_a."""
        nodes_a, _ = self._class_tree(cls_a)
        nodes_b, tree = self._class_tree(cls_b)
        if tree is None or len(nodes_a) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        found = tree.query_ball_point(self.centroid[nodes_a], d + tolerance_m)
        a = np.repeat(nodes_a, [len(f) for f in found])
        b = nodes_b[np.concatenate([np.sort(f) for f in found]).astype(np.int64)] if len(a) else a
        keep = (np.abs(np.linalg.norm(self.centroid[a] - self.centroid[b], axis=-1) - d) < tolerance_m) & (a != b)
        return a[keep], b[keep]

    def _class_tree(self, cls: int) -> tuple[np.ndarray, cKDTree | None]:
        """The nodes of class `cls` and a KD-tree of their centroids (None when there are none), made on first use."""
        if cls not in self._by_class:
            nodes = np.flatnonzero(self.cls == cls)
            self._by_class[cls] = (nodes, cKDTree(self.centroid[nodes]) if len(nodes) else None)
        return self._by_class[cls]

    def nearest_of_class(self, xyz: np.ndarray, cls: int, radius_m: float) -> np.ndarray:
        """(m,) index of the node of class `cls` nearest each point of xyz ((m, 3), map frame), -1 where none lies
        within radius_m. A KD-tree per class, made on first use: a building's graph holds hundreds of nodes of a
        class, and the distances of every hypothesis's objects to every node (h x n x k) took 130 ms a frame of a
        100-room site."""
        nodes, tree = self._class_tree(cls)
        if tree is None:
            return np.full(len(xyz), -1, dtype=np.int64)
        d, k = tree.query(xyz, distance_upper_bound=radius_m)  # none within: d = inf, k = len(nodes)
        return np.where(d < radius_m, nodes[np.minimum(k, len(nodes) - 1)], -1)

    def in_box_of_class(self, xyz: np.ndarray, cls: int, margin_m: float) -> np.ndarray:
        """(m,) bool: whether each point of xyz ((m, 3), map frame) lies in the box of a node of class `cls`, grown
        by margin_m on every side. The nodes looked at are those whose centroids (the class's KD-tree) lie near enough
        for any of their boxes to hold the point: the centroid's distance from its box's centre plus the box's
        half-diagonal, grown by the margin's diagonal, the class's largest."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        inside = np.zeros(len(xyz), dtype=bool)
        nodes, tree = self._class_tree(cls)
        if tree is None or len(self.box_center) == 0:
            return inside
        reach = float(np.max(np.linalg.norm(self.centroid[nodes] - self.box_center[nodes], axis=1)
                             + 0.5 * np.linalg.norm(self.extent[nodes], axis=1))) + np.sqrt(3.0) * margin_m
        near = tree.query_ball_point(xyz, reach)
        point = np.repeat(np.arange(len(xyz)), [len(n) for n in near])
        if not len(point):
            return inside
        node = nodes[np.concatenate(near).astype(np.int64)]
        # each point in each near box's own axes: Rᵀ (p - c), as `site.objects.points_in_box` for many boxes at once
        local = np.einsum("kji,kj->ki", self.box_R[node], xyz[point] - self.box_center[node])
        hit = np.all(np.abs(local) <= 0.5 * self.extent[node] + margin_m, axis=1)
        inside[point[hit]] = True
        return inside

    @classmethod
    def from_site(cls, site: Site, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> "MapGraph":
        """The nodes of the site's graph whose class the site knows; `top` along the unit vector `up`."""
        names = list(site.classes)
        nodes = [n for n in site.graph.nodes if n.cls in names]
        # Highest point of each oriented box along up: its centre plus half of each extent projected on up.
        tops = [float(n.box_center @ up + 0.5 * np.abs(n.box_R.T @ up) @ n.box_extent) for n in nodes]
        return cls(
            [str(n.id) for n in nodes],
            np.array([names.index(n.cls) for n in nodes], dtype=np.int64),
            np.array([n.centroid for n in nodes], dtype=float).reshape(-1, 3),
            np.array([n.box_extent for n in nodes], dtype=float).reshape(-1, 3),
            np.array(tops, dtype=float),
            np.array([n.box_center for n in nodes], dtype=float).reshape(-1, 3),
            np.array([n.box_R for n in nodes], dtype=float).reshape(-1, 3, 3),
        )


@dataclass
class Hypotheses:
    """A batch of pose hypotheses T_map_camera = [R | t].

    R_table : (h, 3, 3) rotations, one a hypothesis; or, with rot (h,) int, (u, 3, 3) rotations the hypotheses
    index (`R` makes the (h, 3, 3) on first read). A yaw sweep's hypotheses share its few dozen rotations, and a
    100-room building's frame makes 10-450 k of them: a (3, 3) each was most of what they cost to make, for the few
    hundred that pass the screen to use. t : (h, 3) float64. seed : (h, 2) int, the (scan object, map node) pair that
    generated each (map node -1 for fallback seeds). Scores are filled by `score_graph` / the geometric check.
    """

    R_table: np.ndarray
    t: np.ndarray
    seed: np.ndarray
    s_v: np.ndarray = field(default_factory=lambda: np.zeros(0))
    s_e: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sim: np.ndarray = field(default_factory=lambda: np.zeros(0))
    geometric: np.ndarray = field(default_factory=lambda: np.zeros(0))
    assignment: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    rot: np.ndarray | None = None

    @property
    def R(self) -> np.ndarray:
        """(h, 3, 3) rotation of each hypothesis (made from the table on first read, then held)."""
        if self.rot is not None:
            self.R_table, self.rot = self.R_table[self.rot], None
        return self.R_table

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def empty(cls) -> "Hypotheses":
        return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 2), dtype=np.int64))

    @classmethod
    def of_pose(cls, T_map_camera: np.ndarray) -> "Hypotheses":
        """One hypothesis from a pose that no graph seed produced (a prior, an FPFH + RANSAC pose)."""
        return cls(T_map_camera[None, :3, :3].copy(), T_map_camera[None, :3, 3].copy(), np.array([[-1, -1]]))

    @classmethod
    def concat(cls, parts: list["Hypotheses"]) -> "Hypotheses":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        t, seed = np.concatenate([p.t for p in parts]), np.concatenate([p.seed for p in parts])
        if all(p.rot is None for p in parts):
            return cls(np.concatenate([p.R_table for p in parts]), t, seed)
        # One table of the parts' rotations: parts that index one array (a sweep's objects and offsets index its
        # yaws) share its place in it, and each part's indices move to where its array starts.
        blocks: list[np.ndarray] = []
        start_of: dict[int, int] = {}
        rot, size = [], 0
        for p in parts:
            if id(p.R_table) not in start_of:
                start_of[id(p.R_table)], size = size, size + len(p.R_table)
                blocks.append(p.R_table)
            rot.append((np.arange(len(p)) if p.rot is None else p.rot) + start_of[id(p.R_table)])
        return cls(np.concatenate(blocks), t, seed, rot=np.concatenate(rot))

    def take(self, index: np.ndarray) -> "Hypotheses":
        def pick(a: np.ndarray) -> np.ndarray:
            return a[index] if len(a) == len(self) else a
        if self.rot is None:
            R_table, rot = self.R_table[index], None
        else:
            R_table, rot = self.R_table, self.rot[index]
        return Hypotheses(R_table, self.t[index], self.seed[index], pick(self.s_v), pick(self.s_e),
                          pick(self.sim), pick(self.geometric), pick(self.assignment), rot=rot)

    def rotation(self, i: int) -> np.ndarray:
        """(3, 3) rotation of hypothesis i (from the table: no (h, 3, 3) is made)."""
        return self.R_table[i if self.rot is None else self.rot[i]]

    def T(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.rotation(i)
        T[:3, 3] = self.t[i]
        return T


def yaw_rotations(up: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """(h,) angles -> (h, 3, 3) rotations about the unit axis `up`."""
    return Rotation.from_rotvec(np.outer(yaw_rad, up)).as_matrix().reshape(-1, 3, 3)


def _horizontal_basis(up: np.ndarray) -> np.ndarray:
    """(3, 2): unit axes e1, e2 across the unit `up`, e2 = up × e1 (so that e1 × e2 = up)."""
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 1e-3:
        e1 = np.cross(up, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)], axis=1)


def _horizontal_grid(up: np.ndarray, reach_m: float, step_m: float) -> np.ndarray:
    """(o, 3) non-zero offsets orthogonal to `up` on a square grid of `step_m` within a disc of `reach_m`."""
    n = int(np.floor(reach_m / step_m))
    if n < 1:
        return np.zeros((0, 3))
    e1, e2 = _horizontal_basis(up).T
    a, b = np.meshgrid(np.arange(-n, n + 1) * step_m, np.arange(-n, n + 1) * step_m, indexing="ij")
    a, b = a.ravel(), b.ravel()
    keep = (a ** 2 + b ** 2 <= reach_m ** 2 + 1e-9) & ((a != 0) | (b != 0))
    return np.outer(a[keep], e1) + np.outer(b[keep], e2)


def _offset_hypotheses(i: int, nodes: np.ndarray, graph: MapGraph, Rc: np.ndarray, RL: np.ndarray,
                       yaw_index: np.ndarray, grids: dict[float, np.ndarray], *, up: np.ndarray, step_m: float,
                       max_offset_m: float) -> Hypotheses:
    """Scan object i's single-object hypotheses at horizontal offsets of its centroid (`gravity_hypotheses`), node
    by node in the order of `nodes`, each node's yaws (rows of Rc, (y, 3): the object's centroid turned by each yaw)
    by its offsets: those of its reach, half its largest horizontal extent (at most max_offset_m; `grids` holds
    each reach's offsets once made). The nodes of one reach are posed in one pass (a building's hundreds of nodes
    of a class, one by one, took 3 ms of a 100-room frame)."""
    half = 0.5 * graph.extent[nodes][:, :2].max(axis=1) if len(graph.extent) else np.zeros(len(nodes))
    reach = np.minimum(max_offset_m, half)
    blocks: list[np.ndarray | None] = [None] * len(nodes)
    for r in np.unique(reach):
        if float(r) not in grids:
            grids[float(r)] = _horizontal_grid(up, float(r), step_m)
        offsets = grids[float(r)]
        if len(offsets) == 0:
            continue
        at = np.flatnonzero(reach == r)
        tk = (graph.centroid[nodes[at]][:, None, :] - Rc[None])[:, :, None, :] + offsets[None, None]  # (k, y, o, 3)
        for n, block in zip(at, tk.reshape(len(at), -1, 3)):
            blocks[n] = block
    kept = [n for n, b in enumerate(blocks) if b is not None]
    if not kept:
        return Hypotheses.empty()
    rows = np.array([len(blocks[n]) for n in kept])
    seed = np.stack([np.full(rows.sum(), i), np.repeat(nodes[kept], rows)], axis=1)
    rot = np.concatenate([np.repeat(yaw_index, len(blocks[n]) // len(yaw_index)) for n in kept])
    return Hypotheses(RL, np.concatenate([blocks[n] for n in kept]), seed, rot=rot)


def _horizontal(v: np.ndarray, up: np.ndarray) -> np.ndarray:
    return v - np.outer(v @ up, up) if v.ndim == 2 else v - (v @ up) * up


def _pair_hypotheses(c: np.ndarray, node_centroid: np.ndarray, i: np.ndarray, j: np.ndarray, a: np.ndarray,
                     b: np.ndarray, *, up: np.ndarray, R_level: np.ndarray) -> Hypotheses:
    """Scan objects i, j (levelled camera frame `c`) matched to map nodes a, b, all (p,): the yaw about `up` that
    turns the objects' horizontal direction onto the nodes', and the translation that puts the objects' midpoint
    on the nodes'. seed : (i, a)."""
    E = _horizontal_basis(up)  # coordinates across up, in which the yaw is an angle in the plane
    hs, hm = (c[j] - c[i]) @ E, (node_centroid[b] - node_centroid[a]) @ E
    yaw = np.arctan2(hs[:, 0] * hm[:, 1] - hs[:, 1] * hm[:, 0], np.einsum("ij,ij->i", hs, hm))
    R = yaw_rotations(up, yaw)
    t = 0.5 * (node_centroid[a] + node_centroid[b]) - np.einsum("hij,hj->hi", R, 0.5 * (c[i] + c[j]))
    return Hypotheses(R @ R_level, t, np.stack([i, a], axis=1))


def gravity_hypotheses(scan_centroid: np.ndarray, scan_cls: np.ndarray, graph: MapGraph, *, R_level: np.ndarray,
                       up: np.ndarray, camera_height_m: float | np.ndarray | None, yaw_step_deg: float = 10.0,
                       pair_tolerance_m: float = 0.4, min_pair_horizontal_m: float = 0.3,
                       offset_step_m: float = 0.0, max_offset_m: float = 0.5,
                       scan_top: np.ndarray | None = None) -> Hypotheses:
    """4-DoF hypotheses (yaw about `up` + translation) from single objects and object pairs.

    scan_centroid : (n, 3) colour-camera frame; scan_cls : (n,) int. R_level : (3, 3) rotation taking the camera's
    up onto the map's `up` (the unknown yaw is about `up`). camera_height_m : the camera's coordinate along `up`
    when a floor is seen (the map's floor height added to its height above it; (k,) per graph node: the floor of
    the node's room), else None (height from centroids).
    offset_step_m > 0: single-object hypotheses also try horizontal offsets of the centroid on a grid of this
    step, up to half the node's largest extent (at most max_offset_m): a partly seen large object (a 2 m
    whiteboard) has its visible centroid far from the node's.
    scan_top : (n,) highest point of each scan object along up (levelled camera frame). Without a floor, the
    camera height comes from the centroids, and again from the object tops (a view from above sees the top
    of a chair but only part of its legs: its visible centroid sits high, its top does not move).
    """
    c = scan_centroid @ R_level.T
    parts: list[Hypotheses] = []
    # Single objects: the object's centroid fixes the translation for each yaw of a sweep.
    yaws = np.radians(np.arange(0.0, 360.0, yaw_step_deg))
    Ryaw = yaw_rotations(up, yaws)
    RL = Ryaw @ R_level  # each yaw's rotation of the camera, once: the single objects' hypotheses index them
    yaw_index = np.arange(len(yaws))
    grids: dict[float, np.ndarray] = {}  # offsets by reach: a building's nodes share a few
    for i in range(len(c)):
        nodes = np.flatnonzero(graph.cls == scan_cls[i])
        if len(nodes) == 0:
            continue
        Rc = Ryaw @ c[i]  # (y, 3)
        t = graph.centroid[nodes][:, None, :] - Rc[None, :, :]  # (k, y, 3)
        seed = np.stack(np.broadcast_arrays(np.full((len(nodes), len(yaws)), i), nodes[:, None]), axis=-1)
        parts.append(Hypotheses(RL, t.reshape(-1, 3), seed.reshape(-1, 2), rot=np.tile(yaw_index, len(nodes))))
        if offset_step_m > 0:
            parts.append(_offset_hypotheses(i, nodes, graph, Rc, RL, yaw_index, grids, up=up,
                                            step_m=offset_step_m, max_offset_m=max_offset_m))
    # Pairs: the horizontal direction between two objects fixes the yaw. The map's node pairs of every pair of
    # objects are gathered first and posed in one pass (`_pair_hypotheses`): a building's frame has a few hundred
    # pairs of objects, and posing each pair's nodes apart made this 16 ms of a 100-room frame, 12 ms now.
    pair_i, pair_j, pair_a, pair_b = [], [], [], []
    for i, j in permutations(range(len(c)), 2):
        if i > j:
            continue
        ds = c[j] - c[i]
        if np.linalg.norm(_horizontal(ds, up)) < min_pair_horizontal_m:
            continue
        # Every pair of distinct nodes of the two classes as far apart as the two objects (row-major over them)
        d = float(np.linalg.norm(ds))
        if d + pair_tolerance_m <= PAIR_REACH_M:
            A, B, dm = graph.pairs_of_classes(scan_cls[i], scan_cls[j])
            within = slice(np.searchsorted(dm, d - pair_tolerance_m, side="right"),
                           np.searchsorted(dm, d + pair_tolerance_m, side="left"))
            A, B = A[within], B[within]
            row_major = np.lexsort((B, A))
            A, B = A[row_major], B[row_major]
        else:
            A, B = graph.pairs_at(scan_cls[i], scan_cls[j], d, pair_tolerance_m)
        if len(A) == 0:
            continue
        pair_i.append(np.full(len(A), i))
        pair_j.append(np.full(len(A), j))
        pair_a.append(A)
        pair_b.append(B)
    if pair_a:
        parts.append(_pair_hypotheses(c, graph.centroid, np.concatenate(pair_i), np.concatenate(pair_j),
                                      np.concatenate(pair_a), np.concatenate(pair_b), up=up, R_level=R_level))
    hyp = Hypotheses.concat(parts)
    if not len(hyp):
        return hyp
    if camera_height_m is not None:
        # The camera centre is t: put it at the height the floor says, keep its horizontal position. Per node: the
        # camera's height over the floor under the seed's map node.
        height = np.broadcast_to(np.asarray(camera_height_m, dtype=np.float64), (len(graph.ids),))[hyp.seed[:, 1]]
        hyp.t -= np.outer(hyp.t @ up, up)  # in place, in the order t - (t·up) up + height up takes
        hyp.t += np.outer(height, up)
    elif scan_top is not None and len(graph.top):
        h_top = graph.top[hyp.seed[:, 1]] - scan_top[hyp.seed[:, 0]]
        t_top = hyp.t - np.outer(hyp.t @ up, up) + np.outer(h_top, up)
        hyp = Hypotheses(hyp.R_table, np.concatenate([hyp.t, t_top]), np.concatenate([hyp.seed, hyp.seed]),
                         rot=np.tile(np.arange(len(hyp)) if hyp.rot is None else hyp.rot, 2))
    return hyp


def kabsch_hypotheses(scan_centroid: np.ndarray, scan_cls: np.ndarray, graph: MapGraph, *,
                      pair_tolerance_m: float = 0.4, max_hypotheses: int = 5000) -> Hypotheses:
    """6-DoF hypotheses from triples of scan objects matched to triples of map nodes (eq. 9), no gravity needed.

    At most `max_hypotheses`, in the order of the scan's triples and then of the map's node ids. The map triples
    whose pairwise distances agree with the scan triple's (within pair_tolerance_m) are found with array
    operations and fitted in one batched SVD: a building's graph has a hundred nodes of a class, and the loops
    over them (with a cap that only ended the innermost one) took 27 s for one frame of a 100-room site."""
    D = np.linalg.norm(graph.centroid[:, None] - graph.centroid[None], axis=-1)
    Rs, ts, seeds, total = [], [], [], 0
    for tri in combinations(range(len(scan_centroid)), 3):
        if total >= max_hypotheses:
            break
        P = scan_centroid[list(tri)]
        dP = np.linalg.norm(P[:, None] - P[None], axis=-1)
        A, B, C = (np.flatnonzero(graph.cls == scan_cls[k]) for k in tri)
        ia, ib = np.nonzero(np.abs(D[np.ix_(A, B)] - dP[0, 1]) <= pair_tolerance_m)
        a, b = A[ia], B[ib]
        a, b = a[a != b], b[a != b]
        fits = ((np.abs(D[a][:, C] - dP[0, 2]) <= pair_tolerance_m) & (np.abs(D[b][:, C] - dP[1, 2]) <= pair_tolerance_m)
                & (C[None] != a[:, None]) & (C[None] != b[:, None]))
        k, ic = np.nonzero(fits)  # pair-major, then c ascending: the order of nested loops over a, b, c
        k, ic = k[:max_hypotheses - total], ic[:max_hypotheses - total]
        if len(k) == 0:
            continue
        Q = graph.centroid[np.stack([a[k], b[k], C[ic]], axis=1)]  # (m, 3, 3) map triples
        R, t = kabsch_many(P, Q)
        Rs.append(R); ts.append(t)
        seeds.append(np.stack([np.full(len(k), tri[0]), a[k]], axis=1))
        total += len(k)
    if not Rs:
        return Hypotheses.empty()
    return Hypotheses(np.concatenate(Rs), np.concatenate(ts), np.concatenate(seeds).astype(np.int64))


def score_graph(hyp: Hypotheses, scan_centroid: np.ndarray, scan_cls: np.ndarray, graph: MapGraph, *,
                match_radius_m: float = 0.6, edge_max_m: float = 1.5, alpha: float = 0.5, beta: float = 0.5) -> None:
    """Fill hyp.s_v, s_e, sim and assignment (paper eq. 6–8, directions compared under each hypothesis).

    S_V: fraction of scan objects that land within `match_radius_m` of a map node of their class.
    S_E: over scan edges (centroids ≤ δ = edge_max_m apart), mean of (1 + cos)/2 between the scan edge direction
    rotated into the map and the direction between the two assigned map nodes (0 when either end is unassigned).
    assignment : (h, n) map node index per scan object, -1 when none.
    """
    h, n = len(hyp), len(scan_centroid)
    if h == 0 or n == 0:
        hyp.s_v = hyp.s_e = hyp.sim = np.zeros(h)
        hyp.assignment = np.full((h, n), -1, dtype=np.int64)
        return
    c_map = np.einsum("hij,nj->hni", hyp.R, scan_centroid) + hyp.t[:, None, :]
    assign = np.full((h, n), -1, dtype=np.int64)
    for c in np.unique(scan_cls):
        objects = np.flatnonzero(scan_cls == c)
        assign[:, objects] = graph.nearest_of_class(c_map[:, objects].reshape(-1, 3), int(c),
                                                    match_radius_m).reshape(h, len(objects))
    s_v = (assign >= 0).mean(axis=1)
    pairs = [(i, j) for i, j in combinations(range(n), 2)
             if np.linalg.norm(scan_centroid[i] - scan_centroid[j]) <= edge_max_m]
    if pairs:
        I, J = np.array(pairs).T
        dir_scan = scan_centroid[J] - scan_centroid[I]
        dir_scan /= np.linalg.norm(dir_scan, axis=1, keepdims=True) + 1e-12
        dir_scan_map = np.einsum("hij,ej->hei", hyp.R, dir_scan)
        a, b = assign[:, I], assign[:, J]
        both = (a >= 0) & (b >= 0) & (a != b)
        dm = graph.centroid[np.maximum(b, 0)] - graph.centroid[np.maximum(a, 0)]
        dm /= np.linalg.norm(dm, axis=-1, keepdims=True) + 1e-12
        cos = np.einsum("hei,hei->he", dir_scan_map, dm)
        s_e = np.where(both, (1.0 + cos) / 2.0, 0.0).mean(axis=1)
        sim = (alpha * s_v + beta * s_e) / max(alpha + beta, 1e-12)
    else:
        s_e = np.zeros(h)
        sim = s_v.copy()
    hyp.s_v, hyp.s_e, hyp.sim, hyp.assignment = s_v, s_e, sim, assign


def distinct_best(R: np.ndarray, t: np.ndarray, order: np.ndarray, *, count: int, min_translation_m: float = 0.25,
                  min_rotation_deg: float = 15.0) -> list[int]:
    """Greedy non-maximum suppression: up to `count` indices from `order` (best first), pairwise distinct poses
    (farther apart than min_translation_m, or turned more than min_rotation_deg)."""
    if count <= 0 or not len(order):
        return []
    # cos of the angle between R_i and R_k is (trace(R_i^T R_k) - 1) / 2, and trace(R_i^T R_k) = sum(R_i * R_k).
    min_trace = 1.0 + 2.0 * np.cos(np.radians(min_rotation_deg))
    kept = _distinct_best(field_kernels.floats(R), field_kernels.floats(t), np.asarray(order, dtype=np.int64), count,
                          min_translation_m ** 2, min_trace)
    return [int(i) for i in kept]


def distinct_pairs(A: np.ndarray, B: np.ndarray, *, min_translation_m: float = 0.25,
                   min_rotation_deg: float = 15.0) -> np.ndarray:
    """A (a, 4, 4), B (b, 4, 4) poses -> (a, b) bool: whether each pair is distinct as `distinct_best` tells it
    (farther apart than min_translation_m, or turned more than min_rotation_deg), every pair at once."""
    d = A[:, None, :3, 3] - B[None, :, :3, 3]
    far = np.einsum("abi,abi->ab", d, d) > min_translation_m ** 2
    trace = np.einsum("aij,bij->ab", A[:, :3, :3], B[:, :3, :3])
    return far | (trace < 1.0 + 2.0 * np.cos(np.radians(min_rotation_deg)))


def best_overall_and_by_group(scores: np.ndarray, group: np.ndarray, *, count: int, per_group: int) -> np.ndarray:
    """Sorted indices of the `count` best scores and of the `per_group` best of each group (group (n,) int: a
    region index, -1 for none; a few thousand values at most), equal scores taken in index order: what sorting
    every score by value, and each group's, would keep, in one pass. A 100-room frame's first look keeps its best
    among 60-80 k graph hypotheses, and the sorts took 8 ms of it. Written by hand: numpy selects the best overall
    (`partition`), not the best of each of many groups at once."""
    scores = np.asarray(scores, dtype=np.float64)
    n = len(scores)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    keep = np.zeros(n, dtype=bool)
    if count >= n:
        keep[:] = True
    elif count > 0:
        # the count-th best value; every score above it, then the first of those equal to it, in index order
        kth = np.partition(scores, n - count)[n - count]
        above = scores > kth
        keep |= above
        equal = np.flatnonzero(scores == kth)
        keep[equal[: count - int(above.sum())]] = True
    if per_group > 0:
        group = np.asarray(group, dtype=np.int64)
        low = int(group.min())
        _best_of_each(scores, group - low, int(group.max()) - low + 1, int(per_group), keep)
    return np.flatnonzero(keep)


def warm() -> None:
    """Compile (or load from numba's cache) `distinct_best`'s loop (`field_kernels.warm`)."""
    distinct_best(np.eye(3)[None], np.zeros((1, 3)), np.zeros(1, dtype=np.int64), count=1)
    best_overall_and_by_group(np.zeros(2), np.zeros(2, dtype=np.int64), count=1, per_group=1)


@njit(cache=True, nogil=True)
def _best_of_each(scores, group, groups, per_group, keep):
    # Each group's best few so far, best first (ties: the earlier index stays ahead), kept in place as the scores
    # stream by: per_group is a few, so an insertion is a few moves.
    best = np.full((groups, per_group), -1, dtype=np.int64)
    filled = np.zeros(groups, dtype=np.int64)
    for i in range(len(scores)):
        g, s = group[i], scores[i]
        m = filled[g]
        if m == per_group and not s > scores[best[g, m - 1]]:
            continue
        k = min(m, per_group - 1)
        while k > 0 and s > scores[best[g, k - 1]]:
            best[g, k] = best[g, k - 1]
            k -= 1
        best[g, k] = i
        filled[g] = min(m + 1, per_group)
    for g in range(groups):
        for k in range(filled[g]):
            keep[best[g, k]] = True


@njit(cache=True, nogil=True)
def _distinct_best(R, t, order, count, min_translation2, min_trace):
    # Compiled: a building's frame suppresses among thousands of hypotheses, and each test of one against the kept
    # ones cost numpy a dozen calls (18 ms of a 100-room frame).
    kept = np.empty(min(count, len(order)), dtype=np.int64)
    n = 0
    for i in order:
        distinct = True
        for m in range(n):
            k = kept[m]
            d2 = (t[i, 0] - t[k, 0]) ** 2 + (t[i, 1] - t[k, 1]) ** 2 + (t[i, 2] - t[k, 2]) ** 2
            if d2 > min_translation2:
                continue
            trace = 0.0
            for a in range(3):
                for b in range(3):
                    trace += R[i, a, b] * R[k, a, b]
            if trace >= min_trace:  # turned by no more than the minimum
                distinct = False
                break
        if distinct:
            kept[n] = i
            n += 1
            if n >= len(kept):
                break
    return kept[:n]
