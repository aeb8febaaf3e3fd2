"""A labelled triangle mesh to render query frames from (map frame, metres, z up).

Object instances are not stored in ScanNet's `*.labels.ply` (class labels only), yet the renderer must count the
objects a view sees: an instance here is a connected component of the mesh restricted to one object label
(vertices joined by an edge of a face whose ends share the label). Structure labels (wall, floor, ceiling,
unlabeled, other structure) are never instances.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..errors import InvalidArgument, InvalidFileError
from ..labels import NYU40, STRUCTURE_CLASSES
from ..site.bundle import Site


def structure_label_ids(label_set: str = "nyu40") -> frozenset[int]:
    """Label ids that are the building rather than objects in it (NYU40: 0, 1, 2, 22, 38)."""
    if label_set != "nyu40":
        return frozenset({0})
    return frozenset(i for i, name in NYU40.items() if name in STRUCTURE_CLASSES)


@dataclass
class LabelledMesh:
    """vertices : (n, 3) float64 metres, map frame; faces : (m, 3) int32; colors : (n, 3) uint8 RGB;
    labels : (n,) uint16 label ids in `label_set` or None; instances : (n,) int32 object instance per vertex,
    -1 for structure / unlabelled (computed from labels when not given)."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    labels: np.ndarray | None = None
    label_set: str = "nyu40"
    instances: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int32)
        self.colors = np.asarray(self.colors, dtype=np.uint8)
        n = len(self.vertices)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or n == 0:
            raise InvalidArgument(f"vertices must be (n, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise InvalidArgument(f"faces must be (m, 3) with m > 0, got {self.faces.shape}")
        if self.faces.min() < 0 or self.faces.max() >= n:
            raise InvalidArgument("face indices out of range")
        if self.colors.shape != (n, 3):
            raise InvalidArgument(f"colors must be ({n}, 3), got {self.colors.shape}")
        if self.labels is not None:
            self.labels = np.asarray(self.labels).astype(np.uint16)
            if self.labels.shape != (n,):
                raise InvalidArgument(f"labels must be ({n},), got {self.labels.shape}")
            if self.instances is None:
                self.instances = object_instances(self.faces, self.labels, structure_label_ids(self.label_set))
        if self.instances is not None:
            self.instances = np.asarray(self.instances, dtype=np.int32)

    @property
    def n_instances(self) -> int:
        return 0 if self.instances is None else int(self.instances.max(initial=-1)) + 1

    def floor_height_m(self) -> float:
        """z of the floor: median of floor-labelled vertices (NYU40 2) when there are enough, else a low percentile."""
        z = self.vertices[:, 2]
        if self.labels is not None and self.label_set == "nyu40":
            floor = z[self.labels == 2]
            if len(floor) >= 100:
                return float(np.median(floor))
        return float(np.percentile(z, 1.0))

    @classmethod
    def from_ply(cls, mesh_path: str | Path, labels_path: str | Path | None = None) -> "LabelledMesh":
        """Read a coloured mesh PLY (and ScanNet-style per-vertex `label` from `labels_path` or the mesh itself)."""
        from ..io.ply import read_scan

        scan = read_scan(mesh_path, labels_path)
        if scan.faces is None or len(scan.faces) == 0:
            raise InvalidFileError(mesh_path, "has no faces: the renderer needs a triangle mesh")
        return cls(scan.points, scan.faces, scan.colors, scan.labels)

    def write_ply(self, path: str | Path) -> None:
        """Write the mesh as a scan PLY `from_ply` and `site build --scan` read: the vertices its faces use (a
        building's copy of a room keeps the vertices of the objects it lacks, unreferenced: `site build` reads a
        scan's vertices as its points), their colours and, when it has labels, their `label`; the faces."""
        from ..io.ply import scan_ply_bytes

        used, faces = np.unique(self.faces, return_inverse=True)
        Path(path).write_bytes(scan_ply_bytes(self.vertices[used].astype(np.float32), self.colors[used],
                                              faces.reshape(-1, 3), None if self.labels is None else self.labels[used]))


def object_instances(faces: np.ndarray, labels: np.ndarray, structure: frozenset[int]) -> np.ndarray:
    """(n,) int32 instance id per vertex: connected components of same-label object vertices; -1 for structure."""
    n = len(labels)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    la, lb = labels[edges[:, 0]], labels[edges[:, 1]]
    is_obj = ~np.isin(labels, np.fromiter(structure, dtype=np.int64)) if structure else np.ones(n, bool)
    keep = (la == lb) & is_obj[edges[:, 0]]
    e = edges[keep]
    graph = sp.coo_matrix((np.ones(len(e), np.int8), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    out = np.full(n, -1, dtype=np.int32)
    obj_idx = np.flatnonzero(is_obj)
    if len(obj_idx):
        _, dense = np.unique(comp[obj_idx], return_inverse=True)
        out[obj_idx] = dense.astype(np.int32)
    return out


def mesh_from_site(site: Site, *, poisson_depth: int = 8, trim_quantile: float = 0.03) -> LabelledMesh:
    """A renderable mesh of a site whose source mesh is not at hand (fused sites, bundles copied alone).

    Screened Poisson reconstruction (Open3D) of the site's raw scan points with their normals and colours; vertices
    of low support density and those outside the points' box are trimmed (Poisson closes holes with invented
    surface). Labels come from the nearest raw point's class, mapped back to the site's NYU40 ids (the first id of
    each class); structure gets 0, so the floor height falls back to a low percentile. A coarser, smoother stand-in
    for the scan: at depth 8 the grid is 1/256 of the site's extent.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    raw = site.cloud("raw")
    pts = raw.points.astype(np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(raw.rgb01())
    pcd.normals = o3d.utility.Vector3dVector(raw.normals.astype(np.float64))
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=poisson_depth, n_threads=1)
    density = np.asarray(density)
    lo, hi = pts.min(axis=0) - 0.02, pts.max(axis=0) + 0.02
    v = np.asarray(mesh.vertices)
    drop = (density < np.quantile(density, trim_quantile)) | np.any((v < lo) | (v > hi), axis=1)
    mesh.remove_vertices_by_mask(drop)
    mesh.remove_unreferenced_vertices()
    v = np.asarray(mesh.vertices)
    colors = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    _, nearest = cKDTree(pts).query(v)
    cls = raw.class_index[nearest]
    nyu = site.label_maps.get("nyu40", {})
    first_id: dict[str, int] = {}
    for label_id, name in sorted(nyu.items()):
        first_id.setdefault(name, int(label_id))
    lut = np.array([first_id.get(c, 0) for c in site.classes] + [0], dtype=np.uint16)  # index -1 -> 0
    labels = lut[np.where(cls >= 0, cls, len(site.classes))]
    return LabelledMesh(v, np.asarray(mesh.triangles), colors, labels, label_set="nyu40")
