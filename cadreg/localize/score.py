"""Geometric check of a pose hypothesis: how well the frame's points lie on the map.

A distance field (distance from every voxel of a grid over the map to the nearest map point) is built once per
site, so that scoring one hypothesis costs a transform and a gather of a few hundred points; thousands of
hypotheses per frame stay cheap. scipy's exact Euclidean distance transform does the work.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.ndimage import distance_transform_edt, minimum_filter

from ..camera import CameraIntrinsics
from ..site.bundle import FieldGrid
from . import field_kernels, view_kernels
from .points import voxel_indices

# The free-space check's z-buffer cells (`ViewCheck`, cell_px pixels, pooled) and its count of cells to compare
# (min_cells) were set on 640 x 480 depth images: every frame is projected as a camera of that many pixels would see
# it (`reference_camera`).
ZBUFFER_REFERENCE_PIXELS = 640 * 480

# A stored field holds distances in steps of truncate_m / QUANT_MAX, one byte a cell.
QUANT_MAX = 255


class DistanceField:
    """Truncated distance to the nearest map point on a regular grid (map frame, metres).

    points : (n, 3) float map points. voxel_m : grid spacing; grown when the grid would exceed `max_cells`.
    Distances are exact to about half a voxel; beyond `truncate_m` (and outside the grid) they read `truncate_m`.
    """

    def __init__(self, points: np.ndarray, *, voxel_m: float = 0.03, margin_m: float = 0.3, truncate_m: float = 0.5,
                 max_cells: int = 40_000_000) -> None:
        points = np.asarray(points, dtype=np.float64)
        lo = points.min(axis=0) - margin_m
        hi = points.max(axis=0) + margin_m
        while np.prod(np.ceil((hi - lo) / voxel_m) + 1) > max_cells:
            voxel_m *= 1.25
        occupied = np.ones(tuple((np.ceil((hi - lo) / voxel_m) + 1).astype(np.int64)), dtype=bool)
        ijk = np.floor((points - lo) / voxel_m).astype(np.int64)
        occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = False
        dist = np.minimum(distance_transform_edt(occupied) * voxel_m, truncate_m).astype(np.float32)
        # A one-voxel border at the truncation distance: clipped indices of outside points land on it.
        self._hold(np.pad(dist, 1, constant_values=np.float32(truncate_m)), lo, voxel_m, truncate_m, None)

    def _hold(self, padded: np.ndarray, origin: np.ndarray, voxel_m: float, truncate_m: float,
              step_m: float | None) -> None:
        """Take `padded` ((dims + 2) cells along each axis, its one-cell border at the truncation distance) as this
        field's grid. step_m : metres per unit of a quantized grid (None: the grid holds metres)."""
        self.voxel_m = float(voxel_m)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.dims = np.array(padded.shape, dtype=np.int64) - 2
        self.truncate_m = float(truncate_m)
        self.step_m = step_m
        self.grid = padded.reshape(-1)
        d = self.dims + 2
        self._strides = np.array([d[1] * d[2], d[2], 1], dtype=np.int64)

    @classmethod
    def from_grid(cls, stored: FieldGrid) -> "DistanceField":
        """The field a site stores (`building_field`), read where it lies (a memory map: shared by the worker
        processes through the page cache, and paged in where frames are scored)."""
        self = cls.__new__(cls)
        self._hold(stored.grid, stored.origin, stored.voxel_m, stored.truncate_m, float(stored.truncate_m) / QUANT_MAX)
        return self

    def coarsened(self, factor: int) -> "DistanceField":
        """This field with cells `factor` times as large (same origin), each holding the least distance of the cells
        it covers: a lower bound, off by at most a coarse cell's diagonal, in 1 / factor³ of the memory. A
        building's field is 100-400 MB, and a frame's first look at its 30-160 k graph hypotheses reads it at
        random: 25 ns a read from the fine field, a few from a coarse one that stays in the processor's cache."""
        factor = int(factor)
        far = np.asarray(self.truncate_m if self.step_m is None else QUANT_MAX, dtype=self.grid.dtype)
        blocks = self.grid.reshape(tuple(self.dims + 2))[1:-1, 1:-1, 1:-1]
        for axis in range(3):
            blocks = _least_of_runs(blocks, factor, axis, far)
        out = DistanceField.__new__(DistanceField)
        out._hold(np.pad(blocks, 1, constant_values=far), self.origin.copy(), self.voxel_m * factor, self.truncate_m,
                  self.step_m)
        return out

    def surface_points(self, spacing_m: float) -> np.ndarray:
        """(m, 3) float64 centres of the cells within half a voxel of the map, thinned to one per `spacing_m` cube
        (map frame): where the map has surfaces, read from the field alone (a building's points stay on disk)."""
        within = 0.5 * self.voxel_m
        threshold = within if self.step_m is None else within / self.step_m
        d = self.dims + 2
        thin = max(1, int(round(spacing_m / self.voxel_m)))
        if thin == 1:  # (cubes of one cell: a mask of the grid is no bigger than the marks below)
            ijk = np.stack(np.unravel_index(np.flatnonzero(self.grid <= threshold), tuple(d)), axis=1)
        else:  # one pass marking the cubes (a mask of the grid, then its cells' cubes made unique: several times that)
            blocks = -(-d // thin)
            cubes = np.zeros(int(np.prod(blocks)), dtype=np.bool_)
            field_kernels.occupied_cubes(field_kernels.read_only(self.grid), d, threshold, thin, blocks, cubes)
            ijk = np.stack(np.unravel_index(np.flatnonzero(cubes), tuple(blocks)), axis=1) * thin
        return self.origin + (ijk - 1 + 0.5) * self.voxel_m

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """points : (..., 3) float map frame -> (...) float32 distances, metres."""
        return self.lookup_xyz(points[..., 0], points[..., 1], points[..., 2])

    def lookup_xyz(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Same as `lookup` with the coordinates as separate arrays of one shape (no (..., 3) copy)."""
        x, y, z = (field_kernels.floats(c) for c in np.broadcast_arrays(x, y, z))
        out = np.empty(x.shape, dtype=np.float32)
        field_kernels.lookup(*self.kernel_args(), x.reshape(-1), y.reshape(-1), z.reshape(-1), out.reshape(-1))
        return out

    def kernel_args(self) -> tuple:
        """The grid as `field_kernels` reads it: (flat grid, metres per unit, origin, voxel, last cell index per
        axis, flat strides)."""
        return (field_kernels.read_only(self.grid), 1.0 if self.step_m is None else float(self.step_m),
                field_kernels.floats(self.origin),
                self.voxel_m, (self.dims + 1).astype(np.float64), self._strides)


def _least_of_runs(a: np.ndarray, factor: int, axis: int, far: np.ndarray) -> np.ndarray:
    """The least of each run of `factor` cells of `a` along `axis` (a shorter last run as it is): one pass over `a`,
    and no copy of it (a building's field is memory-mapped, and a worker makes its coarse copy at start)."""
    runs = -(-a.shape[axis] // factor)
    out = np.full(a.shape[:axis] + (runs,) + a.shape[axis + 1:], far, dtype=a.dtype)
    for k in range(factor):
        part = a[(slice(None),) * axis + (slice(k, None, factor),)]
        into = out[(slice(None),) * axis + (slice(0, part.shape[axis]),)]
        np.minimum(into, part, out=into)
    return out


def building_field(clouds: list[np.ndarray], *, voxel_m: float = 0.03, margin_m: float = 0.3, truncate_m: float = 0.5,
                   max_cells: int = 400_000_000) -> FieldGrid:
    """The distance field of a building, made room by room: `DistanceField`'s truncated distance over the box of
    every cloud, at one byte a cell (steps of truncate_m / 255, about 2 mm), to be stored in the bundle.

    clouds : per region, (n_i, 3) float map points. A cell within truncate_m of a point lies within truncate_m of
    that point's region box, so the exact transform of each region's box grown by truncate_m, with that region's
    points, and the minimum over regions gives the field of the whole map without one transform over the whole
    building's box (a room's box is a hundredth of a 100-room building's: memory and time stay a room's).
    """
    clouds = [np.asarray(c, dtype=np.float64) for c in clouds]
    boxes = [(c.min(axis=0), c.max(axis=0)) for c in clouds if len(c)]
    lo = np.min([b[0] for b in boxes], axis=0) - margin_m
    hi = np.max([b[1] for b in boxes], axis=0) + margin_m
    while np.prod(np.ceil((hi - lo) / voxel_m) + 1) > max_cells:
        voxel_m *= 1.25
    dims = (np.ceil((hi - lo) / voxel_m) + 1).astype(np.int64)
    grid = np.full(tuple(dims + 2), QUANT_MAX, dtype=np.uint8)  # the one-cell border stays at the truncation
    reach = int(np.ceil(truncate_m / voxel_m)) + 1
    for cloud in clouds:
        if not len(cloud):
            continue
        ijk = np.floor((cloud - lo) / voxel_m).astype(np.int64)
        a = np.maximum(ijk.min(axis=0) - reach, 0)
        b = np.minimum(ijk.max(axis=0) + reach + 1, dims)
        free = np.ones(tuple(b - a), dtype=bool)
        local = ijk - a
        free[local[:, 0], local[:, 1], local[:, 2]] = False
        dist = np.minimum(distance_transform_edt(free) * voxel_m, truncate_m)
        steps = np.rint(dist * (QUANT_MAX / truncate_m)).astype(np.uint8)
        view = grid[a[0] + 1:b[0] + 1, a[1] + 1:b[1] + 1, a[2] + 1:b[2] + 1]
        np.minimum(view, steps, out=view)
    return FieldGrid(grid, lo, float(voxel_m), float(truncate_m))


def inlier_score(distances: np.ndarray, tau_m: float) -> np.ndarray:
    """Soft inlier fraction over the last axis: mean of max(0, 1 - (d / tau)²), in [0, 1]."""
    return np.clip(1.0 - (distances / tau_m) ** 2, 0.0, 1.0).mean(axis=-1)


def score_poses(field: DistanceField, points_camera: np.ndarray, R_map_camera: np.ndarray, t_map_camera: np.ndarray,
                *, tau_m: float = 0.1, rot: np.ndarray | None = None) -> np.ndarray:
    """Score many poses at once (`inlier_score` of the field's distances at each pose's points, in one compiled loop:
    no (h, m) array of distances is made).

    points_camera : (m, 3) float camera frame. R_map_camera : (h, 3, 3), or with rot (h,) int the rotations rot
    indexes (`match.Hypotheses.R_table`); t_map_camera : (h, 3). Returns (h,) float64 soft inlier fractions.
    """
    out = np.empty(len(t_map_camera))
    table = field_kernels.NO_TABLE if field.step_m is None else _quantized_scores(field.step_m, float(tau_m))
    rot = np.arange(len(R_map_camera)) if rot is None else np.asarray(rot, dtype=np.int64)
    # the compiled loop reads R[rot[h]] unchecked
    if len(rot) != len(t_map_camera) or (len(rot) and not 0 <= rot.min() <= rot.max() < len(R_map_camera)):
        raise ValueError(f"{len(rot)} rotation indices for {len(t_map_camera)} poses and {len(R_map_camera)} "
                         "rotations")
    field_kernels.score_poses(*field.kernel_args(), field_kernels.floats(points_camera),
                              field_kernels.floats(R_map_camera), rot, field_kernels.floats(t_map_camera), float(tau_m),
                              table, out)
    return out


@lru_cache(maxsize=16)
def _quantized_scores(step_m: float, tau_m: float) -> np.ndarray:
    """`field_kernels.quantized_scores`, made once per (step, tau): a site has one step and a few taus. (Writable,
    as `field_kernels.warm` compiles for: a read-only table is another type to numba.)"""
    return field_kernels.quantized_scores(step_m, tau_m)


class ViewCheck:
    """Free-space check of a pose: map surfaces that the frame sees through.

    At the right pose, the map's surfaces in the camera's view lie at or behind what the frame measured (behind:
    occluded, or mapped but unseen). At a wrong pose that happens to fit a wall or a counter, much of the map lies
    in front of the measured depth, in space the sensor saw to be empty. The share of such map points is a
    rotation- and label-free check that the fitness alone lacks (a frame of a place the map does not hold can
    still put half its points on some surface). Written here: no library has it in this form; compiled loops do
    the projection (`view_kernels.py`).

    map_xyz : (n, 3) map points; the see-through check draws on a random sample of them (its cost is linear in
    it), render and compare (`depth_agreement`) on one point per `surface_voxel_m` voxel: the map's nearest surface
    in a cell must be there to compare with, and a fixed sample of a building's region (a room and the 3 m halo of
    its neighbours) left most cells of a right pose holding only a surface behind it (agreement 0.54-0.81 where
    every point of a 2 cm grid gave 0.89-1.0). cell_px : pixels per z-buffer cell.
    """

    def __init__(self, map_xyz: np.ndarray, *, sample: int = 30000, seed: int = 0,
                 surface_voxel_m: float = 0.02) -> None:
        xyz = np.asarray(map_xyz, dtype=np.float64)
        self._all_xyz, self._surface_voxel_m = xyz, surface_voxel_m
        self._surface_xyz: np.ndarray | None = None
        if len(xyz) > sample:
            # The sample's points in the map's own order (the check counts them, in any order): read in order, not
            # at random (a building's region of 150-200 k points gave its sample in 2 ms, not 4).
            xyz = xyz[np.sort(np.random.default_rng(seed).choice(len(xyz), sample, replace=False, shuffle=False))]
        self.map_xyz = xyz

    @property
    def surface_xyz(self) -> np.ndarray:
        """One map point per surface_voxel_m voxel, made on first use: a building builds the view checks of many
        regions a frame and compares depth in one (30-40 ms for a region's 200 k points)."""
        if self._surface_xyz is None:
            self._surface_xyz = self._all_xyz[voxel_indices(self._all_xyz, self._surface_voxel_m)]
        return self._surface_xyz

    @staticmethod
    def zbuffer(xyz_camera: np.ndarray, K, *, cell_px: int = 8) -> np.ndarray:
        """(rows, cols) nearest measured depth per cell of `cell_px` pixels (inf where nothing was measured).
        xyz_camera : (m, 3) frame points, camera frame; K : the depth camera's intrinsics, at the resolution the
        checks project with (`reference_camera`; the colour camera's offset of a few centimetres does not matter at
        this resolution)."""
        return ViewCheck._render(xyz_camera, np.eye(4), K, cell_px=cell_px, z_min=1e-3)

    @staticmethod
    def _render(points: np.ndarray, T_map_camera: np.ndarray, K, *, cell_px: int, z_min: float) -> np.ndarray:
        """(rows, cols) the least camera depth (beyond z_min) of the points (n, 3) seen from T_map_camera per cell of
        cell_px pixels, inf where none falls (`view_kernels.zbuffer`)."""
        out = np.full((int(np.ceil(K.height / cell_px)), int(np.ceil(K.width / cell_px))), np.inf)
        view_kernels.zbuffer(field_kernels.floats(points), *_pose(T_map_camera), K.fx, K.fy, K.cx, K.cy,
                             float(cell_px), z_min, out)
        return out

    @staticmethod
    def _cells(p: np.ndarray, K, cell_px: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row and column of the z-buffer cell each camera-frame point (z > 0) projects to, and which lie inside."""
        rows, cols = shape
        u = ((K.fx * p[:, 0] / p[:, 2] + K.cx) // cell_px).astype(np.int64)
        v = ((K.fy * p[:, 1] / p[:, 2] + K.cy) // cell_px).astype(np.int64)
        return v, u, (u >= 0) & (u < cols) & (v >= 0) & (v < rows)

    def depth_agreement(self, T_map_camera: np.ndarray, zbuf: np.ndarray, K, *, cell_px: int = 8, pool: int = 2,
                        tolerance_m: float = 0.05, tolerance_ratio: float = 0.02, max_depth_m: float = 4.0,
                        min_cells: int = 20, unseen: float = 1.0) -> float:
        """Share of the view's cells holding both measured depth and map surface in which the two agree (the
        nearest of each within tolerance_m + tolerance_ratio · depth): render and compare, on cells of
        cell_px · pool pixels (a map sample leaves finer cells empty or holding only a surface behind another).

        At the right pose the frame's depth is the map's, except where something the map lacks stands in front.
        A wrong pose can still put most frame points near some surface (the fitness: a floor and a wall fit anywhere
        along them, a counter fits a table), but along the rays the map's surfaces lie elsewhere. Cells the map has
        nothing in (the frame looks past the map) say nothing either way and are left out, so partial overlap costs
        nothing here. `unseen` when fewer than min_cells cells hold both: 1.0 for a gate (no evidence against the
        pose), 0.0 where agreement must be shown.
        """
        mapped = self.map_depth(T_map_camera, K, cell_px=cell_px * pool)
        return _agreement(_min_pool(zbuf, pool), mapped, tolerance_m=tolerance_m, tolerance_ratio=tolerance_ratio,
                          max_depth_m=max_depth_m, min_cells=min_cells, unseen=unseen)

    def compare_depth(self, T_map_camera: np.ndarray, zbuf: np.ndarray, K, xyz_camera: np.ndarray, *,
                      cell_px: int = 8, pool: int = 2, max_depth_m: float = 4.0) -> tuple[float, float]:
        """(depth agreement as `depth_agreement`, map coverage): the coverage is the share of the frame points
        `xyz_camera` (camera frame) whose cell holds some map surface, nearer than max_depth_m or not: the part
        of the frame the map can say anything about. One rendering of the map serves both."""
        mapped = self.map_depth(T_map_camera, K, cell_px=cell_px * pool)
        agreement = _agreement(_min_pool(zbuf, pool), mapped, max_depth_m=max_depth_m)
        p = xyz_camera[xyz_camera[:, 2] > 1e-3]
        v, u, inside = self._cells(p, K, cell_px * pool, mapped.shape)
        if not inside.any():
            return agreement, 0.0
        return agreement, float(np.mean(np.isfinite(mapped[v[inside], u[inside]])))

    def map_depth(self, T_map_camera: np.ndarray, K, *, cell_px: int) -> np.ndarray:
        """(rows, cols) the map's nearest surface (one point per surface voxel) per cell of `cell_px` pixels seen
        from the pose, inf where the map has none in view."""
        return self._render(self.surface_xyz, T_map_camera, K, cell_px=cell_px, z_min=0.2)

    def see_through(self, T_map_camera: np.ndarray, zbuf: np.ndarray, K, *, cell_px: int = 8, margin_m: float = 0.1,
                    margin_ratio: float = 0.04, max_depth_m: float = 4.0, min_points: int = 50) -> float:
        """Share of the map points in view (in cells where the frame measured depth, not farther than
        max_depth_m) that lie in front of the measured depth by more than margin_m + margin_ratio · depth."""
        # Against the nearest depth of the cell and its 8 neighbours: a map point on a silhouette (the top of a
        # low wall, the rim of a scan's hole) falls a cell to the far side of the depth edge as often as not, and
        # views across a building's low walls, all edges, saw through 3-5 % of the map at their true pose.
        measured = minimum_filter(zbuf, size=3, mode="nearest")
        seen, front = view_kernels.in_front(field_kernels.floats(self.map_xyz), *_pose(T_map_camera), K.fx, K.fy,
                                            K.cx, K.cy, float(cell_px), 0.2, float(max_depth_m), measured,
                                            float(margin_m), float(margin_ratio))
        return 0.0 if seen < min_points else front / seen


def reference_camera(K: CameraIntrinsics, reference_pixels: int = ZBUFFER_REFERENCE_PIXELS) -> CameraIntrinsics:
    """The camera K at the resolution of about `reference_pixels` pixels, its field of view kept: what a frame's
    z-buffer (`ViewCheck.zbuffer`) and every check against it project with, so that a cell of cell_px pixels spans the
    same angle whatever the sensor's resolution. In the sensor's own pixels an 80 x 60 frame's z-buffer held 5 x 4
    cells once pooled, and fewer than the 20 a depth comparison needs held both a measured depth and the map, which
    counts as no evidence against a pose (1.0): real RedKitchen frames shrunk to 80 x 60 were answered `ok` 0.4-1.05 m
    off (5 of 50), where at 160 x 120 and up they were held back by their depth. A 4096 x 3072 frame's cells were
    finer than the map's surface sampling."""
    scale = np.sqrt(reference_pixels / (K.width * K.height))
    if abs(scale - 1.0) < 1e-9:
        return K
    return K.scaled_to(max(1, int(round(K.width * scale))), max(1, int(round(K.height * scale))))


def _pose(T_map_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a pose as the compiled loops take them."""
    T = np.asarray(T_map_camera, dtype=np.float64)
    return np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])


def _agreement(measured: np.ndarray, mapped: np.ndarray, *, tolerance_m: float = 0.05, tolerance_ratio: float = 0.02,
               max_depth_m: float = 4.0, min_cells: int = 20, unseen: float = 1.0) -> float:
    """Share of the cells holding both a measured depth and a map surface nearer than max_depth_m in which the two
    agree within tolerance_m + tolerance_ratio · depth; `unseen` when fewer than min_cells hold both."""
    measured, mapped = measured.ravel(), mapped.ravel()
    both = np.isfinite(measured) & (mapped < max_depth_m)
    if both.sum() < min_cells:
        return unseen
    z = measured[both]
    return float(np.mean(np.abs(z - mapped[both]) < tolerance_m + tolerance_ratio * z))


def _min_pool(grid: np.ndarray, k: int) -> np.ndarray:
    """(rows, cols) -> (ceil(rows/k), ceil(cols/k)): the minimum of each k × k block (inf pads the edges)."""
    rows, cols = grid.shape
    padded = np.full((-(-rows // k) * k, -(-cols // k) * k), np.inf)
    padded[:rows, :cols] = grid
    return padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k).min(axis=(1, 3))
