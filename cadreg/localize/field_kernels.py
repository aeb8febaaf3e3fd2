"""Compiled loops over a distance grid: gathers, many poses' scores, sphere-traced rays, the field alignment and
the label-free search's bounds.

A building's frame reads its distance field tens of millions of times (thousands of hypotheses scored, hundreds of
poses aligned and rendered along the frame's rays). As numpy passes, each read cost a dozen temporaries (a cell
index per axis, clipped, scaled, summed) and each traced step a gather of every live ray's state; the loops below
read each cell once, in the cache order of the points, with no temporaries. Written here with numba: no library
gathers from a quantized (or float) grid under many poses, or sphere-traces one. The cell of a coordinate is
floor((c - origin) / voxel) + 1, clamped to the grid's one-cell border (`score.DistanceField`: it reads the
truncation distance), and a NaN coordinate reads the border.

grid : flat (uint8 steps of `scale` metres, or float32 metres with scale 1.0), C order over dims + 2 cells a side.
origin : (3,) map frame, metres. voxel : metres. hi : (3,) float, the last cell index per axis (dims + 1).
strides : (3,) int64 flat strides of the padded grid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Rays traced together (`trace`) and cells read together (`lookup`): enough independent reads in flight, few
# enough for the batch's state to stay in the first-level cache.
TRACE_BATCH = 256
LOOKUP_BATCH = 1024
# `score_poses` of a grid without a table of its values' scores (a float grid).
NO_TABLE = np.zeros(0)


def floats(a: np.ndarray) -> np.ndarray:
    """`a` as the loops take their float arrays: C-ordered, writable float64, copied only when it is not (numba
    compiles the loops once per type of argument, and a read-only or strided array is another type)."""
    return np.require(a, np.float64, ["C", "W"])


def read_only(grid: np.ndarray) -> np.ndarray:
    """A grid as the loops take it: a plain, read-only view (a memory map opened for reading is read-only, a grid
    built in memory is not; one type for both)."""
    view = grid.view(np.ndarray)
    view.flags.writeable = False
    return view


@njit(cache=True, nogil=True, inline="always")
def _cell(origin, voxel, hi, strides, x, y, z):
    flat = _axis(x, origin[0], voxel, hi[0]) * strides[0]
    flat += _axis(y, origin[1], voxel, hi[1]) * strides[1]
    flat += _axis(z, origin[2], voxel, hi[2]) * strides[2]
    return flat


@njit(cache=True, nogil=True, inline="always")
def _axis(c, origin, voxel, hi):
    # A division, not a product with the inverse: points on cell boundaries (a coarser grid's centres) must read the
    # cell numpy's (c - origin) / voxel puts them in.
    return _index((c - origin) / voxel + 1.0, hi)


@njit(cache=True, nogil=True, inline="always")
def _index(u, hi):
    # floor(u) for u = (c - origin) / voxel + 1, which truncation gives once it is known to be >= 0 (no call to
    # floor), clamped to the border.
    if not u >= 0.0:  # negative, or NaN
        return np.int64(0)
    return np.int64(min(u, hi))


@njit(cache=True, nogil=True, inline="always")
def _cell_of_units(hi, strides, u, v, w):
    """The flat cell of a point given in cell units, (x - origin) / voxel + 1 an axis (`_cell` less its divisions).
    The loops over arbitrary poses (scores, rays, the field alignment) fold the division into each pose's or ray's
    few constants: three divisions a read were a quarter of a 100-room frame's first look. (Arbitrary poses put no
    point on a cell boundary, where the product with the inverse could round across one: on every benchmark set
    the same cells were read, the same answers given.)"""
    return _index(u, hi[0]) * strides[0] + _index(v, hi[1]) * strides[1] + _index(w, hi[2]) * strides[2]


@njit(cache=True, nogil=True)
def lookup(grid, scale, origin, voxel, hi, strides, x, y, z, out):
    """out[i] = the field's distance at (x[i], y[i], z[i]), metres (flat float arrays of one length)."""
    cells = np.empty(LOOKUP_BATCH, dtype=np.int64)
    for first in range(0, len(x), LOOKUP_BATCH):
        count = min(LOOKUP_BATCH, len(x) - first)
        for j in range(count):  # the cells, then the reads (`score_poses`)
            cells[j] = _cell(origin, voxel, hi, strides, x[first + j], y[first + j], z[first + j])
        for j in range(count):
            out[first + j] = grid[cells[j]] * scale


