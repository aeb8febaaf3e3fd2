"""Build a site from a scan (+ labels, + Scan2CAD alignments and a CAD library), or from labelled points.

    build_site(scan_ply, labels_ply=..., scan2cad_json=..., cad_root=..., auto_cad=..., site_id=...) -> Site
    site_from_labelled_points(points, colors, normals, labels, site_id=..., inputs=..., cad_root=..., auto_cad=...)
        -> Site  (CADs only from automatic alignment)
    auto_cad_document(site) -> Scan2CAD records of a site's CADs (None unless built with auto_cad)

Steps: read -> voxel down-sample the raw scan -> [automatic CAD alignment of the labelled instances no annotation
covers (cadreg/site/autocad.py)] -> enhance with CADs (paper §2.2) -> cluster the labelled points no CAD covers
into object nodes -> semantic graph (paper §2.3.2) -> Site (call `site.save(dir)` to write the bundle).
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..config import AutoCadConfig, GraphConfig, SiteBuildConfig
from ..errors import InvalidArgument, InvalidFileError
from ..io.bundle_files import sha256_file
from ..io.cad import cad_model_path, load_cad_mesh
from ..io.ply import ScanPoints, read_scan
from ..io.scan2cad import TRS, read_scan2cad, select_scan
from ..labels import GRAPH_CLASSES, NYU40, STRUCTURE_CLASSES, default_label_maps, labels_to_class_index, synset_class
from ..localize.gravity import map_up_axis
from ..pointset import SOURCE_RAW, PointSet
from .bundle import Site
from .enhance import CadPlacement, EnhancedMap, enhance_map
from .graph import ObjectNode, build_graph
from .objects import Cluster, aabb_center, affine_box, classwise_clusters, merge_stacked, points_in_box, upright_box
from .partition import partitioned

Progress = Callable[[int, int], None]
log = logging.getLogger("cadreg.site")


# Points sampled on a scan mesh's large triangles at most (`sample_large_triangles`): 10 M take about 2 GB while they
# are made, and cover 2250 m² of triangles at the default 1.5 cm spacing.
MAX_TRIANGLE_SAMPLES = 10_000_000


# A site's distance field holds one byte a 3 cm cell over the box of its map, 0.3 m wider a side
# (`score.building_field`, `score.DistanceField`): a scan whose box would need more cells than this is refused before
# anything is built. A building of 120 x 80 x 10 m needs 3.8 G; a room scanned in millimetres (3.5 km
# across) or three stray vertices 2 km away asked for 10^11-10^14, and the build ran the machine out of memory.
MAX_FIELD_CELLS = 4_000_000_000
FIELD_VOXEL_M = 0.03
FIELD_MARGIN_M = 0.3
# A Scan2CAD model lies on the scan it annotates: the median distance of its surface to the scan's points was 1.9-4.6
# cm for scene0470's seven. One farther than this is refused, naming the file (`_check_annotation_fits`): the
# annotation of a y-up copy of the scan put its CADs 58-117 cm off, and the site built without a word answered
# `ok` where it was wrong.
MAX_ANNOTATION_MEDIAN_M = 0.15
# A scan whose surfaces put its up farther than this from +z is warned of (`_warn_of_its_frame_and_labels`).
MAX_UP_TILT_DEG = 20.0
# The surfaces of a scan made from inside face where it was scanned from: at each side of its box (the floor, the
# ceiling, the outer walls) the points whose normal lies along that side's axis face into the box. When more than this
# share of them face out, the mesh's winding (or its stored normals) is reversed and every normal is turned: the
# localizer takes a surface seen from behind as no evidence (`Localizer._seen_from_behind`), and a scan with
# reversed winding built without a word and placed no frame (0 of 50 renders, all `uncertain`).
REVERSED_SHARE = 0.8
SIDE_BAND_M = 0.15
MIN_SIDE_POINTS = 100


def _check_extent(path: Path, xyz: np.ndarray) -> None:
    """InvalidFileError when the scan's box would need more than MAX_FIELD_CELLS field cells (module text)."""
    extent = xyz.max(axis=0).astype(np.float64) - xyz.min(axis=0)
    cells = float(np.prod(np.ceil((extent + 2 * FIELD_MARGIN_M) / FIELD_VOXEL_M) + 2))
    if cells > MAX_FIELD_CELLS:
        size = " x ".join(f"{e:,.1f}" for e in extent)
        raise InvalidFileError(path, f"spans {size} m: its distance field would hold {cells:.2g} cells of "
                                     f"{FIELD_VOXEL_M * 100:.0f} cm, more than a site may ({MAX_FIELD_CELLS:.0g}). Is "
                                     "it in millimetres (scale it to metres), or are there stray vertices far from "
                                     "the rest (remove them)?")


