"""Map enhancement (paper §2.2): replace the raw scan points of each CAD-aligned object by dense points sampled on
the aligned CAD surface, with colours carried over from the raw points they replace.

Scan points are often incomplete and noisy on furniture (thin legs, occluded backs); the CAD surface is complete,
so the enhanced map gives the refinement whole objects to lock onto. The raw points stay in the site as well.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import EnhanceConfig
from ..pointset import SOURCE_CAD, PointSet
from .graph import ObjectNode
from .objects import aabb_center, affine_box, points_in_box

@dataclass
class CadPlacement:
    """One aligned CAD model.

    mesh : trimesh.Trimesh in the CAD model's own frame.
    A_scan_cad : (4, 4) float64 affine (rotation · anisotropic scale + translation) CAD frame -> scan/map frame.
    cls : graph class; cad_id : "<synset>/<model id>".
    origin : "annotation" (a Scan2CAD file) or "auto" (cadreg/site/autocad.py); fit : the auto-alignment's fit
    (JSON-able) or None; sym : Scan2CAD symmetry name when known; trs : the Scan2CAD TRS A_scan_cad was made from
    (scan frame = map frame), when it was, so that writing it back is exact.
    """

    mesh: object
    A_scan_cad: np.ndarray
    cls: str
    cad_id: str
    origin: str = "annotation"
    fit: dict | None = None
    sym: str | None = None
    trs: object | None = None


@dataclass
class EnhancedMap:
    """The enhanced map and the CAD object nodes (ids "cad-<i>", instance i)."""

    map: PointSet
    cad_nodes: list[ObjectNode]
    removed_raw: int
    cad_fit: list[dict]  # per CAD: node id, raw points replaced, median/p90 distance of its samples to the raw scan,
    #                      origin ("annotation" | "auto") and, for auto-alignments, their fit ("auto_fit")


def sample_cad_surface(mesh_scan, spacing_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points on a mesh (already in the map frame) at about `spacing_m` mean spacing, with face normals.

    Returns points (n, 3) float64 and unit normals (n, 3) float64, oriented away from the box centre: ShapeNet
    faces are not consistently wound, and outward normals are what a sensor sees.
    """
    import trimesh

    count = max(int(np.ceil(mesh_scan.area / spacing_m**2)), 1)
    pts, face = trimesh.sample.sample_surface(mesh_scan, count, seed=seed)
    normals = np.asarray(mesh_scan.face_normals[face], dtype=np.float64)
    center = aabb_center(mesh_scan.vertices)
    flip = np.einsum("ij,ij->i", normals, pts - center) < 0
    normals[flip] *= -1
    return np.asarray(pts, dtype=np.float64), normals


def transfer_colors(targets: np.ndarray, source_points: np.ndarray, source_colors: np.ndarray, k: int) -> np.ndarray:
    """Colour per target point: inverse-distance-weighted mean of its k nearest source points.

    targets (n, 3), source_points (m, 3) float; source_colors (m, 3) uint8. Returns (n, 3) uint8.
    """
    k = min(k, len(source_points))
    d, i = cKDTree(source_points).query(targets, k=k)
    if k == 1:
        d, i = d[:, None], i[:, None]
    w = 1.0 / np.maximum(d, 1e-3)
    w /= w.sum(axis=1, keepdims=True)
    rgb = np.einsum("nk,nkc->nc", w, source_colors[i].astype(np.float64))
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)


def enhance_map(
    raw: PointSet,
    structure: np.ndarray,
    placements: list[CadPlacement],
    classes: list[str],
    config: EnhanceConfig = EnhanceConfig(),
    progress: Callable[[int, int], None] | None = None,
    seed: int = 0,
) -> EnhancedMap:
    """Put the CAD models into the raw map.

    raw : the raw scan points (instance -1, source 0).
    structure : (N,) bool, raw points known to be wall/floor/ceiling: kept even inside a box, because a box that
        stands on the floor, grown by the dilation, would otherwise punch holes into the floor and walls.
        Raw points whose class is another object class than the CAD's are kept too (objects on or under it).
    placements : the aligned CADs; CAD i becomes instance i and node "cad-<i>".
    Returns the enhanced map: kept raw points first, then each CAD's samples.
    """
    index = {c: i for i, c in enumerate(classes)}
    remove = np.zeros(len(raw), dtype=bool)
    parts: list[PointSet] = []
    nodes: list[ObjectNode] = []
    fits: list[dict] = []
    # How far each CAD's surface lies from the scan says how good the alignment is (a wrong model or pose shows up
    # here, not only later as failed registrations). Distances to raw points, not to the scan's faces: a slight
    # over-estimate of the point-to-surface distance at the raw voxel spacing.
    raw_tree = cKDTree(raw.points) if len(raw) else None
    for i, pl in enumerate(placements):
        mesh = pl.mesh.copy()
        mesh.apply_transform(pl.A_scan_cad)
        lo, hi = pl.mesh.vertices.min(axis=0), pl.mesh.vertices.max(axis=0)
        center, extent, R = affine_box(pl.A_scan_cad, lo, hi)
        cls_i = index.get(pl.cls, -1)
        # Points labelled as another object stay: a bag on a chair, a chair tucked under a table are objects of
        # their own. Unlabelled points in the box go with the CAD (labels are sparse at object borders).
        other_object = (raw.class_index >= 0) & (raw.class_index != cls_i)
        inside = points_in_box(raw.points, center, extent, R, config.box_dilation_m) & ~structure & ~other_object
        remove |= inside
        pts, nrm = sample_cad_surface(mesh, config.cad_sample_spacing_m, seed + i)
        # Colour from the raw points of this object; an object the scan barely saw borrows from its surroundings.
        src = np.flatnonzero(inside)
        if len(src) < config.color_transfer_k:
            src = np.arange(len(raw))
        colors = transfer_colors(pts, raw.points[src], raw.colors[src], config.color_transfer_k)
        n = len(pts)
        parts.append(PointSet(
            pts.astype(np.float32), colors, nrm.astype(np.float32),
            np.full(n, i, np.int32), np.full(n, cls_i, np.int16), np.full(n, SOURCE_CAD, np.uint8),
        ))
        d = raw_tree.query(pts)[0] if raw_tree is not None else None
        fits.append({"id": f"cad-{i}", "cad_id": pl.cad_id, "raw_points_replaced": int(inside.sum()),
                     "median_distance_to_scan_m": None if d is None else round(float(np.median(d)), 4),
                     "p90_distance_to_scan_m": None if d is None else round(float(np.percentile(d, 90)), 4),
                     "origin": pl.origin, **({} if pl.fit is None else {"auto_fit": pl.fit})})
        nodes.append(ObjectNode(
            id=f"cad-{i}", cls=pl.cls, centroid=aabb_center(mesh.vertices), box_center=center, box_extent=extent,
            box_R=R, source="cad", cad_id=pl.cad_id, points=n,
        ))
        if progress is not None:
            progress(i + 1, len(placements))
    kept = raw.take(np.flatnonzero(~remove))
    return EnhancedMap(PointSet.concat([kept, *parts]), nodes, int(remove.sum()), fits)
