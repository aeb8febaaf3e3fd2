"""What the map shows along a frame's rays: its depth image at a pose, traced through the site's distance field.

A building repeats rooms, and copies of a room differ in what a view shows of them: a chair one copy lacks, the
next room seen over a low wall or through a door. Nearest-neighbour fitness cannot see most of that (a frame's
points still lie near the floor where a chair is missing, and surfaces the map holds but the frame never saw cost
nothing), and it weighs a far wall's sparse points like a near table's dense ones. Along the frame's own rays the
map's depth is what the sensor would have measured at that pose, so two poses can be compared as the sensor sees
them: the share of rays on which the frame and the map agree, and the share on which two poses of the map show the
same (the benchmark's repeated-view oracle asks the same of two renders).

The rays are traced through the stored distance field (sphere tracing: a step as long as the field allows, never
across an occupied cell), so no per-room structure is built and a view into any room of the building, or across
rooms, costs the same. Written here: no library traces a quantized, memory-mapped distance grid; the loop is compiled
(`field_kernels.trace`).
"""

from __future__ import annotations

import copy

import numpy as np

from ..frame import Frame
from . import field_kernels
from .score import DistanceField

# A ray hits the map in a cell holding a map point (distance 0). One step moves at most the cell's distance less
# this many voxels (the nearest point may lie anywhere in its cell, and the ray anywhere in its own: √3 voxels in
# all), at least MIN_STEP voxels: half a cell, so that no occupied cell is stepped over along an axis.
SAFETY_VOXELS = 1.8
MIN_STEP_VOXELS = 0.5
# Steps per ray at most: a ray grazing a floor or wall crawls at the smallest step; one that has not hit by then
# is counted as showing nothing.
MAX_STEPS = 96
# The first occupied cell a ray enters lies before the surface it holds: on the 10-room benchmark's renders the
# traced depth was 1.5-1.7 cm short of the measured one (median); this much is added back.
HIT_OFFSET_M = 0.015
# How far a depth camera whose range the client did not give (`Frame.depth_range_m`) is taken to measure, unless the
# frame itself measures farther: Kinect v1 and Azure Kinect (narrow, unbinned) about 4 m, a Structure sensor
# 3.5-4 m, a phone's lidar 5 m; the real 7-Scenes RedKitchen frames reach 2.7-3.6 m. Beyond its range a camera
# measures nothing whatever is there, so a map surface there on a ray it measured nothing on is no evidence
# against a pose. Real RedKitchen frames in a building holding two copies of the kitchen fused from other frames
# of the sequence (the fused kitchen open where its frames never looked): at the true pose the map showed, through
# those openings, 61 rays' worth of neighbouring rooms 4-6 m away on rays the frame measured nothing on, where the
# other copy's showed none, and four frames were answered `ok` in the other copy, 5 m off. A render's sensor
# measures every surface within its cut-off and says so (`RecordedFrames` reads it from frames.json).
DEFAULT_DEPTH_RANGE_M = 4.0
# ... and no farther than this, whatever the client says or the frame measured: a depth camera's noise grows with the
# square of the depth (several centimetres at 4 m for structured light). A depth beyond it is no measure of the
# range: a 16-bit depth image's all-ones "no depth" (65.535 m in millimetres) would otherwise lift it here.
MAX_DEPTH_RANGE_M = 6.0
# The field alignment (`align_on_field`) leaves out points where the field's gradient is weaker than this (per
# metre; 1 on a surface's slope): beyond the truncation, or inside an occupied cell, the field is flat.
MIN_GRADIENT = 0.1