def _facing_inward(scan: ScanPoints) -> ScanPoints:
    """The scan with every normal turned when most of those at the sides of its box face out of it (REVERSED_SHARE;
    the scan as it is when they face in, or too few points say)."""
    if scan.normals is None or not len(scan.points):
        return scan
    xyz, n = scan.points.astype(np.float64), scan.normals.astype(np.float64)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    inward = outward = 0
    for axis in range(3):
        along = np.abs(n[:, axis]) > 0.9
        sides = ((xyz[:, axis] <= lo[axis] + SIDE_BAND_M, 1.0), (xyz[:, axis] >= hi[axis] - SIDE_BAND_M, -1.0))
        for side, into in sides:
            facing = n[along & side, axis] * into
            inward += int(np.count_nonzero(facing > 0))
            outward += int(np.count_nonzero(facing < 0))
    if inward + outward < MIN_SIDE_POINTS or outward <= REVERSED_SHARE * (inward + outward):
        return scan
    log.warning("the scan's normals face out of it at the sides of its box (%d of %d points): its winding is "
                "reversed, and every normal is turned", outward, inward + outward)
    return replace(scan, normals=-scan.normals)


def _warn_of_its_frame_and_labels(scan: ScanPoints) -> None:
    """Warnings (the build goes on) for a scan whose surfaces put its up elsewhere than +z, which the build takes as
    up (objects clustered and boxed, CADs aligned and rooms cut along it: a y-up scene0470 built its chairs as seats
    and bases apart, and auto-CAD aligned none of 8), and for labels none of which is an NYU40 id (raw category ids
    of 1000 and up gave no object, without a word)."""
    if scan.normals is not None and len(scan.normals):
        up = map_up_axis(scan.normals.astype(np.float64), points=scan.points.astype(np.float64))
        if abs(float(up[2])) < np.cos(np.radians(MAX_UP_TILT_DEG)):
            log.warning("the scan's surfaces put its up along (%.2f, %.2f, %.2f), not +z, which the build takes as up: "
                        "turn it z-up (objects are clustered, CADs aligned and rooms cut along z)", *up)
    if scan.labels is not None and len(scan.labels) and not np.isin(scan.labels, list(NYU40)).any():
        log.warning("none of the scan's labels (ids %d to %d) is an NYU40 id: no object is made from them",
                    int(scan.labels.min()), int(scan.labels.max()))


def _check_annotation_fits(fits: list[dict[str, Any]], inputs: dict[str, Any]) -> None:
    """InvalidFileError naming the Scan2CAD file when a CAD it aligns lies more than MAX_ANNOTATION_MEDIAN_M from the
    scan (the median distance of its surface samples to the raw points, `enhance_map`)."""
    off = [f for f in fits if f["origin"] == "annotation" and f["median_distance_to_scan_m"] is not None
           and f["median_distance_to_scan_m"] > MAX_ANNOTATION_MEDIAN_M]
    if off:
        listed = ", ".join(f"{f['id']} ({f['cad_id']}) {100 * f['median_distance_to_scan_m']:.0f} cm" for f in off)
        raise InvalidFileError(inputs["scan2cad"]["path"],
                               f"{len(off)} of the {len(fits)} CAD models it aligns lie farther than "
                               f"{100 * MAX_ANNOTATION_MEDIAN_M:.0f} cm from the scan (the median distance of their "
                               f"surfaces; a fitting alignment lies within a few cm): {listed}. Is it the annotation "
                               "of another scan, or of this one in another frame (z up, metres)?")