@njit(cache=True, nogil=True, inline="always")
def _pose_cells(origin, voxel, hi, strides, points, r, s, cells):
    """cells[i] = the flat cell of r · points[i] + s (the pose scaled to cell units once, `_cell_of_units`)."""
    inv = 1.0 / voxel
    a00, a01, a02 = r[0, 0] * inv, r[0, 1] * inv, r[0, 2] * inv
    a10, a11, a12 = r[1, 0] * inv, r[1, 1] * inv, r[1, 2] * inv
    a20, a21, a22 = r[2, 0] * inv, r[2, 1] * inv, r[2, 2] * inv
    b0, b1, b2 = (s[0] - origin[0]) * inv + 1.0, (s[1] - origin[1]) * inv + 1.0, (s[2] - origin[2]) * inv + 1.0
    for i in range(len(points)):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        cells[i] = _cell_of_units(hi, strides, a00 * px + a01 * py + a02 * pz + b0, a10 * px + a11 * py + a12 * pz + b1,
                                  a20 * px + a21 * py + a22 * pz + b2)


@njit(cache=True, nogil=True)
def score_poses(grid, scale, origin, voxel, hi, strides, points, R, rot, t, tau, table, out):
    """out[h] = mean over the points of max(0, 1 - (d / tau)²), d the field's distance at R[rot[h]] · p + t[h].
    points : (m, 3) camera frame; R : (u, 3, 3) rotations, rot : (h,) the one of each pose (`match.Hypotheses`
    shares a table among a yaw sweep's poses); t : (h, 3). table : for a quantized (uint8) grid, (256,) the score
    of a cell holding each value (`quantized_scores`: the same sums, bit for bit, for a read of the table instead of
    a product, a division and a branch a point; a building's frame scores 50-250 k poses), else empty."""
    m = len(points)
    cells = np.empty(m, dtype=np.int64)
    by_table = len(table) > 0
    for h in range(len(t)):
        # The cells first, then the reads: independent reads of a large grid overlap in the memory system, reads
        # interleaved with the arithmetic of the next cell do not (one loop was slower than numpy's passes).
        _pose_cells(origin, voxel, hi, strides, points, R[rot[h]], t[h], cells)
        total = 0.0
        for i in range(m):
            if by_table:  # (the cast: numba types this branch for a float grid too, which never takes it)
                total += table[np.int64(grid[cells[i]])]
                continue
            d = grid[cells[i]] * scale / tau
            if d < 1.0:
                total += 1.0 - d * d
        out[h] = total / max(m, 1)


def quantized_scores(scale: float, tau: float) -> np.ndarray:
    """(256,) float64: the score `score_poses` gives a cell holding g, for each g of a uint8 grid of steps of
    `scale` metres (computed as the loop computes it: (g · scale) / tau, then 1 − d² below 1, else 0)."""
    d = np.arange(256, dtype=np.float64) * float(scale) / float(tau)
    return np.where(d < 1.0, 1.0 - d * d, 0.0)


@njit(cache=True, nogil=True)
def trace(grid, scale, origin, voxel, hi, strides, R, t, origin_camera, dirs_camera, min_depth, max_depth,
          safety, min_step, max_steps, hit_offset, out):
    """out[h, r] = depth (per unit of the ray's direction) of the first occupied cell (distance 0) along ray r at
    pose h, plus hit_offset; inf when none lies within max_depth or max_steps steps, and when the first lies nearer
    than min_depth: the sensor measures nothing there, and what lies behind it is hidden (a ray traced from
    min_depth on saw through a wall a camera stood close to, into the corridor or the room behind it). Each step
    advances by the cell's distance less `safety` metres, at least `min_step` metres, over the ray's length per
    unit depth. R : (h, 3, 3); t : (h, 3); origin_camera : (3,); dirs_camera : (r, 3), per unit depth."""
    n_rays = len(dirs_camera)
    n = len(R) * n_rays
    # Rays advance in batches, a step of each live ray of a batch at a time: a ray's next read waits on its last,
    # and only the reads of different rays can overlap (one ray at a time was no faster than numpy's passes).
    o = np.empty((TRACE_BATCH, 3))
    d = np.empty((TRACE_BATCH, 3))
    per_depth = np.empty(TRACE_BATCH)
    depth = np.empty(TRACE_BATCH)
    live = np.empty(TRACE_BATCH, dtype=np.int64)
    cells = np.empty(TRACE_BATCH, dtype=np.int64)
    flat_out = out.reshape(-1)
    inv = 1.0 / voxel
    for first in range(0, n, TRACE_BATCH):
        count = min(TRACE_BATCH, n - first)
        for j in range(count):
            h, k = divmod(first + j, n_rays)
            r_, s = R[h], t[h]
            for a in range(3):
                o[j, a] = r_[a, 0] * origin_camera[0] + r_[a, 1] * origin_camera[1] + r_[a, 2] * origin_camera[2] + s[a]
                d[j, a] = r_[a, 0] * dirs_camera[k, 0] + r_[a, 1] * dirs_camera[k, 1] + r_[a, 2] * dirs_camera[k, 2]
            per_depth[j] = math.sqrt(d[j, 0] ** 2 + d[j, 1] ** 2 + d[j, 2] ** 2)
            for a in range(3):  # the ray in cell units from here on (`_cell_of_units`)
                o[j, a] = (o[j, a] - origin[a]) * inv + 1.0
                d[j, a] *= inv
            depth[j] = 0.0
            live[j] = j
            flat_out[first + j] = np.inf
        n_live = count
        for _ in range(max_steps):
            if n_live == 0:
                break
            for q in range(n_live):
                j = live[q]
                cells[q] = _cell_of_units(hi, strides, o[j, 0] + d[j, 0] * depth[j], o[j, 1] + d[j, 1] * depth[j],
                                          o[j, 2] + d[j, 2] * depth[j])
            kept = 0
            for q in range(n_live):
                j = live[q]
                dist = grid[cells[q]] * scale
                if dist <= 1e-6:
                    if depth[j] + hit_offset >= min_depth:
                        flat_out[first + j] = depth[j] + hit_offset
                    continue
                depth[j] += max(dist - safety, min_step) / per_depth[j]
                if depth[j] <= max_depth:
                    live[kept] = j
                    kept += 1
            n_live = kept


