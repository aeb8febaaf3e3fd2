"""Label-free global search: branch-and-bound over (x, y, z, yaw) once the frame's up direction is known.

In the style of Cartographer's fast correlative scan matcher (Hess et al. 2016) and 3D-BBS (Aoki et al. 2024): a
score grid over the map (how close each cell is to a map surface) and a pyramid of max-pooled copies of it are
built once per site. A node of the search is a yaw and a cube of 2^h × 2^h × 2^h camera positions; the sum of the
level-h grid at the node's corner plus each frame point is an upper bound of the score of every position in the
cube, so whole cubes are dropped when their bound cannot reach the best leaf found. Nodes are expanded in batches
(compiled sums over nodes × points: `field_kernels.sums_at` for the roots, `child_sums` for each level's children
and their bounds at once), best first with a greedy dive for the first bound,
and the number of nodes kept per level is capped so that the cost of a frame is bounded by its inputs, not by its
luck.

Written here because no library does it: 3D-BBS is a C++/CUDA ROS package without Python bindings, and
Cartographer's matcher is 2-D and part of the Cartographer C++ tree.

Frames: `level` is the map rotated so that the map's up is +z (`R_level_map`); yaw is about +z there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.ndimage import binary_dilation

from ..config import LabelFreeConfig
from ..geometry import rotation_between
from ..site.bundle import StoredPyramid
from . import field_kernels
from .match import Hypotheses, distinct_best
from .score import DistanceField

# The score grid is stored as uint8 (0..SCALE): a quarter of float32's memory, and sums of a few hundred points
# stay exact in int32.
SCALE = 255
# A frame needs this many normals of vertical surfaces to say which way it faces (`frame_direction_histogram`).
MIN_FRAME_NORMALS = 40
# Seed of the order in which nodes with equal bounds are cut (`highest`, `best_first`): the same frame gives the same
# answer.
TIE_SEED = 0


@dataclass
class SearchStats:
    """What one search did: nodes whose bound was computed, leaves scored, whether a level's node cap cut the
    search (then the result may miss the best leaf), and the best leaf score in [0, 1]."""

    nodes: int = 0
    leaves: int = 0
    capped: bool = False
    best: float = 0.0


class GridPyramid:
    """Max-pooled score grids over one site's map, in the level frame.

    field : the site's distance field (map frame). up : (3,) the map's unit up vector. voxel_m : cell size of the
    finest level (the leaves' translation step). levels : pyramid levels above the finest (a root covers
    2^levels cells a side). tau_m : a cell whose centre is d from the map scores max(0, 1 − (d / tau)²).
    reach_m : frame points farther than this from the camera are not used (the grid is padded by it).
    margin_m : the camera may stand this far outside the box of the map (a view from the doorway of a room whose
    map holds only what is ahead of it).
    max_cells : cap on the cells of one level; the voxel grows until it fits (memory is (levels + 1) bytes a cell).

    A building's bundle stores its pyramid (`to_stored`, `from_stored`; `site.bundle.StoredPyramid`): a worker maps
    it rather than building it at start (2 s and 95 MB of its own for 100 rooms).
    """

    def __init__(self, field: DistanceField, map_xyz: np.ndarray, up: np.ndarray, *, voxel_m: float = 0.1,
                 levels: int = 4, tau_m: float = 0.15, reach_m: float = 4.0, margin_m: float = 1.0,
                 max_cells: int = 32_000_000) -> None:
        settings = built_with(up, voxel_m=voxel_m, levels=levels, tau_m=tau_m, reach_m=reach_m, margin_m=margin_m,
                              max_cells=max_cells)
        p = np.asarray(map_xyz, dtype=np.float64) @ _level_rotation(settings).T
        self._place(settings, p.min(axis=0), p.max(axis=0))
        voxel_m, dims = self.voxel_m, self.dims
        # Finest level: the score at each cell centre, from the exact distance field (looked up in the map frame).
        # Only cells within tau of a map point can score: those (the occupied cells grown by tau) are looked up,
        # a tenth of the grid or less, so that building the pyramid costs a fraction of a second.
        occupied = np.zeros(tuple(dims), dtype=bool)
        cell = np.floor((p - self.origin) / voxel_m).astype(np.int64)
        occupied[cell[:, 0], cell[:, 1], cell[:, 2]] = True
        # A centre within tau of a point lies at most ceil(tau / voxel + ½) cells from its cell along each axis.
        near = binary_dilation(occupied, structure=np.ones((3, 3, 3), dtype=bool),
                               iterations=int(np.ceil(tau_m / voxel_m + 0.5)))
        flat = np.flatnonzero(near)
        idx = np.stack(np.unravel_index(flat, tuple(dims)), axis=1)
        centres = self.origin + (idx + 0.5) * voxel_m
        d = field.lookup(centres @ self.R_level_map)  # rows: R_level_mapᵀ · c, back in the map frame
        base = np.zeros(int(np.prod(dims)), dtype=np.uint8)
        base[flat] = np.rint(np.clip(1.0 - (d / tau_m) ** 2, 0.0, 1.0) * SCALE).astype(np.uint8)
        base = base.reshape(tuple(dims))
        self.grids = [base.ravel()]
        g = base
        for h in range(1, self.levels + 1):
            # Level h at cell i is the max of level h−1 at i and i + 2^(h−1) along each axis: the max over the
            # 2^h cube whose lower corner is i (cells past the grid's end read 0).
            step = 2 ** (h - 1)
            g = g.copy()
            for axis in range(3):
                sl_dst = [slice(None)] * 3
                sl_src = [slice(None)] * 3
                sl_dst[axis] = slice(0, dims[axis] - step)
                sl_src[axis] = slice(step, None)
                np.maximum(g[tuple(sl_dst)], g[tuple(sl_src)], out=g[tuple(sl_dst)])
            self.grids.append(g.ravel())
        self.nbytes = sum(x.nbytes for x in self.grids)

    def _place(self, settings: dict[str, Any], lo: np.ndarray, hi: np.ndarray) -> None:
        """The grid's layout over a map whose box in the level frame is lo..hi, for `built_with`'s settings: the
        same for a pyramid built and for one read back (`from_stored` derives it rather than reading it, so that
        what a bundle stores cannot disagree with itself)."""
        self.built_with = settings
        self.R_level_map = _level_rotation(settings)
        self.levels = int(settings["levels"])
        self.reach_m = float(settings["reach_m"])
        extent = hi - lo
        self.voxel_m = pyramid_voxel(extent, voxel_m=settings["voxel_m"], levels=self.levels, reach_m=self.reach_m,
                                     margin_m=settings["margin_m"], max_cells=settings["max_cells"])
        self.margin, self.pad, self.inner, self.dims = _layout(extent, self.voxel_m, self.levels, self.reach_m,
                                                               settings["margin_m"])
        # inner: the map's cells (the camera's (x, y) stays over the map); origin: cell (0, 0, 0)'s corner
        self.origin = lo - self.pad * self.voxel_m
        self.map_lo_level, self.map_hi_level = lo, hi
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)

    # ------------------------------------------------------------------------------------------------------------
    def to_stored(self) -> StoredPyramid:
        """This pyramid as a bundle stores it: its grids one level a row, what it was built with and the map's box
        (`from_stored` gives it back)."""
        return StoredPyramid(np.stack(self.grids), self.built_with, self.map_lo_level, self.map_hi_level)

    @classmethod
    def from_stored(cls, stored: StoredPyramid, wanted: dict[str, Any]) -> "GridPyramid | None":
        """The pyramid a bundle stores, its grids used where they lie (a memory map), when it is the one this code
        would build for `wanted` (`built_with`): the same settings and up (`StoredPyramid.matches`), and grids of
        the shape its layout gives (a bundle of another version of this code may differ); else None."""
        if not stored.matches(wanted):
            return None
        pyr = cls.__new__(cls)
        pyr._place(dict(stored.built_with), stored.map_lo_level, stored.map_hi_level)
        if stored.grids.dtype != np.uint8 or stored.grids.shape != (pyr.levels + 1, int(np.prod(pyr.dims))):
            return None
        pyr.grids = list(stored.grids)
        pyr.nbytes = int(stored.grids.nbytes)
        return pyr

    # ------------------------------------------------------------------------------------------------------------
    def camera_domain(self, z_range_level: tuple[float, float] | None = None,
                      box_level: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) inclusive cell indices of camera positions searched: the map's box grown by margin_m (a
        camera is not far from everything it sees); in z `z_range_level` when given; within `box_level` ((2, 3)
        min and max corners, level frame, metres: a client's search region) when given."""
        lo = np.full(3, self.pad - self.margin)
        hi = np.full(3, self.pad) + self.inner - 1 + self.margin
        if box_level is not None:
            cells = np.floor((np.asarray(box_level, dtype=np.float64) - self.origin) / self.voxel_m).astype(np.int64)
            lo = np.maximum(lo, cells[0])
            hi = np.maximum(np.minimum(hi, cells[1]), lo)
        if z_range_level is not None:
            zl, zh = (np.floor((np.asarray(z_range_level) - self.origin[2]) / self.voxel_m)).astype(np.int64)
            z_lo, z_hi = lo[2], hi[2]
            lo[2], hi[2] = max(z_lo, zl), min(z_hi, zh)
            if hi[2] < lo[2]:
                lo[2] = hi[2] = int(np.clip((zl + zh) // 2, z_lo, z_hi))
        return lo, hi

    def search(self, points_level: np.ndarray, yaws_rad: np.ndarray, *, z_range_level: tuple[float, float] | None = None,
               box_level: np.ndarray | None = None, keep_ratio: float = 0.85, max_nodes: int = 1500,
               dives: int = 4, places: "YawPlaces | None" = None) -> tuple[np.ndarray, np.ndarray, SearchStats]:
        """Best leaves of the search (camera positions within `box_level` when given, see `camera_domain`).

        points_level : (m, 3) frame points rotated so that the camera's up is +z (camera at the origin).
        yaws_rad : (k,) yaws searched. Leaves scoring at least keep_ratio × the best are returned:
        (poses (l, 4): yaw, x, y, z of the camera in the level frame; scores (l,) in [0, 1]), best first.
        max_nodes : nodes kept per level (the highest bounds); the cap bounds the cost of any frame.
        places : where each yaw is searched (a building whose rooms face their own directions), None: everywhere.
        """
        stats = SearchStats()
        rng = np.random.default_rng(TIE_SEED)
        pts = np.asarray(points_level, dtype=np.float64)
        pts = pts[np.linalg.norm(pts, axis=1) < self.reach_m - self.voxel_m]
        if len(pts) == 0 or len(yaws_rad) == 0:
            return np.zeros((0, 4)), np.zeros(0), stats
        n = len(pts)
        c, s = np.cos(yaws_rad), np.sin(yaws_rad)
        x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1]
        y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1]
        z = np.broadcast_to(pts[None, :, 2], x.shape)
        v = self.voxel_m
        offs = (np.floor(x / v).astype(np.int64) * self.strides[0] + np.floor(y / v).astype(np.int64) * self.strides[1]
                + np.floor(z / v).astype(np.int64) * self.strides[2])  # (k, n)
        lo, hi = self.camera_domain(z_range_level, box_level)
        H = self.levels
        span = 2 ** H
        axes = [np.arange(lo[a], hi[a] + 1, span) for a in range(3)]
        gi, gj, gk = np.meshgrid(*axes, indexing="ij")
        corner = np.stack([gi.ravel(), gj.ravel(), gk.ravel()], axis=1)
        yi = np.repeat(np.arange(len(yaws_rad)), len(corner))
        if places is not None:
            # Each root keeps the yaws of the rooms its cube meets; its children lie inside it and keep its yaw.
            lo_level = self.origin + corner * v
            allowed = places.at(lo_level, lo_level + span * v).T.ravel()  # yaw-major, as yi
            yi, corner = yi[allowed], np.tile(corner, (len(yaws_rad), 1))[allowed]
        else:
            corner = np.tile(corner, (len(yaws_rad), 1))
        if len(corner) == 0:
            return np.zeros((0, 4)), np.zeros(0), stats

        offs = np.ascontiguousarray(offs)
        grids = [field_kernels.read_only(g) for g in self.grids]

        def bound(level: int, yaw: np.ndarray, cell: np.ndarray) -> np.ndarray:
            out = np.empty(len(yaw), dtype=np.int64)
            field_kernels.sums_at(grids[level], offs, np.ascontiguousarray(yaw, dtype=np.int64),
                                  np.ascontiguousarray(cell @ self.strides, dtype=np.int64), out)
            stats.nodes += len(yaw)
            return out

        def children(level: int, yaw: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """The children of nodes of `level` that lie in the domain, parent by parent, with their bounds."""
            out_yaw = np.empty(8 * len(yaw), dtype=np.int64)
            out_cell = np.empty((8 * len(yaw), 3), dtype=np.int64)
            out_bound = np.empty(8 * len(yaw), dtype=np.int64)
            count = field_kernels.child_sums(grids[level - 1], offs, self.strides, hi, 2 ** (level - 1),
                                             np.ascontiguousarray(yaw, dtype=np.int64),
                                             np.ascontiguousarray(cell, dtype=np.int64), out_yaw, out_cell, out_bound)
            stats.nodes += count
            return out_yaw[:count], out_cell[:count], out_bound[:count]

        b = bound(H, yi, corner)
        # A first bound to prune with: greedy dives from the best roots to a leaf.
        best = 0
        order = np.argsort(-b)[:dives]
        dy, dc = yi[order], corner[order]
        for level in range(H, 0, -1):
            cy, cc, cb = children(level, dy, dc)
            if len(cy) == 0:
                break
            # The best child of each dive (children of one parent are consecutive, 8 or fewer).
            picks = []
            for parent_yaw, parent_cell in zip(dy, dc):
                m = np.flatnonzero((cy == parent_yaw) & np.all((cc >= parent_cell) & (cc < parent_cell + 2 ** level), axis=1))
                if len(m):
                    picks.append(m[np.argmax(cb[m])])
            picks = np.array(picks, dtype=np.int64)
            dy, dc = cy[picks], cc[picks]
            if level == 1:
                best = int(cb[picks].max())
        for level in range(H, 0, -1):
            keep = np.flatnonzero(b >= keep_ratio * best)
            if len(keep) > max_nodes:
                stats.capped = True
                keep = keep[highest(b[keep], max_nodes, rng)]
            yi, corner, b = children(level, yi[keep], corner[keep])
            if level == 1 and len(b):
                best = max(best, int(b.max()))
        keep = np.flatnonzero(b >= keep_ratio * best)
        keep = keep[best_first(b[keep], rng)]
        stats.leaves = len(b)
        stats.best = best / (SCALE * n)
        pos = self.origin + corner[keep] * v
        poses = np.column_stack([yaws_rad[yi[keep]], pos])
        return poses, b[keep] / (SCALE * n), stats

    def hypotheses(self, poses: np.ndarray, scores: np.ndarray, R_up_camera: np.ndarray, *, count: int,
                   min_translation_m: float, min_rotation_deg: float, consider: int = 3000,
                   exact: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                   extra: int = 0) -> Hypotheses:
        """Distinct best leaves as map-frame hypotheses T_map_camera (R, t); `geometric` holds the leaf scores.

        R_up_camera : (3, 3) rotation taking the camera's up to +z (the frame's levelling).
        exact, extra : up to `extra` more distinct leaves after those, the best by exact(R, t) ((l,) scores of the
        leaves' poses; ties in the search's order), the first `count` counted as taken. A close view's leaves tie
        at the search's bound (a small patch fits anywhere on its coarse cells) and are taken in a random order; the
        exact field tells them apart (the m16 building's close views without labels, 2 of the 12 unique views it
        missed, and 5 of 2,560 searches on walks through scene0470 and the 10-room building, now right `ok`; no
        answer of the benchmark's sets changed)."""
        poses, scores = poses[:consider], scores[:consider]
        if len(poses) == 0:
            return Hypotheses.empty()
        c, s = np.cos(poses[:, 0]), np.sin(poses[:, 0])
        Rz = np.zeros((len(poses), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        R = self.R_level_map.T @ Rz @ R_up_camera
        t = poses[:, 1:] @ self.R_level_map
        keep = np.array(distinct_best(R, t, np.arange(len(R)), count=count, min_translation_m=min_translation_m,
                                      min_rotation_deg=min_rotation_deg), dtype=np.int64)
        if exact is not None and extra > 0:
            by_exact = np.argsort(-exact(R, t), kind="stable")
            keep = np.array(distinct_best(R, t, np.concatenate([keep, by_exact]), count=len(keep) + extra,
                                          min_translation_m=min_translation_m, min_rotation_deg=min_rotation_deg),
                            dtype=np.int64)
        hyp = Hypotheses(R[keep], t[keep], np.full((len(keep), 2), -1, dtype=np.int64))
        hyp.geometric = scores[keep]
        return hyp


def built_with(up: np.ndarray, *, voxel_m: float, levels: int, tau_m: float, reach_m: float, margin_m: float,
               max_cells: int) -> dict[str, Any]:
    """What a pyramid is built from, besides the site's field and points (JSON): a stored pyramid serves a localizer
    whose up and settings give the same (`StoredPyramid.matches`)."""
    return {"up": [float(x) for x in np.asarray(up, dtype=np.float64).reshape(3)], "voxel_m": float(voxel_m),
            "levels": int(levels), "tau_m": float(tau_m), "reach_m": float(reach_m), "margin_m": float(margin_m),
            "max_cells": int(max_cells)}


def pyramid_settings(lf: LabelFreeConfig) -> dict[str, Any]:
    """`GridPyramid`'s keyword settings from the label-free search's config."""
    return {"voxel_m": lf.voxel_m, "levels": lf.levels, "tau_m": lf.tau_m, "reach_m": lf.reach_m,
            "margin_m": lf.camera_margin_m, "max_cells": lf.max_cells}


def building_pyramid(field: DistanceField, up: np.ndarray, lf: LabelFreeConfig) -> GridPyramid:
    """A building's pyramid: its occupied cells read from its stored field (its points stay where they lie), one per
    half a cell (`DistanceField.surface_points`). What `site compose` stores, and what a worker builds when the
    bundle stores none for its settings."""
    return GridPyramid(field, field.surface_points(lf.voxel_m / 2), up, **pyramid_settings(lf))


def _level_rotation(settings: dict[str, Any]) -> np.ndarray:
    """R_level_map of a pyramid built with `settings` (`built_with`): the map's up onto +z."""
    return rotation_between(np.asarray(settings["up"], dtype=np.float64), np.array([0.0, 0.0, 1.0]))


def pyramid_voxel(extent_m: np.ndarray, *, voxel_m: float, levels: int, reach_m: float, margin_m: float,
                  max_cells: int) -> float:
    """The finest cell of a map's pyramid: voxel_m, grown by a quarter at a time until a level of the map's
    extent ((3,) metres along the level frame's axes, `GridPyramid`'s padding added) holds at most max_cells."""
    while np.prod(_layout(np.asarray(extent_m, dtype=np.float64), voxel_m, levels, reach_m, margin_m)[3]) > max_cells:
        voxel_m *= 1.25
    return float(voxel_m)


def _layout(extent_m: np.ndarray, voxel_m: float, levels: int, reach_m: float,
            margin_m: float) -> tuple[int, int, np.ndarray, np.ndarray]:
    """(margin, pad, inner, dims) in cells of a pyramid over a map of this extent at this voxel: the camera's
    margin outside the map, the padding a side (the frame's reach and the margin), the map's cells and the grid's."""
    margin = int(np.ceil(margin_m / voxel_m))
    pad = int(np.ceil(reach_m / voxel_m)) + 1 + margin
    inner = np.ceil(extent_m / voxel_m).astype(np.int64) + 1
    return margin, pad, inner, inner + 2 * pad + 2 ** int(levels)


def highest(values: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of `count` of the highest `values` (all of them when there are fewer), in no order; among values equal
    to the lowest one kept, a random choice of `rng`'s.

    A large site's coarse levels saturate: in a 100-room building every frame point finds a surface within a root's
    3 m cube, and a third to a half of the roots bound 1.0, as do their children. Cut in the array's order, which is
    yaw-major, the cap kept every tied node of some yaws and none of others, so a view's pose lived or died by where
    its yaw fell (the 100-room frames without labels: of the 11 unique views the search missed, 10 had their pose's
    branch cut among tied nodes at the first to third level). A random choice gives every tied node the same chance,
    and a larger cap then keeps more of them."""
    if len(values) <= count:
        return np.arange(len(values))
    if count <= 0:
        return np.zeros(0, dtype=np.int64)
    cut = np.partition(values, len(values) - count)[len(values) - count]  # the count-th highest value
    above = np.flatnonzero(values > cut)
    tied = np.flatnonzero(values == cut)
    return np.concatenate([above, rng.choice(tied, count - len(above), replace=False)])


def best_first(values: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices ordering `values` highest first, equal values in a random order of `rng`'s (see `highest`)."""
    return np.lexsort((rng.random(len(values)), -values))


def all_yaws(step_deg: float) -> np.ndarray:
    """Every yaw (radians) of a search at this step: 0, step, ... below 360°."""
    return np.radians(np.arange(0.0, 360.0, step_deg))


def frame_direction_histogram(frame_normals_level: np.ndarray, *,
                              min_normals: int = MIN_FRAME_NORMALS) -> np.ndarray | None:
    """The frame's `axial_histogram` of its vertical surfaces' normals (level frame), or None when it shows fewer than
    min_normals of them: too few to say which way the camera faces."""
    n = frame_normals_level
    horizontal = n[np.abs(n[:, 2]) < 0.3]
    return axial_histogram(horizontal) if len(horizontal) >= min_normals else None


def yaws_allowed(frame_hist: np.ndarray | None, map_hist: np.ndarray | None, *, step_deg: float,
                 keep_ratio: float = 0.4, spread_deg: float = 6.0) -> np.ndarray:
    """(k,) bool over `all_yaws(step_deg)`: the yaws worth searching for a frame of these wall directions in a map
    (or a room) of those; all of them when either histogram is None.

    Walls, cupboard fronts and furniture sides of the frame face the directions the map's do, turned by the
    camera's yaw: the circular correlation of the two histograms of horizontal normal directions (axial, mod
    180°: normals of a depth frame and of a map may be flipped) peaks at the right yaw (and, in a box-shaped room,
    every 90°). Yaws near the peaks at least keep_ratio of the highest are kept, both ways round.
    """
    yaws = all_yaws(step_deg)
    if frame_hist is None or map_hist is None:
        return np.ones(len(yaws), dtype=bool)
    bins = len(map_hist)
    # corr[s] = Σ_b fh[b] · m[b + s]: the frame's direction b lies at b + s in the map after a yaw of s bins. m is
    # the square root of the map's histogram: a map dominated by one wall direction must not outvote the true yaw
    # of a frame that sees the other (a kitchen's long counter against its short side walls).
    corr = np.real(np.fft.ifft(np.conj(np.fft.fft(frame_hist)) * np.fft.fft(np.sqrt(np.maximum(map_hist, 0.0)))))
    if not np.isfinite(corr).all() or corr.max() <= 0:
        return np.ones(len(yaws), dtype=bool)
    good = np.flatnonzero(corr >= keep_ratio * corr.max())
    centres = np.concatenate([good, good + bins]) * (180.0 / bins)  # mod 180 -> both ways round
    diff = np.abs((np.degrees(yaws)[:, None] - centres[None, :] + 180.0) % 360.0 - 180.0)
    return diff.min(axis=1) <= spread_deg / 2 + step_deg / 2


@dataclass
class YawPlaces:
    """Where each yaw of a search is tried: in a building whose rooms face directions of their own (rooms turned by
    odd angles), the camera positions near a room try the yaws its own walls give (`yaws_allowed` of its
    histogram; `FallbackStage._yaws`).

    boxes_level : (b, 2, 3) min and max corners (level frame, metres) of the places (a building's regions).
    allowed : (b, k) bool, the yaws of the search (its yaws_rad, in order) tried from a place. A root of the search
    whose cube meets no place tries every yaw."""

    boxes_level: np.ndarray
    allowed: np.ndarray

    def at(self, lo_level: np.ndarray, hi_level: np.ndarray) -> np.ndarray:
        """(c, k) bool: the yaws tried from each cube [lo, hi] ((c, 3) corners, level frame)."""
        meets = np.all((lo_level[:, None, :] <= self.boxes_level[None, :, 1])
                       & (self.boxes_level[None, :, 0] <= hi_level[:, None, :]), axis=2)  # (c, b)
        out = (meets.astype(np.int64) @ self.allowed.astype(np.int64)) > 0
        out[~meets.any(axis=1)] = True
        return out


def axial_histogram(normals_level: np.ndarray, *, bins: int = 90, smooth_bins: float = 1.5) -> np.ndarray:
    """Normalized histogram of horizontal normal directions mod 180° (bins of 180/bins degrees), smoothed
    circularly: the noise of a depth frame's normals is a few degrees."""
    a = np.degrees(np.arctan2(normals_level[:, 1], normals_level[:, 0])) % 180.0
    h = np.bincount(np.minimum((a / (180.0 / bins)).astype(np.int64), bins - 1), minlength=bins).astype(np.float64)
    k = np.arange(bins)
    d = np.minimum(k, bins - k)
    kernel = np.exp(-0.5 * (d / smooth_bins) ** 2)
    h = np.real(np.fft.ifft(np.fft.fft(h) * np.fft.fft(kernel)))
    return h / max(h.sum(), 1e-12)


def map_direction_histogram(normals_level: np.ndarray, *, sample: int = 50000, seed: int = 0) -> np.ndarray | None:
    """The map's `axial_histogram` of its vertical surfaces (None when it has none to speak of)."""
    n = np.asarray(normals_level, dtype=np.float64)
    n = n[np.linalg.norm(n, axis=1) > 0.5]
    if len(n) > sample:
        n = n[np.random.default_rng(seed).choice(len(n), sample, replace=False)]
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    horizontal = n[np.abs(n[:, 2]) < 0.3]
    if len(horizontal) < 100:
        return None
    return axial_histogram(horizontal)


def turned_histogram(hist: np.ndarray, yaws_rad: np.ndarray) -> np.ndarray:
    """An `axial_histogram` of a room's directions made one of all its copies: the mean of it turned by each of the
    copies' yaws (radians, the copy's turn from the room) that differ modulo a quarter turn, to the nearest bin.
    A room's walls face the same directions after a quarter turn: copies so turned (a building's grid) leave the
    histogram as it is, while a copy turned by an odd angle (a wing at 30°) adds its own directions, which the
    yaws searched for its views must come from."""
    bins = len(hist)
    shifts = np.unique(np.rint(np.degrees(np.asarray(yaws_rad, dtype=np.float64)) / (180.0 / bins)).astype(np.int64)
                       % (bins // 2))
    return np.mean([np.roll(hist, int(s)) for s in shifts], axis=0) if len(shifts) else hist


def polish(field: DistanceField, points_camera: np.ndarray, hyp: Hypotheses, up: np.ndarray, *, step_m: float = 0.05,
           step_deg: float = 1.5, rounds: int = 2, tau_m: float = 0.1, later_within: float | None = None) -> Hypotheses:
    """Each hypothesis moved to the best of its neighbours on the exact distance field: yaw ± step_deg and each
    translation axis ± step_m (81 poses), the steps halved each round. The search's leaves are cell corners and
    yaw steps apart; this brings them within a few centimetres and a degree at the cost of a few hundred lookups.
    later_within : after the first round, only the hypotheses scoring within this of the best are polished further
    (None: all); the others keep their first round's pose and score."""
    from .match import yaw_rotations
    from .score import score_poses

    if len(hyp) == 0:
        return hyp
    R, t = hyp.R.copy(), hyp.t.copy()
    grid = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.float64)
    best = score_poses(field, points_camera, R, t, tau_m=tau_m)
    live = np.arange(len(R))
    for round_ in range(rounds):
        if round_ > 0 and later_within is not None:
            live = np.flatnonzero(best >= best.max() - later_within)
        dR = yaw_rotations(up, np.radians(np.array([-step_deg, 0.0, step_deg])))  # (3, 3, 3)
        # Every live hypothesis's 81 neighbours scored in one call, yaw-major as (yaw, offset) pairs.
        Rs = np.repeat(np.einsum("yij,hjk->hyik", dR, R[live]), len(grid), axis=1).reshape(-1, 3, 3)
        ts = np.tile((t[live][:, None, :] + grid[None] * step_m), (1, len(dR), 1)).reshape(-1, 3)
        s = score_poses(field, points_camera, Rs, ts, tau_m=tau_m).reshape(len(live), -1)
        k = np.argmax(s, axis=1)
        better = np.flatnonzero(s[np.arange(len(live)), k] > best[live])
        moved = better * s.shape[1] + k[better]
        R[live[better]], t[live[better]], best[live[better]] = Rs[moved], ts[moved], s[better, k[better]]
        step_m, step_deg = step_m / 2, step_deg / 2
    out = Hypotheses(R, t, hyp.seed)
    out.geometric = best
    return out