def _stage(progress: Progress | None, base: int, span: int, total: int) -> Progress | None:
    """Map a stage's own (done, of) onto the build's overall 0..total scale."""
    if progress is None:
        return None
    return lambda done, of: progress(base + int(span * done / max(of, 1)), total)


def voxel_representatives(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices (sorted, int64) of one point per occupied voxel of size voxel_m (the first one in input order).

    A representative, not a mean, so colour, normal and label stay those of a real scan point.
    """
    if voxel_m <= 0 or len(points) == 0:
        return np.arange(len(points))
    keys = np.floor(np.asarray(points, np.float64) / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def estimate_normals(points: np.ndarray, radius_m: float = 0.1, max_nn: int = 30) -> np.ndarray:
    """(n, 3) float32 unit normals by Open3D's local PCA, oriented towards the scan's centroid (inside a room)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=max_nn))
    pcd.orient_normals_towards_camera_location(np.asarray(points, np.float64).mean(axis=0))
    return np.asarray(pcd.normals, dtype=np.float32)


def _structure_mask(labels: np.ndarray | None, label_set: str, n: int) -> np.ndarray:
    if labels is None or label_set != "nyu40":
        return np.zeros(n, dtype=bool)
    ids = np.array([i for i, name in NYU40.items() if name in STRUCTURE_CLASSES and name != "unlabeled"])
    return np.isin(labels, ids)


def _remnant_of(pts: np.ndarray, cls: str, cad_nodes: list[ObjectNode], margin_m: float) -> ObjectNode | None:
    """The CAD node of the same class whose box, grown by margin_m, holds most of these points, if any."""
    for node in cad_nodes:
        if node.cls == cls and points_in_box(pts, node.box_center, node.box_extent, node.box_R, margin_m).mean() > 0.5:
            return node
    return None


def object_clusters(points: np.ndarray, class_index: np.ndarray, graph: GraphConfig,
                    progress: Progress | None = None) -> list[Cluster]:
    """Object instances of labelled points: class-wise Euclidean clustering, then stacked parts of one piece of
    furniture merged (the graph's cluster nodes and the instances auto-CAD fits are made alike)."""
    clusters = classwise_clusters(points, class_index, graph.cluster_tolerance_m, graph.min_cluster_points, progress)
    if graph.stacked_merge_overlap > 0:
        clusters = merge_stacked(points, clusters, graph.stacked_merge_overlap)
    return clusters


def _cluster_nodes(
    enhanced: PointSet, classes: list[str], cad_nodes: list[ObjectNode], config: SiteBuildConfig,
    progress: Progress | None,
) -> list[ObjectNode]:
    """Nodes from class-wise clustering of the labelled raw points no CAD replaced; sets their instance ids.

    Clusters that are leftovers of a CAD object (same class, next to its box) join that CAD's instance instead.
    """
    free = np.flatnonzero((enhanced.source == SOURCE_RAW) & (enhanced.instance < 0) & (enhanced.class_index >= 0))
    clusters = object_clusters(enhanced.points[free], enhanced.class_index[free], config.graph, progress)
    nodes: list[ObjectNode] = []
    for cl in clusters:
        idx = free[cl.indices]
        pts = enhanced.points[idx]
        owner = _remnant_of(pts, classes[cl.class_index], cad_nodes, config.graph.remnant_margin_m)
        if owner is not None:
            enhanced.instance[idx] = int(owner.id.split("-")[1])
            continue
        j = len(nodes)
        enhanced.instance[idx] = len(cad_nodes) + j
        center, extent, R = upright_box(pts)
        nodes.append(ObjectNode(
            id=f"cluster-{j}", cls=classes[cl.class_index], centroid=aabb_center(pts), box_center=center,
            box_extent=extent, box_R=R, source="cluster", cad_id=None, points=len(idx),
        ))
    return nodes


