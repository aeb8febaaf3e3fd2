"""File I/O of site bundles and build inputs: hashing, reading and writing the bundle's files.

The bundle logic (what goes in which file, integrity rules) lives in `cadreg/site/bundle.py`; this module only
moves bytes, so that the core's file access stays in `cadreg/io/`.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import InvalidFileError


class FileStamp(NamedTuple):
    """What the file system says of a file: a write to it, or another file put in its place, changes one of these
    (the kernel sets the change time; no user can set it back)."""

    device: int
    inode: int
    size: int
    mtime_ns: int
    ctime_ns: int


def file_stamp(path: str | Path) -> FileStamp:
    try:
        st = os.stat(path)
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    return FileStamp(st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def sha256_bytes(data: bytes | bytearray) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes; InvalidFileError when it cannot be read."""
    path = Path(path)
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    return h.hexdigest()


def read_json(path: str | Path) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InvalidFileError(path, f"not valid JSON: {exc}") from exc


def read_bytes(path: str | Path) -> bytes:
    path = Path(path)
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc


def npy_bytes(array: np.ndarray) -> bytes:
    """The bytes of `array` as a .npy file (deterministic for the same array)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def map_npy(path: str | Path) -> np.ndarray:
    """A .npy file memory-mapped read-only (no pickle); InvalidFileError naming it when it is not one."""
    path = Path(path)
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InvalidFileError(path, f"not a readable .npy array: {exc}") from exc


def write_bundle_dir(out_dir: str | Path, files: dict[str, bytes | bytearray]) -> None:
    """Write the files of a bundle into `out_dir` (created if needed), as `BundleWriter` writes them."""
    with BundleWriter(out_dir) as bundle:
        for name, data in files.items():
            bundle.stage(name, data)
        bundle.commit()


class BundleWriter:
    """The files of a bundle written into `out_dir` (created if needed): each to a temporary name as it is staged,
    all renamed into place by `commit`, `site.json` (the file that vouches for the others) last, so a reader never sees
    a new site.json beside half-written data. Leaving the `with` block before the commit (an error) removes what was
    staged: the folder is as it was. Staged as they are encoded, a large bundle's files are never held in memory at
    once (a 100-room building's are 1.4 GB)."""

    def __init__(self, out_dir: str | Path) -> None:
        self.out = Path(out_dir)
        if self.out.exists() and not self.out.is_dir():
            raise InvalidFileError(self.out, "is a file: a bundle is written into a folder")
        self.out.mkdir(parents=True, exist_ok=True)
        self._staged: list[tuple[str, str]] = []

    def __enter__(self) -> "BundleWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        for _, tmp in self._staged:
            Path(tmp).unlink(missing_ok=True)
        self._staged = []

    def stage(self, name: str, data: bytes | bytearray) -> None:
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", dir=self.out)
        self._staged.append((name, tmp))
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; a service under another user must read the bundle

    def commit(self) -> None:
        for name, tmp in sorted(self._staged, key=lambda staged: (staged[0] == "site.json", staged[0])):
            os.replace(tmp, self.out / name)
        self._staged = []
