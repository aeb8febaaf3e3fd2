"""A picture of one localization (paper Fig. 6–9): the frame's points placed by the result over the map's top
view, the matched graph nodes and the camera frustum. Returns PNG bytes; the runner writes them.
"""

from __future__ import annotations

import io

import numpy as np

from ..frame import Frame
from ..geometry import transform_points
from ..result import LocalizationResult
from ..site.bundle import Site
from .points import frame_to_points, voxel_downsample


def frustum_map(T_map_camera: np.ndarray, frame: Frame, depth_m: float = 1.0) -> np.ndarray:
    """(5, 3) map-frame points: the camera centre and the four image corners at `depth_m`."""
    K = frame.color_intrinsics
    corners = np.array([[0, 0], [K.width - 1, 0], [K.width - 1, K.height - 1], [0, K.height - 1]], dtype=float)
    rays = np.stack([(corners[:, 0] - K.cx) / K.fx, (corners[:, 1] - K.cy) / K.fy, np.ones(4)], axis=1) * depth_m
    return transform_points(T_map_camera, np.vstack([np.zeros(3), rays]))


def render_localization_png(site: Site, frame: Frame, result: LocalizationResult, *, localizer=None, dpi: int = 150,
                            T_true: np.ndarray | None = None) -> bytes:
    """PNG bytes: map top view, frame points (by height) at the estimated pose, matched nodes, frustum."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from ..site.show import draw_site_top_view

    fig = Figure(figsize=(8, 7))
    ax = fig.add_subplot(1, 1, 1)
    draw_site_top_view(ax, site, label_nodes=True)
    title = f"frame {result.frame_id}: {result.status.value}, {result.diagnostics.method}"
    if result.T_map_camera is not None:
        T = np.asarray(result.T_map_camera)
        pts = voxel_downsample(frame_to_points(frame), 0.03)
        p = transform_points(T, pts.xyz)
        # One strong colour: the frame's own colours would vanish among the map's.
        ax.scatter(p[:, 0], p[:, 1], s=2.5, c="tab:blue", linewidths=0, alpha=0.8, zorder=6, rasterized=True,
                   label="frame points")
        f = frustum_map(T, frame, depth_m=float(np.median(pts.xyz[:, 2])))
        for k in range(1, 5):
            ax.plot([f[0, 0], f[k, 0]], [f[0, 1], f[k, 1]], color="red", lw=1.2, zorder=7)
        ax.plot(f[[1, 2, 3, 4, 1], 0], f[[1, 2, 3, 4, 1], 1], color="red", lw=1.2, zorder=7)
        nodes = {str(n.id): n for n in site.graph.nodes}
        for m in result.diagnostics.matches:
            if m.node_id in nodes and m.scan_object < len(result.diagnostics.scan_objects):
                c_scan = transform_points(T, np.asarray([result.diagnostics.scan_objects[m.scan_object].centroid]))[0]
                c_map = np.asarray(nodes[m.node_id].centroid)
                ax.plot([c_scan[0], c_map[0]], [c_scan[1], c_map[1]], color="magenta", lw=1.5, zorder=8)
                ax.scatter([c_map[0]], [c_map[1]], s=120, facecolors="none", edgecolors="magenta", linewidths=2, zorder=8)
        title += f", confidence {result.confidence:.2f}"
    if T_true is not None:
        f = frustum_map(np.asarray(T_true), frame, depth_m=0.5)
        for k in range(1, 5):
            ax.plot([f[0, 0], f[k, 0]], [f[0, 1], f[k, 1]], color="green", lw=1.0, ls="--", zorder=7)
    ax.set_title(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()
