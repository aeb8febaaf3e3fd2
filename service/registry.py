"""The site registry: which sites the service serves, at which bundle version, from which directory.

The parent reads manifests, the workers load maps: at start every bundle under the sites root
(`<root>/<site_id>/site.json`) is checked here by `Site.check_files` (schema, keys, version, every file's sha256; no
point cloud is parsed) to learn its id, version and counts; only the workers parse the arrays. What the check found
(each file's hash with its stamp) goes to the workers with the path: they do not hash again a file they map that
has not changed since (an upload's files, written a moment before their check, get no stamp: the workers hash them).
An upload is hash-checked once by the parent, on its staged copy. A reload validates the new bundle first, has every
worker load it (they keep the old version for requests already dispatched), and only then swaps the registry entry:
requests in flight finish on the old version, requests admitted after the swap carry the new one.
"""

from __future__ import annotations

import logging
import lzma
import re
import shutil
import tarfile
import threading
import uuid
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any

from cadreg.errors import BundleIntegrityError, CadregError, InputError, InvalidFileError, PayloadTooLarge, UnknownSite
from cadreg.labels import label_set_name
from cadreg.site.bundle import DATA_FILES, OPTIONAL_FILES, FileChecks

from .logs import log_event

log = logging.getLogger("cadreg.service.registry")

STAGING_DIR = ".incoming"
SITE_ID_RULE = "^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$"
_SITE_ID = re.compile(SITE_ID_RULE)
BUNDLE_FILES = ("site.json", *DATA_FILES, *OPTIONAL_FILES)  # all an archive may install: site.json and the files it references
MAX_ARCHIVE_MEMBERS = 10_000
_COPY_CHUNK = 1024 * 1024
_UPLOAD = "upload"  # what an archive is called in messages: never a server path


def check_site_id(site_id: str) -> str:
    """The one check of a site id from a client (URL, zenoh key): letters, digits, '.', '_', '-', starting with a
    letter or digit, at most 128 characters -> the id; else InputError (422 invalid_input) naming the rule. An id
    that passes is a safe single directory name under the sites root."""
    if not isinstance(site_id, str) or not _SITE_ID.fullmatch(site_id):
        shown = site_id[:40] + "..." if isinstance(site_id, str) and len(site_id) > 40 else site_id
        raise InputError(f"site id {shown!r} does not match {SITE_ID_RULE} (letters, digits, '.', '_', '-'; "
                         "at most 128 characters)", detail={"rule": SITE_ID_RULE})
    return site_id


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
    label_sets: tuple[str, ...] = ()  # the label sets the site has a label map for (site.json `label_maps`)
    regions: tuple[dict[str, Any], ...] = ()  # {id, bounds, objects, points} per region (`GET /v1/sites/{id}`)
    # what the parent's hash check found: the workers load the bundle without hashing again what has not changed
    checked: FileChecks = field(default_factory=dict, compare=False, repr=False)

    def summary(self) -> dict[str, Any]:
        return {"site_id": self.site_id, "version": self.version}

    def info(self) -> dict[str, Any]:
        return {"site_id": self.site_id, "version": self.version, "nodes": self.nodes, "edges": self.edges,
                "points": self.points, "classes": list(self.classes), "regions": [dict(r) for r in self.regions]}


def inspect_bundle(path: str | Path) -> SiteEntry:
    """Hash-check the bundle at `path` and read its manifest (raises InvalidFileError / BundleIntegrityError naming
    the file) -> its entry. Reads every file to hash it but parses only site.json: a map of millions of points
    costs the parent no memory, the workers load it."""
    from cadreg.site.bundle import Site

    meta_path = Path(path) / "site.json"
    meta, checked = Site.check_files(path)
    counts = meta.get("counts")
    if not isinstance(counts, dict):
        raise InvalidFileError(meta_path, "missing key 'counts' (points, raw_points, nodes, edges)")
    try:
        sizes = {key: int(counts[key]) for key in ("points", "nodes", "edges")}
        classes = tuple(str(c) for c in meta["classes"])
        label_sets = tuple(sorted(label_set_name(k) for k in meta.get("label_maps", {})))
        raw_points = int(counts.get("raw_points", 0))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InvalidFileError(meta_path, f"malformed counts, classes or label_maps: {exc!r}") from None
    regions = _region_infos(meta, meta_path, sizes, raw_points)
    return SiteEntry(
        site_id=str(meta["site_id"]),
        version=str(meta["version"]),
        path=str(Path(path).resolve()),
        classes=classes,
        label_sets=label_sets,
        regions=regions,
        checked=checked,
        **sizes,
    )