class FieldView:
    """The frame's rays (a grid of depth pixels) and the depth measured along each.

    frame : the frame the rays come from. grid : (columns, rows) of rays over the depth image. min_depth_m,
    max_depth_m : the sensor's range (depth along the optical axis): nearer or farther counts as nothing seen, in
    the frame and in the map's renders alike; max_depth_m None: `sensor_range_m` of the frame's `depth_range_m` and
    the depths measured along the rays.
    T_color_depth moves the rays into the colour camera, whose pose (T_map_camera) the renders take.
    """

    def __init__(self, frame: Frame, *, grid: tuple[int, int] = (48, 36), min_depth_m: float = 0.4,
                 max_depth_m: float | None = None) -> None:
        K = frame.depth_intrinsics
        cols, rows = grid
        u = ((np.arange(cols) + 0.5) * K.width / cols).astype(np.int64)
        v = ((np.arange(rows) + 0.5) * K.height / rows).astype(np.int64)
        uu, vv = np.meshgrid(u, v)
        uu, vv = uu.ravel(), vv.ravel()
        z = frame.depth[vv, uu].astype(np.float64) / frame.depth_scale
        if max_depth_m is None:
            max_depth_m = sensor_range_m(frame.depth_range_m, z)
        self.measured = np.where((z >= min_depth_m) & (z <= max_depth_m), z, np.inf)  # (r,) depth along z
        d = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones(len(uu))], axis=1)  # z = 1 in depth frame
        T = np.asarray(frame.T_color_depth, dtype=np.float64)
        self.dirs_camera = d @ T[:3, :3].T  # (r, 3) per unit of depth, colour-camera frame
        self.origin_camera = T[:3, 3].copy()
        self.min_depth_m, self.max_depth_m = float(min_depth_m), float(max_depth_m)
        self.shape = (rows, cols)

    def thinned(self, step: int) -> "FieldView":
        """The same view on every step-th ray of every step-th row (a quarter of the rays for 2): a cheaper look
        at many poses before the full one at the few that matter. Its rays are `thinned_rays(step)` of this view's."""
        rows, cols = self.shape
        out = self._rays(self.thinned_rays(step))
        out.shape = ((rows + step - 1) // step, (cols + step - 1) // step)
        return out

    def thinned_rays(self, step: int) -> np.ndarray:
        """Indices of the rays `thinned(step)` keeps, in its order."""
        rows, cols = self.shape
        return np.arange(rows * cols).reshape(rows, cols)[::step, ::step].ravel()

    def render_completing(self, field: DistanceField, T_map_camera: np.ndarray, rays: np.ndarray,
                          rendered: np.ndarray) -> np.ndarray:
        """`render` at poses whose depths along some of the rays are known already: rendered (h, len(rays)) along
        `rays` (indices into this view's rays); the other rays are traced. Each ray is traced on its own, so this is
        `render` exactly, for the rays' share less of the cost."""
        T = np.asarray(T_map_camera, dtype=np.float64).reshape(-1, 4, 4)
        out = np.empty((len(T), len(self)))
        rest = np.setdiff1d(np.arange(len(self)), rays)
        out[:, rays] = rendered
        out[:, rest] = self._rays(rest).render(field, T)
        return out

    def _rays(self, index: np.ndarray) -> "FieldView":
        """The same view on the rays `index` (its shape is this view's until the caller sets it)."""
        out = copy.copy(self)
        out.measured, out.dirs_camera = self.measured[index], self.dirs_camera[index]
        return out

    def __len__(self) -> int:
        return len(self.measured)

    def render(self, field: DistanceField, T_map_camera: np.ndarray) -> np.ndarray:
        """(h, r) depth (along the depth camera's axis) of the first map surface on each ray at each pose, inf
        where the ray meets none within the sensor's range. T_map_camera : (h, 4, 4) or (4, 4)."""
        T = np.asarray(T_map_camera, dtype=np.float64).reshape(-1, 4, 4)
        out = np.empty((len(T), len(self)))
        vox = field.voxel_m
        field_kernels.trace(*field.kernel_args(), field_kernels.floats(T[:, :3, :3]), field_kernels.floats(T[:, :3, 3]),
                            field_kernels.floats(self.origin_camera), field_kernels.floats(self.dirs_camera), self.min_depth_m,
                            self.max_depth_m, SAFETY_VOXELS * vox, MIN_STEP_VOXELS * vox, MAX_STEPS, HIT_OFFSET_M, out)
        return out

    def agreement(self, rendered: np.ndarray, other: np.ndarray | None = None, *, tolerance_m: float = 0.04,
                  tolerance_ratio: float = 0.02) -> np.ndarray:
        """(h,) share of the rays with a surface in either view on which both show one at the same depth (within
        tolerance_m + tolerance_ratio · depth): of each render in `rendered` (h, r) against the frame's measured
        depth, or against `other` (r,) or (h, r), another render (two poses of the map compared as a sensor
        would see them). 1.0 where neither view shows anything."""
        rendered = np.atleast_2d(rendered)
        ref = np.broadcast_to(self.measured if other is None else other, rendered.shape)
        a, b = np.isfinite(rendered), np.isfinite(ref)
        either = (a | b).sum(axis=1)
        near = np.minimum(rendered, ref)
        with np.errstate(invalid="ignore"):
            both = a & b & (np.abs(rendered - ref) < tolerance_m + tolerance_ratio * near)
        return np.where(either > 0, both.sum(axis=1) / np.maximum(either, 1), 1.0)

    def shared(self, rendered: np.ndarray, *, tolerance_m: float = 0.04, tolerance_ratio: float = 0.02,
               min_rays: int = 20) -> tuple[float, float]:
        """(depth agreement, map coverage) of one render (r,), as `score.ViewCheck.compare_depth` gives them: the
        share of the rays with a depth in both the frame and the map on which the two agree, and the share of the
        frame's measured rays on which the map shows a surface. (1.0, coverage) when fewer than min_rays hold
        both: no evidence against the pose."""
        a, b = np.isfinite(rendered), np.isfinite(self.measured)
        both = a & b
        coverage = float(both.sum() / max(b.sum(), 1))
        if both.sum() < min_rays:
            return 1.0, coverage
        z = np.minimum(rendered[both], self.measured[both])
        close = np.abs(rendered[both] - self.measured[both]) < tolerance_m + tolerance_ratio * z
        return float(close.mean()), coverage


def sensor_range_m(given_m: float | None, measured_m: np.ndarray) -> float:
    """The farthest depth (metres) at which a frame's camera would have measured a surface: the client's range
    (given_m, `Frame.depth_range_m`), else DEFAULT_DEPTH_RANGE_M, or the farthest of the depths measured along the
    view's rays (measured_m, metres, 0 = none) when that is farther; at most MAX_DEPTH_RANGE_M, and a depth beyond
    it is no measure. Along the rays, not over every pixel: a stray far pixel moves it only where a ray meets it."""
    within = measured_m[(measured_m > 0) & (measured_m <= MAX_DEPTH_RANGE_M)]
    reach = float(within.max()) if len(within) else 0.0
    return min(max(DEFAULT_DEPTH_RANGE_M if given_m is None else given_m, reach), MAX_DEPTH_RANGE_M)


def align_on_field(field: DistanceField, points_camera: np.ndarray, R: np.ndarray, t: np.ndarray, *,
                   up: np.ndarray | None = None, iterations: int = 10,
                   reach_m: tuple[float, float] = (0.25, 0.06)) -> tuple[np.ndarray, np.ndarray]:
    """Many poses pulled onto the map at once, by Gauss-Newton on the distance field: each minimizes the squared
    field distance of the frame points it places (a point-to-surface ICP whose correspondences the field holds),
    with the points farther than a reach that shrinks from reach_m[0] to reach_m[1] left out.

    points_camera : (m, 3) frame points (colour camera). R : (h, 3, 3), t : (h, 3) starting poses (map frame).
    up : the map's unit up when the frame's is known: the poses then turn about it only (x, y, z, yaw), as the
    graph's hypotheses were made; else all six degrees of freedom move. Returns the moved (R, t).

    What a coarse GICP against a region's map did, without a region map: a building's tied rooms are all pulled in
    from the one stored field. The field's gradient is taken by central differences one voxel wide (exact to a
    few millimetres at the field's 3 cm cells, enough to start the fine refinement from).
    """
    R, t = np.array(R, dtype=np.float64), np.array(t, dtype=np.float64)
    if len(R) == 0 or len(points_camera) == 0:
        return R, t
    field_kernels.align(*field.kernel_args(), field_kernels.floats(points_camera), R, t,
                        field_kernels.floats(np.zeros(3) if up is None else up), up is not None, iterations,
                        float(reach_m[0]), float(reach_m[1]), MIN_GRADIENT)
    return R, t
