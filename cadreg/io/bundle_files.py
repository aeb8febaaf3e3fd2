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


def sha256_bytes(data: bytes) -> str:
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


def write_bundle_dir(out_dir: str | Path, files: dict[str, bytes]) -> None:
    """Write the files of a bundle into `out_dir` (created if needed).

    Each file goes to a temporary name first and is renamed into place, and `site.json` (the file that vouches for
    the others) is renamed last, so a reader never sees a new site.json beside half-written data.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in sorted(files, key=lambda name: (name == "site.json", name)):
        write_bundle_file(out, name, files[name])


def write_bundle_file(out_dir: Path, name: str, data: bytes) -> None:
    """One file of a bundle into the existing folder `out_dir`: written to a temporary name, renamed into place
    (`write_bundle_dir`; a writer of large bundles writes each file as it is encoded, site.json last)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", dir=out_dir)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; a service under another user must read the bundle
        os.replace(tmp, out_dir / name)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
