"""Compiled loops of the free-space check (`score.ViewCheck`): points projected into a pose's coarse z-buffer.

Each check projects tens of thousands of map points (a room's 2 cm surface grid, a region's 30 k sample) into the
camera, once or twice per refined pose. As numpy passes each projection made a dozen temporaries the size of the
map (the transform, the divisions, the cell indices, the masks): 3-3.5 ms a pose for scene0470's 48 k surface
points, a tenth of that as one loop. Written here with numba: no library projects points into a min-depth grid.

A pose is T_map_camera = (R, t): a map point p lies at R^T (p - t) in the camera (OpenCV axes), summed in the order
numpy's `(p - t) @ R` sums. A point's cell is ((f · x / z + c) // cell_px) along each axis, as `ViewCheck._cells`
puts it.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _to_camera(points, i, R, t):
    dx, dy, dz = points[i, 0] - t[0], points[i, 1] - t[1], points[i, 2] - t[2]
    return (dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0], dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1],
            dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2])


@njit(cache=True, nogil=True, inline="always")
def _cell(x, y, z, fx, fy, cx, cy, cell_px):
    return int((fx * x / z + cx) // cell_px), int((fy * y / z + cy) // cell_px)


@njit(cache=True, nogil=True)
def zbuffer(points, R, t, fx, fy, cx, cy, cell_px, z_min, out):
    """out[v, u] (rows, cols) lowered to the camera depth z of each point (n, 3) seen from the pose (R, t) with
    z > z_min whose cell is (u, v)."""
    rows, cols = out.shape
    for i in range(len(points)):
        x, y, z = _to_camera(points, i, R, t)
        if not z > z_min:
            continue
        u, v = _cell(x, y, z, fx, fy, cx, cy, cell_px)
        if 0 <= u < cols and 0 <= v < rows and z < out[v, u]:
            out[v, u] = z


@njit(cache=True, nogil=True)
def in_front(points, R, t, fx, fy, cx, cy, cell_px, z_min, z_max, measured, margin_m, margin_ratio):
    """(seen, front): of the points (n, 3) seen from the pose (R, t) at a camera depth z_min < z < z_max in a cell of
    `measured` (rows, cols; inf where the frame measured nothing) holding a depth m, how many (seen) and how many of
    those lie in front of it by more than margin_m + margin_ratio · m (front)."""
    rows, cols = measured.shape
    seen, front = 0, 0
    for i in range(len(points)):
        x, y, z = _to_camera(points, i, R, t)
        if not (z > z_min and z < z_max):
            continue
        u, v = _cell(x, y, z, fx, fy, cx, cy, cell_px)
        if not (0 <= u < cols and 0 <= v < rows):
            continue
        m = measured[v, u]
        if np.isfinite(m):
            seen += 1
            if z < m - (margin_m + margin_ratio * m):
                front += 1
    return seen, front


def warm() -> None:
    """Compile (or load from numba's cache) the loops (`Localizer.warm`)."""
    p, R, t = np.zeros((1, 3)), np.eye(3), np.zeros(3)
    grid = np.full((1, 1), np.inf)
    zbuffer(p, R, t, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, grid)
    in_front(p, R, t, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0, grid, 0.1, 0.0)
