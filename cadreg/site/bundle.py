"""A site: the enhanced map, the raw scan, the semantic graph and the label maps, saved as a bundle directory.

Bundle layout (DESIGN §3), self-describing, no pickle:

    site.json   schema, site id, version, build time, source inputs (with sha256), build parameters, classes,
                label maps, and the sha256 of every other file
    map.ply     enhanced map: x y z (float32), red green blue (uint8), nx ny nz (float32), instance (int32),
                class (int16, index into `classes`, -1 none), source (uint8, 0 raw, 1 CAD)
    raw.ply     the raw scan points kept for refinement, same columns (instance -1, source 0)
    graph.json  nodes and edges of the semantic graph

`version` is the first 12 hex digits of the sha256 over the sorted "name:sha256" lines of map.ply, raw.ply and
graph.json: the same content gives the same version, a rebuilt or replaced site a new one.
`Site.load` checks every hash and raises BundleIntegrityError naming the file that does not match.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import BundleIntegrityError, InvalidFileError
from ..io.bundle_files import read_bytes, read_json, sha256_bytes, write_bundle_dir
from ..io.ply import parse_ply, ply_bytes
from ..labels import labels_to_class_index
from .graph import ObjectNode, SemanticGraph  # noqa: F401  (ObjectNode is part of this module's API)

SCHEMA = "cadreg.site/1"
DATA_FILES = ("map.ply", "raw.ply", "graph.json")
_COLUMNS = ("x", "y", "z", "red", "green", "blue", "nx", "ny", "nz", "instance", "class", "source")


def _cloud_columns(points, colors, normals, instance, class_index, source) -> dict[str, np.ndarray]:
    p = np.asarray(points, np.float32)
    c = np.asarray(colors, np.uint8)
    n = np.asarray(normals, np.float32)
    return {
        "x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
        "red": c[:, 0], "green": c[:, 1], "blue": c[:, 2],
        "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2],
        "instance": np.asarray(instance, np.int32), "class": np.asarray(class_index, np.int16),
        "source": np.asarray(source, np.uint8),
    }


def _cloud_from_ply(blob: bytes, path: Path) -> dict[str, np.ndarray]:
    v = parse_ply(blob, path).vertex
    missing = [c for c in _COLUMNS if c not in v]
    if missing:
        raise InvalidFileError(path, f"missing vertex columns {missing}")
    return {
        "points": np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32),
        "colors": np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8),
        "normals": np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float32),
        "instance": v["instance"].astype(np.int32),
        "class_index": v["class"].astype(np.int16),
        "source": v["source"].astype(np.uint8),
    }


def version_of(file_hashes: dict[str, str]) -> str:
    """Content version: 12 hex digits of sha256 over the sorted "name:sha256" lines."""
    text = "\n".join(f"{k}:{file_hashes[k]}" for k in sorted(file_hashes))
    return sha256_bytes(text.encode())[:12]


@dataclass(eq=False)  # arrays inside: compare sites by version, not with ==
class Site:
    """A site, in memory.

    points (N, 3) float32, map frame, metres; colors (N, 3) uint8 RGB; normals (N, 3) float32 unit;
    instance (N,) int32 (-1 none; CAD instance i is node "cad-<i>"); class_index (N,) int16 index into `classes`
    (-1 none/structure); source (N,) uint8 (0 raw, 1 CAD) — the enhanced map.
    raw_points (M, 3) float32, raw_colors (M, 3) uint8, raw_normals (M, 3) float32, raw_class_index (M,) int16 —
    the scan as it was, down-sampled.
    graph : the semantic graph; classes : graph class names; label_maps : {label set: {label id: class}}.
    meta : the parsed site.json (for a site not yet saved: what site.json will hold).
    """

    site_id: str
    version: str
    meta: dict[str, Any]
    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    instance: np.ndarray
    class_index: np.ndarray
    source: np.ndarray
    raw_points: np.ndarray
    raw_colors: np.ndarray
    raw_normals: np.ndarray
    raw_class_index: np.ndarray
    graph: SemanticGraph
    classes: list[str]
    label_maps: dict[str, dict[int, str]] = field(default_factory=dict)

    # --- queries -------------------------------------------------------------------------------------------------

    def classes_for_labels(self, label_set: str, labels: np.ndarray) -> np.ndarray:
        """Label ids in `label_set` -> class indices into `classes`.

        labels : (...) integer array. Returns the same shape, int16, -1 = none/structure/unknown id.
        Raises KeyError for a label set this site has no map for.
        """
        if label_set not in self.label_maps:
            raise KeyError(f"site {self.site_id!r} has no label map {label_set!r} (has {sorted(self.label_maps)})")
        return labels_to_class_index(labels, self.label_maps[label_set], self.classes)

    def class_name(self, index: int) -> str | None:
        return self.classes[index] if 0 <= index < len(self.classes) else None

    # --- encoding ------------------------------------------------------------------------------------------------

    def encode_data_files(self) -> dict[str, bytes]:
        """The bytes of map.ply, raw.ply and graph.json (deterministic: same content, same bytes)."""
        raw_n = len(self.raw_points)
        return {
            "map.ply": ply_bytes(_cloud_columns(self.points, self.colors, self.normals, self.instance,
                                                self.class_index, self.source)),
            "raw.ply": ply_bytes(_cloud_columns(self.raw_points, self.raw_colors, self.raw_normals,
                                                np.full(raw_n, -1, np.int32), self.raw_class_index,
                                                np.zeros(raw_n, np.uint8))),
            "graph.json": json.dumps(self.graph.to_dict(), indent=1, sort_keys=True).encode(),
        }

    def refresh_version(self) -> dict[str, bytes]:
        """Recompute `version` and bring `meta` up to date with the content (what site.json will hold: schema,
        site id, version, file hashes, classes, label maps, counts). Returns the encoded data files."""
        files = self.encode_data_files()
        hashes = {k: sha256_bytes(v) for k, v in files.items()}
        self.version = version_of(hashes)
        meta = dict(self.meta)
        meta.update({
            "schema": SCHEMA,
            "site_id": self.site_id,
            "version": self.version,
            "files": hashes,
            "classes": list(self.classes),
            "label_maps": {k: {str(i): c for i, c in sorted(v.items())} for k, v in self.label_maps.items()},
            "counts": {"points": int(len(self.points)), "raw_points": int(len(self.raw_points)),
                       "nodes": len(self.graph.nodes), "edges": self.graph.graph.number_of_edges()},
        })
        self.meta = meta
        return files

    def save(self, out_dir: str | Path) -> None:
        """Write the bundle into `out_dir` (created if needed; existing bundle files are replaced)."""
        files = self.refresh_version()
        files["site.json"] = json.dumps(self.meta, indent=1, sort_keys=True).encode()
        write_bundle_dir(out_dir, files)

    @staticmethod
    def read_manifest(site_dir: str | Path, *, verify: bool = True) -> dict[str, Any]:
        """The bundle's site.json, checked: schema, required keys, the version against the file hashes and, with
        `verify`, every data file's sha256 (files are hashed, not parsed). Raises InvalidFileError or
        BundleIntegrityError naming the file. For runners that need a site's id, version and counts
        (`meta["counts"]`) without loading its arrays."""
        return _read_checked(Path(site_dir), verify=verify)[0]

    @classmethod
    def load(cls, site_dir: str | Path) -> "Site":
        """Read and verify a bundle. Raises InvalidFileError (missing/malformed file) or BundleIntegrityError (a file
        whose sha256 differs from site.json, or a version that does not match the hashes), naming the file."""
        root = Path(site_dir)
        meta_path = root / "site.json"
        meta, blobs = _read_checked(root, verify=True)
        m = _cloud_from_ply(blobs["map.ply"], root / "map.ply")
        r = _cloud_from_ply(blobs["raw.ply"], root / "raw.ply")
        try:
            graph = SemanticGraph.from_dict(json.loads(blobs["graph.json"]))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InvalidFileError(root / "graph.json", f"malformed: {exc!r}") from exc
        try:
            label_maps = {str(k): {int(i): str(c) for i, c in v.items()} for k, v in meta["label_maps"].items()}
            classes = [str(c) for c in meta["classes"]]
        except (TypeError, ValueError, AttributeError) as exc:
            raise InvalidFileError(meta_path, f"malformed label_maps or classes: {exc!r}") from exc
        bad_class = (m["class_index"] >= len(classes)).any() or (r["class_index"] >= len(classes)).any()
        if bad_class:
            raise InvalidFileError(root / "map.ply", f"class indices beyond the {len(classes)} classes of site.json")
        return cls(
            site_id=str(meta["site_id"]), version=str(meta["version"]), meta=meta,
            points=m["points"], colors=m["colors"], normals=m["normals"], instance=m["instance"],
            class_index=m["class_index"], source=m["source"],
            raw_points=r["points"], raw_colors=r["colors"], raw_normals=r["normals"],
            raw_class_index=r["class_index"],
            graph=graph, classes=classes, label_maps=label_maps,
        )


def _read_checked(root: Path, *, verify: bool) -> tuple[dict[str, Any], dict[str, bytes]]:
    """(site.json, {data file: bytes}) of the bundle at `root`; the blobs only when `verify` (they are read to be
    hashed, and `Site.load` parses the same bytes rather than reading them twice)."""
    meta_path = root / "site.json"
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
        raise InvalidFileError(meta_path, f"not a cadreg site (schema {meta.get('schema') if isinstance(meta, dict) else None!r}, expected {SCHEMA!r})")
    for key in ("site_id", "version", "files", "classes", "label_maps"):
        if key not in meta:
            raise InvalidFileError(meta_path, f"missing key {key!r}")
    hashes = meta["files"]
    if not isinstance(hashes, dict) or set(hashes) != set(DATA_FILES):
        raise InvalidFileError(meta_path, f"'files' must list exactly {list(DATA_FILES)}")
    if version_of(hashes) != meta["version"]:
        raise BundleIntegrityError(meta_path, f"version {meta['version']!r} does not match the file hashes")
    blobs: dict[str, bytes] = {}
    if verify:
        for name in DATA_FILES:
            blob = read_bytes(root / name)
            if sha256_bytes(blob) != hashes[name]:
                raise BundleIntegrityError(root / name, "sha256 does not match site.json: the file was modified "
                                           "or belongs to another build")
            blobs[name] = blob
    return meta, blobs
