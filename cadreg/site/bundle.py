"""A site: the enhanced map, the raw scan, the semantic graph and the label maps, saved as a bundle directory.

Bundle layout (DESIGN §3), self-describing, no pickle:

    site.json   schema, site id, version, build time, source inputs (with sha256), build parameters, classes,
                label maps, and the sha256 of every other file
    map.ply     the enhanced map, a `PointSet` (cadreg/pointset.py: x y z, red green blue, nx ny nz, instance,
                class as an index into `classes`, source)
    raw.ply     the raw scan points kept for refinement, the same columns (instance -1, source raw)
    graph.json  nodes and edges of the semantic graph
    field.npy   (optional, buildings) the distance field over the whole map, built once when the site is composed
                (`FieldGrid`): loading it is a memory map, not a rebuild
    regions.npy (optional, buildings) each region's map points on a grid, its neighbours' within a halo included
                (`RegionGrids`): what a localizer builds a region's search structures from, read, not gathered
    pyramid.npy (optional, buildings) the label-free search's pyramid of score grids (`StoredPyramid`), mapped by a
                worker whose settings are those it was built with, not built again in each

`version` is the first 12 hex digits of the sha256 over the sorted "name:sha256" lines of map.ply, raw.ply,
graph.json (and field.npy, regions.npy, pyramid.npy when present): the same content gives the same version, a
rebuilt or replaced site a new one.
`Site.load` checks every hash and raises BundleIntegrityError naming the file that does not match (a file that
another process's check found matching, that is not read whole and has not changed since, counts as checked:
`FileChecks`).
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..config import GraphConfig
from ..errors import BundleIntegrityError, ConfigError, InvalidFileError, InvalidFrame
from ..io.bundle_files import (BundleWriter, FileStamp, file_stamp, map_npy, npy_bytes, read_bytes, read_json,
                                sha256_bytes, sha256_file)
from ..io.ply import release_pages
from ..labels import label_set_name, labels_to_class_index
from ..pointset import MappedRows, PointSet
from .graph import ObjectNode, SemanticGraph  # noqa: F401  (ObjectNode is part of this module's API)
from .regions import Region, from_manifest, region_from_points, to_manifest

SCHEMA = "cadreg.site/1"
DATA_FILES = ("map.ply", "raw.ply", "graph.json")
OPTIONAL_FILES = ("field.npy", "regions.npy", "pyramid.npy")
# A stored region grid's rows: position (map frame, metres), colour, class index (-1: none).
REGION_GRID_DTYPE = np.dtype([("xyz", "<f4", (3,)), ("rgb", "u1", (3,)), ("cls", "<i2")])
CLOUDS = ("raw", "enhanced", "both")


@dataclass(frozen=True)
class FileCheck:
    """A bundle file a hash check found matching: its sha256 as site.json lists it, and its stamp when it was
    hashed."""

    sha256: str
    stamp: FileStamp


# What a hash check of a bundle found (`Site.check_files`), by file name. `Site.load(..., checked=)` takes a file not
# read whole whose listed hash and stamp are still these as checked rather than hash it again, as git's index does:
# a server's parent checks a bundle once and each of its workers loads it (a 100-room bundle is 1.3 GB, a second of
# hashing for each).
FileChecks = dict[str, FileCheck]
# A file changed less than this before its check began gets no stamp (git's "racy" rule): file times tick coarsely
# (milliseconds here, seconds on some file systems), so a write in the same tick, while or right after it was hashed,
# could leave its stamp as it was.
SETTLED_NS = 2_000_000_000
# Files hashed side by side when a bundle is checked.
HASH_THREADS = 4


def version_of(file_hashes: dict[str, str]) -> str:
    """Content version: 12 hex digits of sha256 over the sorted "name:sha256" lines."""
    text = "\n".join(f"{k}:{file_hashes[k]}" for k in sorted(file_hashes))
    return sha256_bytes(text.encode())[:12]


@dataclass(frozen=True, eq=False)
class FieldGrid:
    """A stored distance field (field.npy): grid (I, J, K) uint8, the distance from each cell to the nearest map
    point in steps of truncate_m / 255 (255 = truncate_m or farther), with a one-cell border at 255; the cell
    (i, j, k) of the grid holds the voxel whose lower corner is origin + (i − 1, j − 1, k − 1) · voxel_m (map frame,
    metres). Built by `cadreg.localize.score.building_field`, read by `DistanceField.from_grid`."""

    grid: np.ndarray
    origin: np.ndarray
    voxel_m: float
    truncate_m: float

    def to_manifest(self) -> dict[str, Any]:
        return {"origin": [float(x) for x in self.origin], "voxel_m": float(self.voxel_m),
                "truncate_m": float(self.truncate_m), "shape": [int(x) for x in self.grid.shape]}


@dataclass(frozen=True, eq=False)
class RegionGrids:
    """Each region's map points as a building's localizer uses them (regions.npy): the points of cloud `cloud`
    ("raw" | "enhanced" | "both") inside the region's box grown by halo_m (its neighbours' points included), one per
    voxel_m voxel (`localize.points.voxel_indices`). Built when the site is composed
    (`cadreg.localize.regions.region_grids`), so that a worker makes a region's search structures from one read of
    its rows rather than by gathering and gridding the building's points.

    points : (n,) REGION_GRID_DTYPE rows, region after region in the order of the site's regions; offsets : (r + 1,)
    int64, region k's rows are points[offsets[k]:offsets[k + 1]]. tree_leaf : each region's rows are in the order
    of its KD-tree of leaves of this many points (`localize.point_tree.tree_order`), so that a worker's tree is a
    read; 0: in no such order (a bundle composed before trees were stored)."""

    points: np.ndarray
    offsets: np.ndarray
    cloud: str
    halo_m: float
    voxel_m: float
    tree_leaf: int = 0

    def rows(self, k: int) -> np.ndarray:
        return self.points[int(self.offsets[k]):int(self.offsets[k + 1])]

    def release(self, k: int) -> None:
        """Hand back the pages of region k's rows once they have been read (a memory-mapped regions.npy; a row read
        again later is paged in again from the file)."""
        mm = getattr(self.points, "_mmap", None)
        if mm is not None:
            item = self.points.dtype.itemsize
            release_pages(mm, self.points.offset + int(self.offsets[k]) * item,
                          self.points.offset + int(self.offsets[k + 1]) * item)

    def matches(self, *, cloud: str, halo_m: float, voxel_m: float) -> bool:
        """Whether these grids are what a localizer of these settings would build itself."""
        return self.cloud == cloud and np.isclose(self.halo_m, halo_m) and np.isclose(self.voxel_m, voxel_m)

    def to_manifest(self) -> dict[str, Any]:
        return {"cloud": self.cloud, "halo_m": float(self.halo_m), "voxel_m": float(self.voxel_m),
                "tree_leaf": int(self.tree_leaf), "offsets": [int(x) for x in self.offsets]}


@dataclass(frozen=True, eq=False)
class StoredPyramid:
    """A building's label-free search pyramid (pyramid.npy; `cadreg.localize.bbs.GridPyramid.to_stored`): grids
    (levels + 1, cells) uint8, its max-pooled score grids one level a row; built_with, the map's up and the search's
    settings it was built with (`bbs.built_with`); map_lo_level, map_hi_level (3,) the map's box in its level frame,
    from which the grid's layout follows. Built when the site is composed, so that a worker whose settings are those
    maps it rather than building its own (`GridPyramid.from_stored`)."""

    grids: np.ndarray
    built_with: dict[str, Any]
    map_lo_level: np.ndarray
    map_hi_level: np.ndarray

    def matches(self, wanted: dict[str, Any]) -> bool:
        """Whether it was built with `wanted` (`bbs.built_with`): the settings exactly, the up within rounding (one
        machine's estimate of a map's up and another's may differ in the last bits; no cell moves for that)."""
        others = lambda d: {k: v for k, v in d.items() if k != "up"}  # noqa: E731
        return others(self.built_with) == others(wanted) and bool(
            np.allclose(self.built_with["up"], wanted["up"], rtol=0.0, atol=1e-9))

    def to_manifest(self) -> dict[str, Any]:
        return {"built_with": dict(self.built_with), "map_lo_level": [float(x) for x in self.map_lo_level],
                "map_hi_level": [float(x) for x in self.map_hi_level]}


@dataclass(eq=False)  # arrays inside: compare sites by version, not with ==
class Site:
    """A site, in memory.

    map : the enhanced map (kept raw points, then the points sampled on each CAD; `PointSet` columns).
    raw : the scan as it was, down-sampled (instance -1, source raw).
    graph : the semantic graph; classes : graph class names (what `class_index` indexes);
    label_maps : {label set: {label id: class}}.
    manifest : the parsed site.json (for a site not yet saved: what site.json will hold).
    mapped_rows : for a memory-mapped site (`load(mapped=True)`, a building by default), where each cloud's rows lie
    in its file, for `release`. field_grid : a building's stored distance field (field.npy), or None.
    region_grids : a building's stored region grids (regions.npy), or None. pyramid : a building's stored
    label-free search pyramid (pyramid.npy), or None.
    """

    site_id: str
    version: str
    manifest: dict[str, Any]
    map: PointSet
    raw: PointSet
    graph: SemanticGraph
    classes: list[str]
    label_maps: dict[str, dict[int, str]] = field(default_factory=dict)
    mapped_rows: dict[str, MappedRows] = field(default_factory=dict, repr=False)
    field_grid: FieldGrid | None = None  # a building's stored distance field (field.npy); None: built at load
    region_grids: RegionGrids | None = None  # a building's stored region grids (regions.npy); None: built on use
    pyramid: StoredPyramid | None = None  # a building's stored search pyramid (pyramid.npy); None: built on use

    def release(self, which: str, rows: slice) -> None:
        """Hand back the pages of rows of a memory-mapped cloud ("map" | "raw") once they have been copied; nothing
        for a site read into memory."""
        if which in self.mapped_rows:
            self.mapped_rows[which].release(rows)

    # --- queries -------------------------------------------------------------------------------------------------

    def cloud(self, which: str) -> PointSet:
        """The raw scan, the enhanced map, or both (raw first). A site that kept no raw points answers every
        request with the enhanced map. Raises ConfigError for another name."""
        if which not in CLOUDS:
            raise ConfigError(f"unknown map cloud {which!r}; choose one of {CLOUDS}")
        if which == "enhanced" or len(self.raw) == 0:
            return self.map
        return self.raw if which == "raw" else PointSet.concat([self.raw, self.map])

    @property
    def regions(self) -> list[Region]:
        """The site's regions (`regions.py`): the rooms of a composed site as site.json lists them, else one
        region holding the whole map, named after the site."""
        entries = self.manifest.get("regions")
        if not entries or len(entries) == 1:
            return [whole_site_region(self, entries[0].get("id") if entries else None)]
        return from_manifest(entries, map_points=len(self.map), raw_points=len(self.raw))

    @property
    def up(self) -> np.ndarray | None:
        """(3,) unit vector opposite to gravity in the map frame, as site.json states it ("up"), or None: a scan mesh
        leaves it to the localizer (z up by convention, else found from the map's surfaces); a fused site states
        it (`fuse.fuse_site`: its frame is its first camera's, with no axis up)."""
        return _manifest_up(self.manifest)

    @property
    def edge_max_m(self) -> float:
        """δ of this site's graph (its build parameters): scan graphs must use the same to be comparable."""
        build = self.manifest.get("build_config", {}).get("graph", {})
        return float(build.get("edge_max_m", GraphConfig().edge_max_m))

    def classes_for_labels(self, label_set: str, labels: np.ndarray) -> np.ndarray:
        """Label ids in `label_set` -> class indices into `classes`.

        labels : (...) integer array. Returns the same shape, int16, -1 = none/structure/unknown id.
        Raises InvalidFrame naming the known label sets for a label set this site has no map for.
        """
        if label_set not in self.label_maps:
            known = sorted(self.label_maps)
            raise InvalidFrame(f"site {self.site_id!r} has no label map {label_set!r}; known label sets: {known}",
                               detail={"label_set": label_set, "known": known})
        return labels_to_class_index(labels, self.label_maps[label_set], self.classes)

    def class_name(self, index: int) -> str | None:
        return self.classes[index] if 0 <= index < len(self.classes) else None

    # --- encoding ------------------------------------------------------------------------------------------------

    def _data_files(self) -> Iterator[tuple[str, bytes | bytearray]]:
        """(name, bytes) of map.ply, raw.ply, graph.json and the stored grids, each encoded as it is asked for
        (deterministic: same content, same bytes). One at a time: a 100-room building's files are 1.4 GB encoded,
        and held at once they were a quarter of its `site compose`'s peak memory."""
        yield "map.ply", self.map.to_ply_bytes()
        yield "raw.ply", self.raw.to_ply_bytes()
        yield "graph.json", json.dumps(self.graph.to_dict(), indent=1, sort_keys=True).encode()
        if self.field_grid is not None:
            yield "field.npy", npy_bytes(self.field_grid.grid)
        if self.region_grids is not None:
            yield "regions.npy", npy_bytes(self.region_grids.points)
        if self.pyramid is not None:
            yield "pyramid.npy", npy_bytes(self.pyramid.grids)

    def refresh_version(self, stage: Callable[[str, bytes | bytearray], None] | None = None) -> None:
        """Recompute `version` and bring `manifest` up to date with the content (what site.json will hold: schema,
        site id, version, file hashes, classes, label maps, counts); each data file, as it is encoded, is also given
        to `stage` (name, bytes) when one is given (`save`)."""
        hashes = {}
        for name, data in self._data_files():
            hashes[name] = sha256_bytes(data)
            if stage is not None:
                stage(name, data)
            del data  # before the next file is encoded
        self.version = version_of(hashes)
        meta = dict(self.manifest)
        meta.pop("field", None)
        if self.field_grid is not None:
            meta["field"] = self.field_grid.to_manifest()
        meta.pop("region_grids", None)
        if self.region_grids is not None:
            meta["region_grids"] = self.region_grids.to_manifest()
        meta.pop("pyramid", None)
        if self.pyramid is not None:
            meta["pyramid"] = self.pyramid.to_manifest()
        regions = meta.get("regions")
        if not regions or len(regions) == 1:
            # One region is the whole site: measured again from the clouds as they are now (a site whose clouds
            # were edited since its regions were written keeps no stale box or ranges).
            region_id = regions[0]["id"] if regions else self.site_id
            meta["regions"] = to_manifest([whole_site_region(self, region_id)])
        else:
            from_manifest(regions, map_points=len(self.map), raw_points=len(self.raw))
        meta.update({
            "schema": SCHEMA,
            "site_id": self.site_id,
            "version": self.version,
            "files": hashes,
            "classes": list(self.classes),
            "label_maps": {k: {str(i): c for i, c in sorted(v.items())} for k, v in self.label_maps.items()},
            "counts": {"points": len(self.map), "raw_points": len(self.raw),
                       "nodes": len(self.graph.nodes), "edges": self.graph.graph.number_of_edges()},
        })
        self.manifest = meta

    def save(self, out_dir: str | Path) -> None:
        """Write the bundle into `out_dir` (created if needed; existing bundle files are replaced, all at once, once
        every one is written: `BundleWriter`)."""
        with BundleWriter(out_dir) as bundle:
            self.refresh_version(bundle.stage)
            bundle.stage("site.json", json.dumps(self.manifest, indent=1, sort_keys=True).encode())
            bundle.commit()

    @staticmethod
    def read_manifest(site_dir: str | Path, *, verify: bool = True) -> dict[str, Any]:
        """The bundle's site.json, checked: schema, required keys, the version against the file hashes and, with
        `verify`, every data file's sha256 (files are hashed, not parsed). Raises InvalidFileError or
        BundleIntegrityError naming the file. For runners that need a site's id, version and counts
        (`meta["counts"]`) without loading its arrays."""
        return _read_checked(Path(site_dir), verify=verify, keep=())[0]

    @staticmethod
    def check_files(site_dir: str | Path) -> tuple[dict[str, Any], FileChecks]:
        """site.json, checked as `read_manifest` checks it with `verify` (the same errors), and what the check found
        (`FileChecks`) for `Site.load(checked=)` in a process that loads the same bundle after this one."""
        meta, _, found = _read_checked(Path(site_dir), verify=True, keep=())
        return meta, found

    @classmethod
    def load(cls, site_dir: str | Path, *, mapped: bool | None = None, checked: FileChecks | None = None) -> "Site":
        """Read and verify a bundle. Raises InvalidFileError (missing/malformed file) or BundleIntegrityError (a file
        whose sha256 differs from site.json, or a version that does not match the hashes), naming the file.

        checked : what another process's check of this bundle found (`check_files`); a file not read whole (a mapped
        cloud, a stored grid) whose hash in site.json and stamp are still those it found is not hashed again. Every
        other file is.

        mapped : memory-map map.ply and raw.ply instead of reading them (read-only columns, paged in as used; see
        `PointSet.open_ply`); None = for a site of several regions (a building: a worker touches the rooms it
        localizes in, not the whole building)."""
        root = Path(site_dir)
        meta_path = root / "site.json"
        if mapped is None:
            head = read_json(meta_path)
            mapped = isinstance(head, dict) and isinstance(head.get("regions"), list) and len(head["regions"]) > 1
        clouds = ("map.ply", "raw.ply")
        meta, blobs, _ = _read_checked(root, verify=True, keep=("graph.json",) if mapped else ("graph.json", *clouds),
                                       checked=checked)
        rows: dict[str, MappedRows] = {}
        if mapped:
            (enhanced, rows["map"]), (raw, rows["raw"]) = (PointSet.open_ply(root / name) for name in clouds)
        else:
            enhanced = PointSet.from_ply_bytes(blobs["map.ply"], root / "map.ply")
            raw = PointSet.from_ply_bytes(blobs["raw.ply"], root / "raw.ply")
        stored_field = _stored_field(root, meta) if "field.npy" in meta["files"] else None
        stored_grids = _stored_region_grids(root, meta) if "regions.npy" in meta["files"] else None
        stored_pyramid = _stored_pyramid(root, meta) if "pyramid.npy" in meta["files"] else None
        try:
            graph = SemanticGraph.from_dict(json.loads(blobs["graph.json"]))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InvalidFileError(root / "graph.json", f"malformed: {exc!r}") from exc
        try:
            label_maps = {label_set_name(k): {int(i): str(c) for i, c in v.items()}
                          for k, v in meta["label_maps"].items()}
            classes = [str(c) for c in meta["classes"]]
        except (TypeError, ValueError, AttributeError) as exc:
            raise InvalidFileError(meta_path, f"malformed label_maps or classes: {exc!r}") from exc
        for name, cloud, which in (("map.ply", enhanced, "map"), ("raw.ply", raw, "raw")):
            if (cloud.class_index >= len(classes)).any():
                raise InvalidFileError(root / name, f"class indices beyond the {len(classes)} classes of site.json")
            if which in rows:  # checked: a mapped cloud's pages go back until a region needs them
                rows[which].release(slice(0, len(cloud)))
        site = cls(site_id=str(meta["site_id"]), version=str(meta["version"]), manifest=meta, map=enhanced, raw=raw,
                   graph=graph, classes=classes, label_maps=label_maps, mapped_rows=rows, field_grid=stored_field,
                   region_grids=stored_grids, pyramid=stored_pyramid)
        if meta.get("regions"):
            from_manifest(meta["regions"], map_points=len(enhanced), raw_points=len(raw), source=str(meta_path))
        try:
            _manifest_up(meta)
        except ValueError as exc:
            raise InvalidFileError(meta_path, str(exc)) from None
        return site


def _manifest_up(meta: dict[str, Any]) -> np.ndarray | None:
    """site.json's "up" as a unit (3,) vector, None when absent; ValueError when it is not a non-zero 3-vector."""
    if meta.get("up") is None:
        return None
    try:
        up = np.asarray(meta["up"], dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"'up' must be 3 numbers, not {meta['up']!r}") from None
    norm = float(np.linalg.norm(up))
    if not np.isfinite(norm) or norm < 1e-6:
        raise ValueError(f"'up' must be a non-zero finite vector, not {meta['up']!r}")
    return up / norm


def _stored_field(root: Path, meta: dict[str, Any]) -> FieldGrid:
    """The field.npy of a bundle, memory-mapped and checked against site.json's "field"."""
    path = root / "field.npy"
    grid = map_npy(path)
    try:
        info = meta["field"]
        origin = np.asarray(info["origin"], dtype=np.float64).reshape(3)
        voxel_m, truncate_m = float(info["voxel_m"]), float(info["truncate_m"])
        ok = (grid.dtype == np.uint8 and grid.ndim == 3 and list(grid.shape) == list(info["shape"])
              and voxel_m > 0 and truncate_m > 0 and np.all(np.isfinite(origin)))
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidFileError(root / "site.json", f"malformed 'field': {exc!r}") from None
    if not ok:
        raise InvalidFileError(path, "not the uint8 grid site.json's 'field' describes")
    return FieldGrid(grid, origin, voxel_m, truncate_m)


def _stored_region_grids(root: Path, meta: dict[str, Any]) -> RegionGrids:
    """The regions.npy of a bundle, memory-mapped and checked against site.json's "region_grids" and "regions"."""
    path = root / "regions.npy"
    points = map_npy(path)
    try:
        info = meta["region_grids"]
        offsets = np.asarray(info["offsets"], dtype=np.int64).reshape(-1)
        cloud, halo_m, voxel_m = str(info["cloud"]), float(info["halo_m"]), float(info["voxel_m"])
        tree_leaf = int(info.get("tree_leaf", 0))
        regions = meta.get("regions") or []
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidFileError(root / "site.json", f"malformed 'region_grids': {exc!r}") from None
    if not (points.dtype == REGION_GRID_DTYPE and points.ndim == 1 and len(offsets) == len(regions) + 1
            and offsets[0] == 0 and offsets[-1] == len(points) and np.all(np.diff(offsets) >= 0)
            and cloud in CLOUDS and halo_m >= 0 and voxel_m > 0 and tree_leaf >= 0):
        raise InvalidFileError(path, "not the region grids site.json's 'region_grids' and 'regions' describe")
    return RegionGrids(points, offsets, cloud, halo_m, voxel_m, tree_leaf)


# site.json's "pyramid"["built_with"]: each setting and its type (`bbs.built_with`).
PYRAMID_SETTINGS = {"up": list, "voxel_m": float, "levels": int, "tau_m": float, "reach_m": float, "margin_m": float,
                    "max_cells": int}


def _stored_pyramid(root: Path, meta: dict[str, Any]) -> StoredPyramid:
    """The pyramid.npy of a bundle, memory-mapped and checked against site.json's "pyramid" (whether its grids have
    the shape their layout gives is `GridPyramid.from_stored`'s to say: it derives the layout)."""
    path = root / "pyramid.npy"
    grids = map_npy(path)
    try:
        info = meta["pyramid"]
        built = {key: kind(info["built_with"][key]) for key, kind in PYRAMID_SETTINGS.items()}
        built["up"] = [float(x) for x in built["up"]]
        lo, hi = (np.asarray(info[key], dtype=np.float64).reshape(3) for key in ("map_lo_level", "map_hi_level"))
        ok = (len(built["up"]) == 3 and np.all(np.isfinite(np.concatenate([built["up"], lo, hi]))) and np.all(hi >= lo)
              and built["voxel_m"] > 0 and 1 <= built["levels"] <= 7 and built["reach_m"] > 0
              and built["margin_m"] >= 0 and built["max_cells"] > 0)
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidFileError(root / "site.json", f"malformed 'pyramid': {exc!r}") from None
    if not ok:
        raise InvalidFileError(root / "site.json", "malformed 'pyramid': its up, box or settings")
    if grids.dtype != np.uint8 or grids.ndim != 2 or grids.shape[0] != built["levels"] + 1:
        raise InvalidFileError(path, "not the grids of the levels site.json's 'pyramid' describes")
    return StoredPyramid(grids, built, lo, hi)


def whole_site_region(site: Site, region_id: str | None = None) -> Region:
    """One region holding all of `site`, named `region_id` (default: after the site)."""
    return region_from_points(region_id or site.site_id, [site.map.points, site.raw.points],
                              [n.id for n in site.graph.nodes], (0, len(site.map)), (0, len(site.raw)))


def _check_file(path: Path, sha256: str, keep: bool, checked: FileCheck | None,
                began_ns: int) -> tuple[bytes | None, FileCheck | None]:
    """(the file's bytes if `keep`, else None; what to trust it by later, or None) of a bundle file that site.json
    lists with `sha256`, whose check began at began_ns (`time.time_ns`); BundleIntegrityError when its bytes do not
    match. A file not kept whose listed hash and stamp are `checked`'s is taken as checked, unread."""
    stamp = file_stamp(path)
    if not keep and checked == FileCheck(sha256, stamp):
        return None, checked
    blob = read_bytes(path) if keep else None
    if (sha256_file(path) if blob is None else sha256_bytes(blob)) != sha256:
        raise BundleIntegrityError(path, "sha256 does not match site.json: the file was modified or belongs to "
                                   "another build")
    # The stamp stands for the bytes hashed only if nothing wrote the file meanwhile, nor in the ticks before.
    settled = file_stamp(path) == stamp and began_ns - max(stamp.mtime_ns, stamp.ctime_ns) > SETTLED_NS
    return blob, FileCheck(sha256, stamp) if settled else None


def _read_checked(root: Path, *, verify: bool, keep: tuple[str, ...] = DATA_FILES,
                  checked: FileChecks | None = None) -> tuple[dict[str, Any], dict[str, bytes], FileChecks]:
    """(site.json, {data file: bytes}, what the check found) of the bundle at `root`; with `verify`, every data file
    is hashed, and the bytes of those named in `keep` are returned (`Site.load` parses the same bytes rather than
    reading them twice); the others are hashed as a stream, never held whole, unless `checked` holds their hash in
    site.json and their stamp as they are now."""
    meta_path = root / "site.json"
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
        raise InvalidFileError(meta_path, f"not a cadreg site (schema {meta.get('schema') if isinstance(meta, dict) else None!r}, expected {SCHEMA!r})")
    for key in ("site_id", "version", "files", "classes", "label_maps"):
        if key not in meta:
            raise InvalidFileError(meta_path, f"missing key {key!r}")
    hashes = meta["files"]
    if not isinstance(hashes, dict) or not set(DATA_FILES) <= set(hashes) <= set(DATA_FILES + OPTIONAL_FILES):
        raise InvalidFileError(meta_path, f"'files' must list {list(DATA_FILES)} (and may list {list(OPTIONAL_FILES)})")
    if version_of(hashes) != meta["version"]:
        raise BundleIntegrityError(meta_path, f"version {meta['version']!r} does not match the file hashes")
    blobs: dict[str, bytes] = {}
    found: FileChecks = {}
    if verify:
        began_ns = time.time_ns()
        # hashlib lets go of the GIL while it hashes: a bundle's files are checked side by side (a server's parent
        # checks 1.3 GB for 100 rooms before its workers start, while the other cores wait).
        with ThreadPoolExecutor(max_workers=HASH_THREADS) as pool:
            checks = [(name, pool.submit(_check_file, root / name, hashes[name], name in keep,
                                         None if checked is None else checked.get(name), began_ns))
                      for name in sorted(hashes)]
            for name, future in checks:  # the first bad file in name order is the one named
                blob, stamped = future.result()
                if blob is not None:
                    blobs[name] = blob
                if stamped is not None:
                    found[name] = stamped
    return meta, blobs, found