def _assemble(
    raw: PointSet, structure: np.ndarray, placements: list[CadPlacement], *, site_id: str, inputs: dict[str, Any],
    label_set: str, config: SiteBuildConfig, progress: Progress | None, total: int, base: int,
    auto_report: dict[str, Any] | None = None,
) -> Site:
    classes = list(GRAPH_CLASSES)
    enhanced: EnhancedMap = enhance_map(raw, structure, placements, classes, config.enhance,
                                        _stage(progress, base, 5, total))
    _check_annotation_fits(enhanced.cad_fit, inputs)
    m = enhanced.map
    cluster_nodes = _cluster_nodes(m, classes, enhanced.cad_nodes, config, _stage(progress, base + 5, 2, total))
    graph = build_graph(enhanced.cad_nodes + cluster_nodes, config.graph.edge_max_m)
    if progress is not None:
        progress(total, total)
    meta = {
        "site_id": site_id,
        "built_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "cadreg_version": __version__,
        "inputs": inputs,
        "label_set": label_set,
        "build_config": config.model_dump(mode="json"),
        "enhance": {"cad_models": len(placements), "raw_points_replaced": enhanced.removed_raw,
                    "cads": enhanced.cad_fit},
    }
    if auto_report is not None:
        auto_report["scan2cad"] = _scan2cad_records(site_id, placements)
        meta["enhance"]["auto_cad"] = auto_report
    site = partitioned(Site(site_id=site_id, version="", manifest=meta, map=m, raw=raw, graph=graph, classes=classes,
                            label_maps=default_label_maps()), config.partition)
    site.refresh_version()
    return site


def _annotated(center: np.ndarray, cls: str, annotated: list[CadPlacement], margin_m: float) -> bool:
    """True when the box centre of an instance lies in the (grown) box of an annotated CAD of its class."""
    for pl in annotated:
        if pl.cls != cls:
            continue
        verts = np.asarray(pl.mesh.vertices)
        box_c, box_e, box_R = affine_box(pl.A_scan_cad, verts.min(axis=0), verts.max(axis=0))
        if points_in_box(center[None], box_c, box_e, box_R, margin_m)[0]:
            return True
    return False


def auto_cad_placements(
    raw: PointSet, structure: np.ndarray, annotated: list[CadPlacement], library, *, config: SiteBuildConfig,
    auto: AutoCadConfig, classes: list[str],
) -> tuple[list[CadPlacement], dict[str, Any]]:
    """CAD placements found by aligning `library` (an autocad.CadLibrary) to the labelled instances of `raw`.

    Instances are the build's object clusters of the raw labelled points (`object_clusters`); those of a class the
    library has no model of, smaller than `auto.min_instance_points`, or covered by an `annotated` CAD are left
    alone (they become cluster nodes, or stay the annotated object). Returns the accepted placements (origin
    "auto", in instance order) and a JSON-able report: per instance the fit of every model tried, and notes.
    """
    from .autocad import AlignJob, align_instances, model_data, support_height

    t0 = time.perf_counter()
    labelled = np.flatnonzero(raw.class_index >= 0)
    clusters = object_clusters(raw.points[labelled], raw.class_index[labelled], config.graph)
    covered = library.classes()
    notes = list(library.notes)
    uncovered: dict[str, int] = {}
    jobs: list[AlignJob] = []
    n_annotated = n_small = 0
    for cl in clusters:
        cls = classes[cl.class_index]
        pts = raw.points[labelled[cl.indices]].astype(np.float64)
        if cls not in covered:
            uncovered[cls] = uncovered.get(cls, 0) + 1
            continue
        if len(pts) < auto.min_instance_points:
            n_small += 1
            continue
        if _annotated(upright_box(pts)[0], cls, annotated, auto.annotated_margin_m):
            n_annotated += 1
            continue
        jobs.append(AlignJob(len(jobs), cls, pts, support_height(raw, structure, pts, auto.support_search_m),
                             [model_data(m) for m in library.of_class(cls)], auto))
    if uncovered:
        listed = ", ".join(f"{c} ({n})" for c, n in sorted(uncovered.items()))
        notes.append(f"the CAD library has no model of these classes (instances): {listed}; they stay cluster nodes")
    results = align_instances(jobs, auto.workers)
    placements: list[CadPlacement] = []
    for r in results:
        if r.accepted is None:
            best = r.fits[0]
            c = r.center
            notes.append(f"no CAD model fits the {r.cls} at ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) (best {best.cad_id}: "
                         f"{best.fit.to_dict()}): it stays a cluster node")
            continue
        m = library.model(r.accepted.cad_id)
        # Placed through the TRS the Scan2CAD file stores, so that rebuilding from that file (--scan2cad) uses the
        # very same matrix: the same bundle, not one that differs in the last bit of a float.
        trs = TRS.from_affine(r.accepted.A_map_cad)
        placements.append(CadPlacement(m.mesh, trs.matrix(), m.cls, m.cad_id, origin="auto",
                                       fit=r.accepted.fit.to_dict(), sym=r.accepted.sym, trs=trs))
    # At debug: the report carries the notes, and `site build` / `site fuse` print them (`note: ...`); at info the
    # CLI's console showed each twice.
    for note in notes[len(library.notes):]:
        log.debug("auto-cad: %s", note)
    report = {
        "library": str(library.root), "library_models": len(library.models), "config": auto.model_dump(mode="json"),
        "instances": [r.to_dict() for r in results], "aligned": len(placements),
        "annotated_instances": n_annotated, "small_instances": n_small, "notes": notes,
        "elapsed_s": round(time.perf_counter() - t0, 2),
    }
    return placements, report