@njit(cache=True, nogil=True)
def align(grid, scale, origin, voxel, hi, strides, points, R, t, up, turn_about_up, iterations, reach_first,
          reach_last, min_gradient):
    """Gauss-Newton on the field, in place on R (h, 3, 3) and t (h, 3) (`field_view.align_on_field` documents the
    method): each pose minimizes the squared field distance of the points (m, 3, camera frame) it places, the
    points farther than the reach (shrinking geometrically from reach_first to reach_last) or on a gradient
    weaker than min_gradient left out; the gradient by central differences one voxel wide. turn_about_up: the
    rotation turns about `up` only (4 degrees of freedom), else freely (6)."""
    m = len(points)
    dof = 4 if turn_about_up else 6
    cells = np.empty((m, 7), dtype=np.int64)
    q = np.empty((m, 3))
    inv = 1.0 / voxel
    offsets = np.zeros((7, 3))  # the point and its neighbours a voxel away along each axis, in cell units
    for a in range(3):
        offsets[1 + 2 * a, a] = 1.0
        offsets[2 + 2 * a, a] = -1.0
    J, step = np.empty(6), np.empty(dof)
    for h in range(len(R)):
        r_, s = R[h], t[h]
        for k in range(iterations):
            reach = reach_first * (reach_last / reach_first) ** (k / max(1, iterations - 1))
            for i in range(m):
                for a in range(3):
                    q[i, a] = r_[a, 0] * points[i, 0] + r_[a, 1] * points[i, 1] + r_[a, 2] * points[i, 2] + s[a]
                u = (q[i, 0] - origin[0]) * inv + 1.0
                v = (q[i, 1] - origin[1]) * inv + 1.0
                w = (q[i, 2] - origin[2]) * inv + 1.0
                for o in range(7):  # the cells first, then the reads (`score_poses`)
                    cells[i, o] = _cell_of_units(hi, strides, u + offsets[o, 0], v + offsets[o, 1], w + offsets[o, 2])
            H = np.zeros((dof, dof))
            for u in range(dof):
                H[u, u] = 1e-6
            b = np.zeros(dof)
            used = 0
            for i in range(m):
                d = grid[cells[i, 0]] * scale
                if not d < reach:
                    continue
                gx = (grid[cells[i, 1]] * scale - grid[cells[i, 2]] * scale) / (2 * voxel)
                gy = (grid[cells[i, 3]] * scale - grid[cells[i, 4]] * scale) / (2 * voxel)
                gz = (grid[cells[i, 5]] * scale - grid[cells[i, 6]] * scale) / (2 * voxel)
                if gx * gx + gy * gy + gz * gz <= min_gradient * min_gradient:
                    continue
                used += 1
                # d(distance)/d(rotation about the map origin) is q x g; d/d(translation) is g
                cx = q[i, 1] * gz - q[i, 2] * gy
                cy = q[i, 2] * gx - q[i, 0] * gz
                cz = q[i, 0] * gy - q[i, 1] * gx
                if turn_about_up:
                    J[0] = cx * up[0] + cy * up[1] + cz * up[2]
                    J[1], J[2], J[3] = gx, gy, gz
                else:
                    J[0], J[1], J[2], J[3], J[4], J[5] = cx, cy, cz, gx, gy, gz
                for u in range(dof):
                    b[u] -= J[u] * d  # -Jᵀ d: the Gauss-Newton step solves H step = b
                    for v in range(dof):
                        H[u, v] += J[u] * J[v]
            if used < 3 * dof:  # too few points within reach: the pose stays
                continue
            if not _solve_positive_definite(H, b, step):  # (a NaN, or rounding past the damping): the pose stays
                continue
            if turn_about_up:
                wx, wy, wz = step[0] * up[0], step[0] * up[1], step[0] * up[2]
            else:
                wx, wy, wz = step[0], step[1], step[2]
            dR = _rotation(wx, wy, wz)
            _turn_in_place(dR, r_)
            s0, s1, s2 = s[0], s[1], s[2]
            for a in range(3):
                s[a] = dR[a, 0] * s0 + dR[a, 1] * s1 + dR[a, 2] * s2 + step[dof - 3 + a]


