"""The site registry: which sites the service serves, at which bundle version, from which directory.

The parent reads manifests, the workers load maps: at start every bundle under the sites root
(`<root>/<site_id>/site.json`) is checked here by `Site.read_manifest(verify=True)` (schema, keys, version, every
file's sha256; no point cloud is parsed) to learn its id, version and counts; only the workers parse the arrays.
An upload is hash-checked once, on its staged copy. A reload validates the new bundle first, has every worker load
it (they keep the old version for requests already dispatched), and only then swaps the registry entry: requests
in flight finish on the old version, requests admitted after the swap carry the new one.
"""

from __future__ import annotations

import logging
import shutil
import tarfile
import threading
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from cadreg.errors import BundleIntegrityError, InvalidFileError, UnknownSite

log = logging.getLogger("cadreg.service.registry")

STAGING_DIR = ".incoming"


@dataclass(frozen=True)
class SiteEntry:
    """What the front ends need to know about a loaded site (no arrays)."""

    site_id: str
    version: str
    path: str
    nodes: int
    edges: int
    points: int
    classes: tuple[str, ...]

    def summary(self) -> dict[str, Any]:
        return {"site_id": self.site_id, "version": self.version}

    def info(self) -> dict[str, Any]:
        return {"site_id": self.site_id, "version": self.version, "nodes": self.nodes, "edges": self.edges,
                "points": self.points, "classes": list(self.classes)}


def inspect_bundle(path: str | Path) -> SiteEntry:
    """Hash-check the bundle at `path` and read its manifest (raises InvalidFileError / BundleIntegrityError naming
    the file) -> its entry. Reads every file to hash it but parses only site.json: a map of millions of points
    costs the parent no memory, the workers load it."""
    from cadreg.site.bundle import Site

    meta_path = Path(path) / "site.json"
    meta = Site.read_manifest(path, verify=True)
    counts = meta.get("counts")
    if not isinstance(counts, dict):
        raise InvalidFileError(meta_path, "missing key 'counts' (points, raw_points, nodes, edges)")
    try:
        sizes = {key: int(counts[key]) for key in ("points", "nodes", "edges")}
        classes = tuple(str(c) for c in meta["classes"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidFileError(meta_path, f"malformed counts or classes: {exc!r}") from None
    return SiteEntry(
        site_id=str(meta["site_id"]),
        version=str(meta["version"]),
        path=str(Path(path).resolve()),
        classes=classes,
        **sizes,
    )


def find_bundles(root: Path) -> list[Path]:
    """Bundle directories under `root`: each sub-directory holding a site.json (or `root` itself when it is one)."""
    if (root / "site.json").is_file():
        return [root]
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / "site.json").is_file())


class SiteRegistry:
    """Site id -> SiteEntry, swapped atomically under a lock."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._lock = threading.Lock()
        self._sites: dict[str, SiteEntry] = {}
        self._reload_locks: dict[str, threading.Lock] = {}

    def load_all(self) -> list[SiteEntry]:
        """Check every bundle under the root (manifest and hashes); any bad bundle fails the start (naming its file)."""
        entries: dict[str, SiteEntry] = {}
        for path in find_bundles(self.root):
            entry = inspect_bundle(path)
            if entry.site_id in entries:
                raise InvalidFileError(path / "site.json", f"site id {entry.site_id!r} is also in {entries[entry.site_id].path}")
            entries[entry.site_id] = entry
            log.info("site %s version %s from %s (%d nodes, %d points)", entry.site_id, entry.version, path,
                     entry.nodes, entry.points)
        with self._lock:
            self._sites = entries
        return list(entries.values())

    def get(self, site_id: str) -> SiteEntry:
        with self._lock:
            entry = self._sites.get(site_id)
        if entry is None:
            raise UnknownSite(f"unknown site {site_id!r}", detail={"site_id": site_id})
        return entry

    def entries(self) -> list[SiteEntry]:
        with self._lock:
            return sorted(self._sites.values(), key=lambda e: e.site_id)

    def paths(self) -> dict[str, str]:
        with self._lock:
            return {sid: e.path for sid, e in self._sites.items()}

    def reload_lock(self, site_id: str) -> threading.Lock:
        """One reload per site at a time."""
        with self._lock:
            return self._reload_locks.setdefault(site_id, threading.Lock())

    def swap(self, entry: SiteEntry) -> SiteEntry | None:
        """Make `entry` the served version of its site; returns the entry it replaced."""
        with self._lock:
            old = self._sites.get(entry.site_id)
            self._sites[entry.site_id] = entry
        log.info("site %s now at version %s (was %s)", entry.site_id, entry.version, old.version if old else None)
        return old

    # --- archives -----------------------------------------------------------------------------------------------

    def stage_archive(self, site_id: str, archive: Path) -> Path:
        """Unpack a tar (optionally compressed) or zip archive of a bundle into a fresh staging directory under
        the root and return the bundle directory in it. The files may sit at the archive's top or inside one
        top-level directory. Members that would land outside the staging directory are refused."""
        staging = self.root / STAGING_DIR / f"{site_id}-{uuid.uuid4().hex[:8]}"
        staging.mkdir(parents=True)
        try:
            if zipfile.is_zipfile(archive):
                with zipfile.ZipFile(archive) as zf:
                    for name in zf.namelist():
                        _check_member(name, archive)
                    zf.extractall(staging)
            elif tarfile.is_tarfile(archive):
                with tarfile.open(archive) as tf:
                    # the "data" filter refuses absolute paths, links out of the tree, devices and the like
                    tf.extractall(staging, filter="data")
            else:
                raise InvalidFileError("upload", "not a tar or zip archive")
        except (tarfile.TarError, zipfile.BadZipFile, OSError, EOFError) as exc:
            shutil.rmtree(staging, ignore_errors=True)
            raise InvalidFileError("upload", f"unreadable archive: {exc}") from None
        except Exception:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        if (staging / "site.json").is_file():
            return staging
        inner = [p for p in staging.iterdir() if p.is_dir()]
        if len(inner) == 1 and (inner[0] / "site.json").is_file():
            return inner[0]
        shutil.rmtree(staging, ignore_errors=True)
        raise InvalidFileError("upload", "the archive holds no site.json (at its top or in one top-level folder)")

    def install(self, site_id: str, bundle_dir: Path) -> Path:
        """Move a validated staged bundle to `<root>/<site_id>`; the directory it replaces is removed.

        Workers already hold the old version in memory, so replacing its files does not disturb them."""
        target = self.root / site_id
        trash = self.root / STAGING_DIR / f"old-{site_id}-{uuid.uuid4().hex[:8]}"
        if target.exists():
            target.rename(trash)
        Path(bundle_dir).rename(target)
        staging_parent = Path(bundle_dir).parent
        if staging_parent != self.root / STAGING_DIR and staging_parent.parent == self.root / STAGING_DIR:
            shutil.rmtree(staging_parent, ignore_errors=True)
        shutil.rmtree(trash, ignore_errors=True)
        return target


def _check_member(name: str, archive: Path) -> None:
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts:
        raise BundleIntegrityError(archive, f"archive member {name!r} would land outside the bundle")