def _scan2cad_records(site_id: str, placements: list[CadPlacement]) -> list[dict[str, Any]]:
    """Every CAD of the site (annotated ones too, re-expressed in the map frame) as a Scan2CAD file's records."""
    from .autocad import aligned_model_record, scan2cad_record

    models = []
    for pl in placements:
        verts = np.asarray(pl.mesh.vertices)
        extra = {"origin": pl.origin, **({} if pl.fit is None else {"fit": pl.fit})}
        trs = pl.trs if pl.trs is not None else TRS.from_affine(pl.A_scan_cad)
        models.append(aligned_model_record(pl.cad_id, trs, verts.min(axis=0), verts.max(axis=0), pl.sym, **extra))
    return [scan2cad_record(site_id, models)]


def auto_cad_document(site: Site) -> list[dict[str, Any]] | None:
    """The Scan2CAD records (JSON-able) of a site built with auto-CAD, for a runner to write beside the bundle
    (`cadreg.io.scan2cad.write_scan2cad`); None for sites built without."""
    auto = site.manifest.get("enhance", {}).get("auto_cad")
    return None if auto is None else auto.get("scan2cad")


def _auto_cad(
    raw: PointSet, structure: np.ndarray, annotated: list[CadPlacement], cad_root, auto: AutoCadConfig,
    config: SiteBuildConfig, has_labels: bool, inputs: dict[str, Any],
) -> tuple[list[CadPlacement], dict[str, Any]]:
    from .autocad import load_library

    if cad_root is None:
        raise InvalidArgument("auto-CAD needs cad_root (the CAD library)")
    if not has_labels:
        raise InvalidArgument("auto-CAD needs per-point labels: it fits CAD models to labelled object instances")
    library = load_library(cad_root, auto.seed)
    inputs["cad_root"] = str(cad_root)
    models = dict(inputs.get("cad_models", {}))
    models.update({m.cad_id: sha256_file(m.path) for m in library.models})
    inputs["cad_models"] = models
    found, report = auto_cad_placements(raw, structure, annotated, library, config=config, auto=auto,
                                        classes=list(GRAPH_CLASSES))
    return annotated + found, report


