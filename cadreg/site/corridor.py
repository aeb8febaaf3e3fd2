"""A building's corridors: plain hallways between the rows of its rooms, for the building benchmark.

A corridor is a floor strip walled on its four sides, in its own frame: x along it from 0 to `length_m`, y across it
from -width_m/2 to +width_m/2, z up from its floor (z = 0) to the top of its walls (`height_m`); its entry in a layout
places that frame in the building (`compose.CorridorEntry.T_building_corridor`). No scan gives such a thing, so it is
made here, the one part of a benchmark building that is not a real scan: five flat panels (floor, two side walls,
two end walls) in two plain colours, labelled NYU40 floor and wall. The composer samples the panels into the map
(`corridor_cloud`), the renderer casts rays at them (`render.building.corridor_mesh`): one geometry for both.

What a corridor puts to the localizer is what a bare hallway does: its views show floor and wall and no object, the
same all along it and at either end, and alike in every corridor of the same size, so that no view of one can be
placed for sure: the right answer is never a confident wrong pose.

    Panel, corridor_panels(length, width, height)   the five panels (corridor frame)
    panel_grid(panel, step_m)                        a panel's points on a grid, with its normal
    corridor_cloud(length, width, height, spacing)   the panels sampled as a PointSet (corridor frame)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..pointset import PointSet

# NYU40 ids of what a corridor is made of.
FLOOR_LABEL = 2
WALL_LABEL = 1
# A pale floor and off-white walls: a painted hallway gives colour nothing to hold on to.
FLOOR_RGB = (150, 140, 125)
WALL_RGB = (214, 212, 204)


@dataclass(frozen=True)
class Panel:
    """A flat rectangle: origin (3,) a corner, u and v (3,) its two edges from there (metres, corridor frame),
    normal (3,) unit, facing into the corridor; label (NYU40 id) and rgb of its surface."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    label: int
    rgb: tuple[int, int, int]


def corridor_panels(length_m: float, width_m: float, height_m: float) -> list[Panel]:
    """The floor, the two side walls (y = ±width/2) and the two end walls (x = 0, x = length) of a corridor, each
    facing inwards."""
    L, W, H = float(length_m), float(width_m), float(height_m)
    x, y, z = np.eye(3)
    return [
        Panel(np.array([0.0, -W / 2, 0.0]), L * x, W * y, z, FLOOR_LABEL, FLOOR_RGB),
        Panel(np.array([0.0, -W / 2, 0.0]), L * x, H * z, y, WALL_LABEL, WALL_RGB),
        Panel(np.array([0.0, W / 2, 0.0]), L * x, H * z, -y, WALL_LABEL, WALL_RGB),
        Panel(np.array([0.0, -W / 2, 0.0]), W * y, H * z, x, WALL_LABEL, WALL_RGB),
        Panel(np.array([L, -W / 2, 0.0]), W * y, H * z, -x, WALL_LABEL, WALL_RGB),
    ]


def panel_grid(panel: Panel, step_m: float) -> tuple[np.ndarray, int, int]:
    """((nu, nv, 3) float64 points on a regular grid spanning the panel, corners included, at most step_m apart
    along each edge; nu, nv)."""
    nu = max(2, int(np.ceil(np.linalg.norm(panel.u) / step_m)) + 1)
    nv = max(2, int(np.ceil(np.linalg.norm(panel.v) / step_m)) + 1)
    a, b = np.meshgrid(np.linspace(0.0, 1.0, nu), np.linspace(0.0, 1.0, nv), indexing="ij")
    return panel.origin + a[..., None] * panel.u + b[..., None] * panel.v, nu, nv


def corridor_cloud(length_m: float, width_m: float, height_m: float, spacing_m: float) -> PointSet:
    """The corridor's panels sampled every `spacing_m` (corridor frame): scanned structure, no class, no
    instance. The edges the panels share are sampled once per panel (a corner holds a few duplicates, as a
    scan's does)."""
    points, normals, colors = [], [], []
    for panel in corridor_panels(length_m, width_m, height_m):
        grid, _, _ = panel_grid(panel, spacing_m)
        xyz = grid.reshape(-1, 3)
        points.append(xyz)
        normals.append(np.broadcast_to(panel.normal, xyz.shape))
        colors.append(np.broadcast_to(np.array(panel.rgb, dtype=np.uint8), xyz.shape))
    return PointSet.scanned(np.concatenate(points).astype(np.float32), np.concatenate(colors),
                            np.concatenate(normals).astype(np.float32))
