"""Pictures of a site (paper Fig. 5): a top view of the enhanced map coloured by class, with the semantic graph.

`draw_site_top_view(ax, site)` draws onto any matplotlib Axes (the localize picture reuses it);
`render_site_png(site)` returns PNG bytes (the runner writes them). Matplotlib's Agg backend: no display needed.
"""

from __future__ import annotations

import io

import numpy as np

from .bundle import Site
from .regions import Region, Storeys

_MAX_DRAWN_POINTS = 60000
_AUTO_CAD_MARKER = "D"  # CAD nodes from automatic alignment are diamonds (annotated ones: squares)


def auto_cad_ids(site: Site) -> set[str]:
    """Ids of the CAD nodes that came from automatic alignment (`site build --auto-cad`)."""
    return {f["id"] for f in site.manifest.get("enhance", {}).get("cads", []) if f.get("origin") == "auto"}


def class_colors(n: int) -> np.ndarray:
    """(n, 3) float RGB in [0, 1], one distinct colour per class index (tab20, then hsv)."""
    from matplotlib import colormaps

    tab = colormaps["tab20"](np.arange(20))[:, :3]
    if n <= 20:
        return tab[:n]
    return np.vstack([tab, colormaps["hsv"](np.linspace(0, 1, n - 20, endpoint=False))[:, :3]])


def draw_site_top_view(ax, site: Site, *, max_points: int = _MAX_DRAWN_POINTS, seed: int = 0,
                       draw_graph: bool = True, label_nodes: bool = True, storey: int | None = None) -> None:
    """Top view (x right, y up, map frame, metres) of `site` on `ax`.

    Points without a class are grey, object points take their class colour (CAD points drawn on top); nodes are
    markers (CAD: filled squares when annotated, filled diamonds when auto-aligned; cluster: hollow circles)
    labelled "<class>", edges are thin lines. storey : only that storey of a building of several (`Storeys`): its
    points, objects and rooms (seen from above the storeys overlap).
    """
    auto = auto_cad_ids(site)
    storeys = Storeys.of(site.regions)

    def on(z: np.ndarray) -> np.ndarray:  # (n,) heights -> (n,) bool: on the storey drawn
        return np.ones(len(z), dtype=bool) if storey is None else storeys.at(z) == storey

    rng = np.random.default_rng(seed)
    pool = np.flatnonzero(on(site.map.points[:, 2]))
    n = len(pool)
    idx = pool[rng.choice(n, size=min(n, max_points), replace=False)] if n > max_points else pool
    # draw low points first so that a table top covers the floor under it
    idx = idx[np.argsort(site.map.points[idx, 2], kind="stable")]
    p = site.map.points[idx]
    c = site.map.class_index[idx]
    palette = class_colors(len(site.classes))
    plain = c < 0
    ax.scatter(p[plain, 0], p[plain, 1], s=0.3, c=[(0.72, 0.72, 0.72)], linewidths=0, rasterized=True)
    ax.scatter(p[~plain, 0], p[~plain, 1], s=0.6, c=palette[c[~plain]], linewidths=0, rasterized=True)
    if draw_graph:
        nodes = site.graph.nodes
        heights = np.array([node.centroid[2] for node in nodes])
        shown = {node.id for node, keep in zip(nodes, on(heights)) if keep}
        for a, b in site.graph.graph.edges():
            if a not in shown or b not in shown:
                continue
            pa, pb = site.graph.node(a).centroid, site.graph.node(b).centroid
            ax.plot([pa[0], pb[0]], [pa[1], pb[1]], color="0.25", lw=0.6, alpha=0.7, zorder=3)
        for node in (node for node in nodes if node.id in shown):
            k = site.classes.index(node.cls) if node.cls in site.classes else -1
            col = palette[k] if k >= 0 else (0, 0, 0)
            if node.source == "cad":
                auto_node = node.id in auto
                ax.scatter([node.centroid[0]], [node.centroid[1]], marker=_AUTO_CAD_MARKER if auto_node else "s",
                           s=80 if auto_node else 60, c=[col], edgecolors="k", linewidths=1.2, zorder=4)
            else:
                ax.scatter([node.centroid[0]], [node.centroid[1]], marker="o", s=60, facecolors="none",
                           edgecolors=[col], linewidths=2.0, zorder=4)
            if label_nodes:
                ax.annotate(node.cls, node.centroid[:2], xytext=(4, 4), textcoords="offset points", fontsize=7,
                            zorder=5)
    if len(site.regions) > 1:
        _draw_regions(ax, [r for r, k in zip(site.regions, storeys.region) if storey is None or k in (storey, -1)])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _draw_regions(ax, regions: list[Region]) -> None:
    """Each region's box outline, named at its corner (a building's rooms)."""
    from matplotlib.patches import Rectangle

    for r in regions:
        (x0, y0, _), (x1, y1, _) = r.bounds
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="tab:blue", lw=0.9, zorder=6))
        ax.annotate(r.id, (x0, y1), xytext=(2, -8), textcoords="offset points", fontsize=6, color="tab:blue",
                    zorder=6)


def render_site_png(site: Site, *, dpi: int = 150) -> bytes:
    """PNG bytes of the top view with a legend (CAD vs cluster nodes) and a title naming the site."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    # A building of several storeys: one panel a storey, ground floor first (seen from above they overlap).
    storeys = Storeys.of(site.regions)
    panels = list(range(len(storeys.base))) if storeys.several else [None]
    fig = Figure(figsize=(8 * len(panels), 7 if len(panels) == 1 else 5))
    axes = [fig.add_subplot(1, len(panels), k + 1) for k in range(len(panels))]
    for ax, storey in zip(axes, panels):
        # A building's hundreds of class names would hide its rooms: nodes are named only in small sites.
        draw_site_top_view(ax, site, label_nodes=len(site.regions) <= 4, storey=storey)
        if storey is not None:
            ax.set_title(f"storey {storey}: floor {storeys.base[storey]:.2f} m", fontsize=9)
    n_cad = sum(1 for n in site.graph.nodes if n.source == "cad")
    n_auto = len(auto_cad_ids(site))
    title = (f"site {site.site_id} v{site.version}: {len(site.graph.nodes)} objects "
             f"({n_cad} CAD{f', {n_auto} auto-aligned' if n_auto else ''}), "
             f"{site.graph.graph.number_of_edges()} edges")
    if storeys.several:
        fig.suptitle(title)
    else:
        axes[0].set_title(title)
    ax = axes[0]
    handles = [
        Line2D([], [], marker="s", ls="", mfc="w", mec="k", label="CAD node (annotation)"),
        Line2D([], [], marker="o", ls="", mfc="none", mec="k", label="cluster node"),
        Line2D([], [], marker=".", ls="", color="0.72", label="no class (wall, floor, ...)"),
    ]
    if len(site.regions) > 1:
        handles.append(Line2D([], [], color="tab:blue", lw=0.9, label=f"region ({len(site.regions)})"))
    if n_auto:
        handles.insert(1, Line2D([], [], marker=_AUTO_CAD_MARKER, ls="", mfc="w", mec="k",
                                 label="CAD node (auto-aligned)"))
    ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()