def sample_large_triangles(scan: ScanPoints, *, min_edge_m: float, spacing_m: float, seed: int = 0,
                           max_samples: int = MAX_TRIANGLE_SAMPLES) -> ScanPoints:
    """The scan with points added on its triangles that have an edge longer than min_edge_m, about one per
    spacing_m² of their area, each with its triangle's colour and normal interpolated and the label of its nearest
    corner. A mesh decimated to large triangles (Replica's office0: 25 k vertices over 100 m², edges up to 0.4 m)
    leaves a map of its vertices sparse, where the distance field (3 cm cells) and GICP need a surface every few
    centimetres: on renders of office0 without labels, 52 % of the frames were placed against its vertices, 85 %
    against them and these samples. A scan whose triangles are all smaller comes back as it is (ScanNet's meshes:
    edges under 9 cm, vertices every 2-3 cm). At most max_samples are added (a mesh of a whole building gets them
    spread thinner, and a malformed one with huge triangles cannot exhaust memory). trimesh samples the triangles;
    numpy interpolates what they carry."""
    if scan.faces is None or not len(scan.faces) or min_edge_m <= 0:
        return scan
    import trimesh

    v = scan.points.astype(np.float64)
    f = scan.faces
    longest = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).max(axis=1)
    large = f[longest > min_edge_m]
    if not len(large):
        return scan
    mesh = trimesh.Trimesh(vertices=v, faces=large, process=False)
    count = int(min(np.ceil(mesh.area / spacing_m ** 2), max_samples))
    xyz, face, w = trimesh.sample.sample_surface(mesh, count, return_barycentric=True, seed=seed)
    corners = large[face]  # (n, 3) vertex indices of each sample's triangle
    colors = np.einsum("nk,nkc->nc", w, scan.colors[corners].astype(np.float64))
    normals = None
    if scan.normals is not None:
        sampled = np.einsum("nk,nkc->nc", w, scan.normals[corners].astype(np.float64))
        sampled /= np.maximum(np.linalg.norm(sampled, axis=1, keepdims=True), 1e-12)
        normals = np.concatenate([scan.normals, sampled.astype(np.float32)])
    labels = None
    if scan.labels is not None:
        labels = np.concatenate([scan.labels, scan.labels[corners[np.arange(len(corners)), np.argmax(w, axis=1)]]])
    return ScanPoints(points=np.concatenate([scan.points, xyz.astype(np.float32)]),
                      colors=np.concatenate([scan.colors, np.clip(np.rint(colors), 0, 255).astype(np.uint8)]),
                      normals=normals, labels=labels, faces=scan.faces)


def _raw_pointset(points, colors, normals, labels, label_set: str, voxel_m: float) -> tuple[PointSet, np.ndarray]:
    keep = voxel_representatives(points, voxel_m)
    pts = np.asarray(points, np.float32)[keep]
    cols = np.asarray(colors, np.uint8)[keep]
    nrm = estimate_normals(pts) if normals is None else np.asarray(normals, np.float32)[keep]
    lab = None if labels is None else np.asarray(labels)[keep]
    maps = default_label_maps()
    if lab is not None and label_set not in maps:
        raise InvalidArgument(f"unknown label set {label_set!r} (known: {sorted(maps)})")
    cls_idx = (np.full(len(pts), -1, np.int16) if lab is None
               else labels_to_class_index(lab, maps[label_set], GRAPH_CLASSES))
    return PointSet.scanned(pts, cols, nrm, cls_idx), _structure_mask(lab, label_set, len(pts))