def _region_infos(meta: dict[str, Any], meta_path: Path, sizes: dict[str, int],
                  raw_points: int) -> tuple[dict[str, Any], ...]:
    """The regions of site.json as the API reports them; a bundle from before regions is one region without
    bounds."""
    from cadreg.site.regions import from_manifest

    if not meta.get("regions"):
        return ({"id": str(meta["site_id"]), "bounds": None, "objects": sizes["nodes"],
                 "points": sizes["points"] + raw_points},)
    regions = from_manifest(meta["regions"], map_points=sizes["points"], raw_points=raw_points, source=str(meta_path))
    return tuple(r.info() for r in regions)


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
            log_event(log, "site_found", site_id=entry.site_id, version=entry.version, path=str(path),
                      nodes=entry.nodes, points=entry.points)
        with self._lock:
            self._sites = entries
        return list(entries.values())

    def get(self, site_id: str) -> SiteEntry:
        """The served entry of `site_id`; InputError for a malformed id, UnknownSite for one not served."""
        check_site_id(site_id)
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

    def checks(self) -> dict[str, FileChecks]:
        """{site_id: what the hash check of its bundle found} (`Site.check_files`), for the workers' loads."""
        with self._lock:
            return {sid: e.checked for sid, e in self._sites.items()}

    def reload_lock(self, site_id: str) -> threading.Lock:
        """One reload per site at a time."""
        with self._lock:
            return self._reload_locks.setdefault(site_id, threading.Lock())

    def swap(self, entry: SiteEntry) -> SiteEntry | None:
        """Make `entry` the served version of its site; returns the entry it replaced."""
        with self._lock:
            old = self._sites.get(entry.site_id)
            self._sites[entry.site_id] = entry
        log_event(log, "site_swapped", site_id=entry.site_id, version=entry.version,
                  previous=old.version if old else None)
        return old

    # --- archives -----------------------------------------------------------------------------------------------

    def stage_archive(self, site_id: str, archive: Path, max_bytes: int) -> Path:
        """Unpack a tar (optionally compressed) or zip archive of a bundle into a fresh staging directory under
        the root and return that directory. The files may sit at the archive's top or inside one top-level
        directory; only `BUNDLE_FILES` are unpacked (anything else is skipped unread), only regular files, at most
        `max_bytes` in all, counted as they are written (a header's size is not trusted): past it PayloadTooLarge.
        Members that would land outside the bundle are refused. Errors name the "upload", never a server path."""
        check_site_id(site_id)
        staging = self.root / STAGING_DIR / f"{site_id}-{uuid.uuid4().hex[:8]}"
        staging.mkdir(parents=True)
        try:
            if zipfile.is_zipfile(archive):
                _unpack_zip(archive, staging, max_bytes)
            elif tarfile.is_tarfile(archive):
                _unpack_tar(archive, staging, max_bytes)
            else:
                raise InvalidFileError(_UPLOAD, "not a tar or zip archive")
            if not (staging / "site.json").is_file():
                raise InvalidFileError(_UPLOAD, "the archive holds no site.json (at its top or in one top-level folder)")
        except CadregError:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        except (tarfile.TarError, zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, zlib.error,
                lzma.LZMAError, RuntimeError, NotImplementedError, ValueError) as exc:
            shutil.rmtree(staging, ignore_errors=True)
            raise InvalidFileError(_UPLOAD, f"unreadable archive: {_scrub(exc, self.root, archive)}") from None
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return staging

    def install(self, site_id: str, bundle_dir: Path) -> Path:
        """Move a validated staged bundle to `<root>/<site_id>`; the directory it replaces is removed. Called only
        once a worker has loaded the staged bundle: the good bundle on disk is never replaced by one that fails.

        Workers already hold the old version in memory, so replacing its files does not disturb them."""
        check_site_id(site_id)
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