@njit(cache=True, nogil=True)
def _rotation(wx, wy, wz):
    """The rotation (3, 3) of the rotation vector (wx, wy, wz) (Rodrigues), I + sin θ K + (1 - cos θ) K², element by
    element (as loops: see `_turn_in_place`)."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    K = np.empty((3, 3))
    K[0, 0], K[0, 1], K[0, 2] = 0.0, -wz, wy
    K[1, 0], K[1, 1], K[1, 2] = wz, 0.0, -wx
    K[2, 0], K[2, 1], K[2, 2] = -wy, wx, 0.0
    R = np.empty((3, 3))
    if theta < 1e-12:
        for a in range(3):
            for c in range(3):
                R[a, c] = (1.0 if a == c else 0.0) + K[a, c]
        return R
    for a in range(3):
        for c in range(3):
            K[a, c] /= theta
    sin, one_less_cos = math.sin(theta), 1.0 - math.cos(theta)
    for a in range(3):
        for c in range(3):
            K2 = K[a, 0] * K[0, c] + K[a, 1] * K[1, c] + K[a, 2] * K[2, c]
            R[a, c] = (1.0 if a == c else 0.0) + sin * K[a, c] + one_less_cos * K2
    return R


# `align`'s small linear algebra by hand, as loops, and why: numba compiles its bindings of np.linalg.solve and of
# the matrix product, and each array expression, for each module that uses them: 7 of the 26 s a cold cache's first
# start took (a fresh install's first server or demo), for a 6 x 6 system and 3 x 3 products.
@njit(cache=True, nogil=True)
def _turn_in_place(A, B):
    """B (3, n) <- A (3, 3) @ B, column by column."""
    for c in range(B.shape[1]):
        b0, b1, b2 = B[0, c], B[1, c], B[2, c]
        for a in range(3):
            B[a, c] = A[a, 0] * b0 + A[a, 1] * b1 + A[a, 2] * b2


@njit(cache=True, nogil=True)
def _solve_positive_definite(H, b, x):
    """x <- H⁻¹ b, H (n, n) symmetric positive definite (a Gauss-Newton system with its damping), by Cholesky.
    Returns False, x unset, where H is not (a pivot not above naught, or NaN)."""
    n = len(b)
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = H[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i != j:
                L[i, j] = acc / L[j, j]
            elif acc > 0.0:
                L[i, i] = math.sqrt(acc)
            else:
                return False
    for i in range(n):  # L y = b
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):  # Lᵀ x = y
        acc = x[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return True


@njit(cache=True, nogil=True)
def sums_at(grid, offsets, rows, bases, out):
    """out[a] = the sum of grid[offsets[rows[a], i] + bases[a]] over i: the label-free search's bound of a node
    (`bbs.GridPyramid.search`: a yaw's row of point offsets from a corner cell). grid : flat uint8;
    offsets : (k, n) int64; rows, bases : (a,) int64; out : (a,) int64."""
    for a in range(len(rows)):
        out[a] = _row_sum(grid, offsets[rows[a]], bases[a])


@njit(cache=True, nogil=True, inline="always")
def _row_sum(grid, row, base):
    """The sum of grid[row[i] + base] over i: one node's bound."""
    total = 0
    for i in range(len(row)):
        total += grid[row[i] + base]
    return total


@njit(cache=True, nogil=True)
def child_sums(grid, offsets, strides, hi, step, rows, cells, out_rows, out_cells, out):
    """The label-free search's children of nodes (`bbs.GridPyramid.search`) with their bounds, in one pass: for each
    node a (its yaw's row rows[a] of point offsets, its corner cell cells[a] (3,)), the cubes whose corners lie
    `step` cells or none further along each axis (x outermost, z innermost), those within hi (inclusive) kept, in
    that order, into out_rows and out_cells, each with `sums_at`'s sum over grid (its level) at its corner in out.
    Returns how many were written (at most 8 a node). What numpy's broadcasts, mask and product did in five passes
    over 8 × the nodes' arrays (8 ms of a 100-room frame's search), with the same children in the same order and
    the same integer sums."""
    count = 0
    for a in range(len(rows)):
        row = offsets[rows[a]]
        for di in (0, step):
            c0 = cells[a, 0] + di
            if c0 > hi[0]:
                continue
            for dj in (0, step):
                c1 = cells[a, 1] + dj
                if c1 > hi[1]:
                    continue
                for dk in (0, step):
                    c2 = cells[a, 2] + dk
                    if c2 > hi[2]:
                        continue
                    out_rows[count] = rows[a]
                    out_cells[count, 0], out_cells[count, 1], out_cells[count, 2] = c0, c1, c2
                    out[count] = _row_sum(grid, row, c0 * strides[0] + c1 * strides[1] + c2 * strides[2])
                    count += 1
    return count


@njit(cache=True, nogil=True)
def occupied_cubes(grid, dims, threshold, thin, blocks, out):
    """out[c] <- True for each cube c of thin³ cells (flat, C order over `blocks` = ceil(dims / thin) cubes a side)
    that holds a cell of the grid (dims (3,) cells a side, border included) at most `threshold`:
    `DistanceField.surface_points` in one pass over the grid. numpy's mask, cell indices and unique over them took
    1.9 s of a 100-room worker's start."""
    for i in range(dims[0]):
        ci = (i // thin) * blocks[1]
        for j in range(dims[1]):
            cj = (ci + j // thin) * blocks[2]
            row = (i * dims[1] + j) * dims[2]
            for k in range(dims[2]):
                if grid[row + k] <= threshold:
                    out[cj + k // thin] = True


# The kinds of grid a distance field holds: a stored (building's) field quantized to bytes, a one-room field built
# at load in metres. The label-free search's pyramid is bytes either way.
FIELD_DTYPES = (np.uint8, np.float32)


def warm(field_dtypes: tuple[type[np.generic], ...] = FIELD_DTYPES) -> None:
    """Compile (or load from numba's cache) every loop for the kinds of grid given (`FIELD_DTYPES`: those a site's
    field may hold), so that no frame pays for it: a first compilation takes seconds, a cached one a fraction of
    one."""
    for dtype in field_dtypes:
        grid = np.zeros(27, dtype=dtype)
        args = (read_only(grid), 1.0, np.zeros(3), 1.0, np.full(3, 2.0), np.array([9, 3, 1], dtype=np.int64))
        one = np.zeros(1)
        lookup(*args, one, one, one, np.empty(1, dtype=np.float32))
        R, t, p = np.eye(3)[None], np.zeros((1, 3)), np.zeros((1, 3))
        rot = np.zeros(1, dtype=np.int64)
        score_poses(*args, p, R, rot, t, 0.1, NO_TABLE, np.empty(1))
        if grid.dtype == np.uint8:
            score_poses(*args, p, R, rot, t, 0.1, quantized_scores(1.0, 0.1), np.empty(1))
        trace(*args, R, t, np.zeros(3), np.array([[0.0, 0.0, 1.0]]), 0.5, 1.0, 0.1, 0.1, 4, 0.0, np.empty((1, 1)))
        for about_up in (True, False):
            align(*args, p, R.copy(), t.copy(), np.array([0.0, 0.0, 1.0]), about_up, 1, 0.5, 0.1, 0.1)
        occupied_cubes(args[0], np.full(3, 3, dtype=np.int64), 0.5, 2, np.full(3, 2, dtype=np.int64),
                       np.zeros(8, dtype=np.bool_))
    pyramid = read_only(np.zeros(27, dtype=np.uint8))
    sums_at(pyramid, np.zeros((1, 1), dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
            np.empty(1, dtype=np.int64))
    child_sums(pyramid, np.zeros((1, 1), dtype=np.int64), np.array([9, 3, 1], dtype=np.int64),
               np.ones(3, dtype=np.int64), 1, np.zeros(1, dtype=np.int64), np.zeros((1, 3), dtype=np.int64),
               np.empty(8, dtype=np.int64), np.empty((8, 3), dtype=np.int64), np.empty(8, dtype=np.int64))