def site_from_labelled_points(
    points: np.ndarray,
    colors: np.ndarray,
    normals: np.ndarray | None,
    labels: np.ndarray | None,
    *,
    label_set: str = "nyu40",
    site_id: str,
    inputs: dict[str, Any],
    config: SiteBuildConfig = SiteBuildConfig(),
    progress: Progress | None = None,
    cad_root: str | Path | None = None,
    auto_cad: AutoCadConfig | None = None,
) -> Site:
    """A site from labelled points alone (e.g. a TSDF-fused map): every node from clustering, or, with `auto_cad`
    and a CAD library at `cad_root`, CAD nodes where the library's models fit the labelled instances.

    points (N, 3) float, map frame, metres; colors (N, 3) uint8 RGB; normals (N, 3) float or None (estimated);
    labels (N,) int ids in `label_set` or None (no object nodes); inputs: JSON-able description of the sources.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise InvalidArgument(f"points must be (N, 3) with N > 0, got {points.shape}")
    if np.asarray(colors).shape != points.shape:
        raise InvalidArgument(f"colors must be {points.shape}, got {np.asarray(colors).shape}")
    if labels is not None and np.asarray(labels).shape != (len(points),):
        raise InvalidArgument(f"labels must be ({len(points)},), got {np.asarray(labels).shape}")
    total = 10
    raw, structure = _raw_pointset(points, colors, normals, labels, label_set, config.enhance.raw_voxel_m)
    if progress is not None:
        progress(3, total)
    placements: list[CadPlacement] = []
    report = None
    if auto_cad is not None:
        inputs = dict(inputs)
        placements, report = _auto_cad(raw, structure, [], cad_root, auto_cad, config, labels is not None, inputs)
    return _assemble(raw, structure, placements, site_id=site_id, inputs=inputs, label_set=label_set, config=config,
                     progress=progress, total=total, base=3, auto_report=report)


def build_site(
    scan_ply: str | Path,
    *,
    labels_ply: str | Path | None = None,
    scan2cad_json: str | Path | None = None,
    cad_root: str | Path | None = None,
    site_id: str | None = None,
    config: SiteBuildConfig = SiteBuildConfig(),
    progress: Progress | None = None,
    auto_cad: AutoCadConfig | None = None,
) -> Site:
    """Build a site from a scan PLY (colours required; NYU40 labels from `labels_ply` or the scan's own `label`),
    optionally enhanced with the Scan2CAD record of this scan (the one whose id_scan the file name starts with, or
    the only one) and CAD models from `cad_root`. With `auto_cad`, the library's models are also aligned to the
    labelled instances no annotation covers (cadreg/site/autocad.py); `auto_cad_document(site)` gives all CADs as
    a Scan2CAD file. Raises InvalidFileError naming any bad or missing input file (a missing or empty library too).
    """
    scan_ply = Path(scan_ply)
    if scan2cad_json is not None and cad_root is None:
        raise InvalidArgument("scan2cad_json needs cad_root (the CAD library)")
    if auto_cad is not None and cad_root is None:
        raise InvalidArgument("auto-CAD needs cad_root (the CAD library)")
    total = 12
    enh = config.enhance
    scan = read_scan(scan_ply, labels_ply)
    _check_extent(scan_ply, scan.points)
    scan = _facing_inward(scan)
    _warn_of_its_frame_and_labels(scan)
    scan = sample_large_triangles(scan, min_edge_m=enh.sample_edge_m, spacing_m=enh.sample_spacing_m)
    inputs: dict[str, Any] = {"scan": {"path": str(scan_ply), "sha256": sha256_file(scan_ply)}}
    if labels_ply is not None:
        inputs["labels"] = {"path": str(labels_ply), "sha256": sha256_file(labels_ply)}
    if progress is not None:
        progress(1, total)
    placements: list[CadPlacement] = []
    if scan2cad_json is not None:
        record = select_scan(read_scan2cad(scan2cad_json), scan_ply.name, scan2cad_json)
        inputs["scan2cad"] = {"path": str(scan2cad_json), "sha256": sha256_file(scan2cad_json),
                              "id_scan": record.id_scan}
        cad_files: dict[str, str] = {}
        for model in record.aligned_models:
            path = cad_model_path(cad_root, model.catid_cad, model.id_cad)
            key = f"{model.catid_cad}/{model.id_cad}"
            if key not in cad_files:
                cad_files[key] = sha256_file(path)
            placements.append(CadPlacement(load_cad_mesh(path), record.A_scan_cad(model),
                                           synset_class(model.catid_cad), key, sym=model.sym))
        inputs["cad_root"] = str(cad_root)
        inputs["cad_models"] = cad_files
    if progress is not None:
        progress(3, total)
    has_labels = scan.labels is not None
    raw, structure = _raw_pointset(scan.points, scan.colors, scan.normals, scan.labels, "nyu40",
                                   config.enhance.raw_voxel_m)
    report = None
    if auto_cad is not None:
        placements, report = _auto_cad(raw, structure, placements, cad_root, auto_cad, config, has_labels, inputs)
    if progress is not None:
        progress(5, total)
    site = _assemble(raw, structure, placements, site_id=site_id or scan_ply.name.split(".")[0], inputs=inputs,
                     label_set="nyu40" if has_labels else "none", config=config, progress=progress, total=total,
                     base=5, auto_report=report)
    return site