def _member_name(name: str) -> str | None:
    """The bundle file an archive member is (`site.json`, `<top>/map.ply`, ...), or None for one to skip. Raises
    BundleIntegrityError for a name that would land outside the bundle."""
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or ".." in p.parts:
        raise BundleIntegrityError(_UPLOAD, f"archive member {name[:200]!r} would land outside the bundle")
    parts = [part for part in p.parts if part not in ("", ".")]
    if len(parts) == 2 and not parts[0].startswith("."):
        parts = parts[1:]
    return parts[0] if len(parts) == 1 and parts[0] in BUNDLE_FILES else None


class _Budget:
    """Bytes left to unpack; counts what is actually written."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.used = 0

    def copy(self, src: IO[bytes], dst: Path) -> None:
        with open(dst, "xb") as out:  # "x": a second member of the same name is refused, not merged
            while chunk := src.read(_COPY_CHUNK):
                self.used += len(chunk)
                if self.used > self.max_bytes:
                    raise PayloadTooLarge(f"the archive unpacks to more than the {self.max_bytes}-byte limit",
                                          detail={"limit_bytes": self.max_bytes})
                out.write(chunk)


def _pick(names: list[tuple[str, Any]]) -> dict[str, Any]:
    """{bundle file: member} of the members to unpack, refusing too many members or a file given twice."""
    if len(names) > MAX_ARCHIVE_MEMBERS:
        raise InvalidFileError(_UPLOAD, f"more than {MAX_ARCHIVE_MEMBERS} archive members")
    chosen: dict[str, Any] = {}
    for raw, member in names:
        name = _member_name(raw)
        if name is None:
            continue
        if name in chosen:
            raise InvalidFileError(_UPLOAD, f"{name} is in the archive twice")
        chosen[name] = member
    return chosen


def _unpack_zip(archive: Path, staging: Path, max_bytes: int) -> None:
    budget = _Budget(max_bytes)
    with zipfile.ZipFile(archive) as zf:
        infos = [i for i in zf.infolist() if not i.is_dir()]
        for name, info in _pick([(i.filename, i) for i in infos]).items():
            with zf.open(info) as src:  # the CRC is checked at the member's end
                budget.copy(src, staging / name)


def _unpack_tar(archive: Path, staging: Path, max_bytes: int) -> None:
    budget = _Budget(max_bytes)
    with tarfile.open(archive) as tf:
        members: list[tuple[str, Any]] = []
        scanned = 0
        for member in tf:  # listing a compressed tar inflates it: skipped members count against the limit too
            scanned += max(0, member.size)
            if scanned > 4 * max_bytes:
                raise PayloadTooLarge(f"the archive unpacks to more than the {max_bytes}-byte limit",
                                      detail={"limit_bytes": max_bytes})
            if len(members) >= MAX_ARCHIVE_MEMBERS:
                raise InvalidFileError(_UPLOAD, f"more than {MAX_ARCHIVE_MEMBERS} archive members")
            if member.isfile():
                members.append((member.name, member))
            elif not member.isdir() and _member_name(member.name) is not None:
                raise InvalidFileError(_UPLOAD, f"{member.name[:200]!r} is not a regular file")
        for name, member in _pick(members).items():
            src = tf.extractfile(member)
            if src is None:
                raise InvalidFileError(_UPLOAD, f"{name} is not a regular file")
            with src:
                budget.copy(src, staging / name)


def _scrub(exc: BaseException, *paths: Path) -> str:
    """An archive error's text with no server path in it."""
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
    for path in paths:
        text = text.replace(str(path), "<upload>")
    return text[:300]
