"""PLY reading and writing: meshes and point clouds with per-vertex colour and extra attributes.

Why a parser of our own: Open3D drops unknown vertex properties (ScanNet's uint16 `label`), and trimesh keeps them
only for some layouts. PLY is simple enough that a header parser plus numpy structured dtypes reads binary
(little and big endian) and ASCII files exactly, with every vertex property kept under its own name.

    read_ply(path) -> PlyData          every element, every property, as numpy arrays
    read_scan(path, labels_path=None)  -> ScanPoints (points, colours, normals, labels, faces) for a site build
    write_ply(path, vertex, faces=None) binary little-endian
    scan_ply_bytes(points, colors, faces, labels=None) a scan PLY as read_scan reads it
"""

from __future__ import annotations

import mmap
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InvalidArgument, InvalidFileError

_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
# A scan's coordinates must be kept to this by the map's 32-bit floats (`_check_precision`): 1 mm, which they
# keep within about 16 km of the origin.
MAX_COORDINATE_STEP_M = 0.001
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                 "f4": "float", "f8": "double"}


@dataclass
class _Element:
    name: str
    count: int
    # (name, dtype code) for scalars, (name, count dtype code, item dtype code) for lists
    props: list[tuple] = field(default_factory=list)


@dataclass
class PlyData:
    """Parsed PLY. `elements[name][prop]` is an array: (count,) for scalars; (count, k) for lists of one length
    k, else an object array of 1-D arrays."""

    format: str
    elements: dict[str, dict[str, np.ndarray]]
    counts: dict[str, int]

    @property
    def vertex(self) -> dict[str, np.ndarray]:
        return self.elements.get("vertex", {})


@dataclass
class ScanPoints:
    """A scan read for a site build (scan frame, metres).

    points : (N, 3) float32; colors : (N, 3) uint8 RGB; normals : (N, 3) float32 or None;
    labels : (N,) int64 label ids (e.g. NYU40) or None; faces : (M, 3) int64 vertex indices or None.
    """

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None
    labels: np.ndarray | None = None
    faces: np.ndarray | None = None


def _parse_header(path: Path, blob: bytes) -> tuple[str, list[_Element], int]:
    if not blob.startswith(b"ply"):
        raise InvalidFileError(path, "not a PLY file (no 'ply' magic)")
    end = blob.find(b"end_header")
    if end < 0:
        raise InvalidFileError(path, "PLY header has no end_header")
    nl = blob.find(b"\n", end)
    body_start = len(blob) if nl < 0 else nl + 1
    lines = blob[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[_Element] = []
    for raw in lines[1:]:
        parts = raw.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        try:
            if parts[0] == "format":
                fmt = parts[1]
            elif parts[0] == "element":
                elements.append(_Element(parts[1], int(parts[2])))
            elif parts[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if parts[1] == "list":
                    elements[-1].props.append((parts[4], _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]]))
                else:
                    elements[-1].props.append((parts[2], _PLY_TYPES[parts[1]]))
        except (IndexError, KeyError, ValueError) as exc:
            raise InvalidFileError(path, f"bad PLY header line {raw!r}: {exc}") from exc
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InvalidFileError(path, f"unsupported PLY format {fmt!r}")
    return fmt, elements, body_start


def _read_binary_element(path: Path, el: _Element, buf: memoryview, offset: int, endian: str):
    scalars = all(len(p) == 2 for p in el.props)
    if scalars:
        dtype = np.dtype([(p[0], endian + p[1]) for p in el.props])
        need = dtype.itemsize * el.count
        if offset + need > len(buf):
            raise InvalidFileError(
                path, f"element '{el.name}' declares {el.count} entries but the file ends after "
                f"{(len(buf) - offset) // max(dtype.itemsize, 1)}"
            )
        arr = np.frombuffer(buf, dtype=dtype, count=el.count, offset=offset)
        return {p[0]: arr[p[0]].copy() for p in el.props}, offset + need
    # Faces: one list property is the common case; try the fast path of all lists of one length first.
    if len(el.props) == 1 and el.count > 0:
        name, cnt_t, item_t = el.props[0]
        cnt_dt = np.dtype(endian + cnt_t)
        if offset + cnt_dt.itemsize > len(buf):
            raise InvalidFileError(path, f"element '{el.name}' is truncated")
        k = int(np.frombuffer(buf, dtype=cnt_dt, count=1, offset=offset)[0])
        dtype = np.dtype([("n", cnt_dt), ("v", endian + item_t, (k,))])
        need = dtype.itemsize * el.count
        if offset + need <= len(buf):
            arr = np.frombuffer(buf, dtype=dtype, count=el.count, offset=offset)
            if np.all(arr["n"] == k):
                return {name: arr["v"].astype(np.int64)}, offset + need
    # General path (mixed list lengths or several properties): one entry at a time.
    cols: dict[str, list] = {p[0]: [] for p in el.props}
    try:
        for _ in range(el.count):
            for p in el.props:
                if len(p) == 2:
                    dt = np.dtype(endian + p[1])
                    cols[p[0]].append(np.frombuffer(buf, dtype=dt, count=1, offset=offset)[0])
                    offset += dt.itemsize
                else:
                    cdt, idt = np.dtype(endian + p[1]), np.dtype(endian + p[2])
                    n = int(np.frombuffer(buf, dtype=cdt, count=1, offset=offset)[0])
                    offset += cdt.itemsize
                    cols[p[0]].append(np.frombuffer(buf, dtype=idt, count=n, offset=offset).copy())
                    offset += idt.itemsize * n
    except ValueError as exc:
        raise InvalidFileError(path, f"element '{el.name}' is truncated: {exc}") from exc
    return {k: _stack(v) for k, v in cols.items()}, offset


def _stack(values: list) -> np.ndarray:
    if values and isinstance(values[0], np.ndarray):
        lengths = {len(v) for v in values}
        if len(lengths) == 1:
            return np.stack(values).astype(np.int64)
        out = np.empty(len(values), dtype=object)
        out[:] = values
        return out
    return np.asarray(values)


def _read_ascii(path: Path, elements: list[_Element], body: bytes):
    tokens_by_line = body.decode("ascii", errors="replace").splitlines()
    lines = [ln for ln in tokens_by_line if ln.strip()]
    out: dict[str, dict[str, np.ndarray]] = {}
    row = 0
    for el in elements:
        if row + el.count > len(lines):
            raise InvalidFileError(
                path, f"element '{el.name}' declares {el.count} entries but the file has {len(lines) - row} lines left"
            )
        chunk = lines[row:row + el.count]
        row += el.count
        if all(len(p) == 2 for p in el.props):
            try:
                table = np.array([ln.split() for ln in chunk], dtype=np.float64).reshape(el.count, len(el.props))
            except ValueError as exc:
                raise InvalidFileError(path, f"element '{el.name}' has a malformed line: {exc}") from exc
            out[el.name] = {p[0]: table[:, i].astype(p[1]) for i, p in enumerate(el.props)}
        else:
            cols: dict[str, list] = {p[0]: [] for p in el.props}
            for ln in chunk:
                vals = ln.split()
                pos = 0
                try:
                    for p in el.props:
                        if len(p) == 2:
                            cols[p[0]].append(np.dtype(p[1]).type(float(vals[pos])))
                            pos += 1
                        else:
                            n = int(vals[pos])
                            cols[p[0]].append(np.array(vals[pos + 1:pos + 1 + n], dtype=np.int64))
                            if len(cols[p[0]][-1]) != n:
                                raise ValueError("list shorter than its count")
                            pos += 1 + n
                except (IndexError, ValueError) as exc:
                    raise InvalidFileError(path, f"element '{el.name}' has a malformed line {ln!r}: {exc}") from exc
            out[el.name] = {k: _stack(v) for k, v in cols.items()}
    return out


def read_ply(path: str | Path) -> PlyData:
    """Read any PLY file (ASCII, binary little or big endian). Raises InvalidFileError naming the file."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    return parse_ply(blob, path)


def map_vertices(path: str | Path) -> tuple[np.ndarray, mmap.mmap, int]:
    """The vertex element of a binary little-endian PLY whose only element is `vertex` with scalar properties,
    memory-mapped read-only: ((N,) structured array over the file's pages, the mmap, the byte offset of the first
    vertex). Nothing is read until it is
    used, and the pages a reader no longer needs can be handed back (`release_pages`). Raises InvalidFileError
    naming the file when it is not such a PLY or is shorter than its header says."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
            size = os.fstat(fh.fileno()).st_size
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else None
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    fmt, elements, body_start = _parse_header(path, head)
    if fmt != "binary_little_endian" or [e.name for e in elements] != ["vertex"] or any(
            len(p) != 2 for p in elements[0].props):
        raise InvalidFileError(path, "not a binary little-endian PLY of scalar vertex properties")
    el = elements[0]
    dtype = np.dtype([(p[0], "<" + p[1]) for p in el.props])
    if mm is None or body_start + dtype.itemsize * el.count > size:
        raise InvalidFileError(path, f"element 'vertex' declares {el.count} entries but the file is shorter")
    return np.frombuffer(mm, dtype=dtype, count=el.count, offset=body_start), mm, body_start


def release_pages(mm: mmap.mmap, start: int, stop: int) -> None:
    """Tell the kernel the mapped bytes [start, stop) of a read-only file map are not needed now: they leave the
    process's resident set and are read again from the page cache when next used."""
    page = mmap.PAGESIZE
    lo = (start // page) * page
    if stop > lo and hasattr(mm, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        mm.madvise(mmap.MADV_DONTNEED, lo, min(stop, len(mm)) - lo)


def parse_ply(blob: bytes, path: str | Path = "<bytes>") -> PlyData:
    """Parse PLY bytes; `path` only names the source in errors."""
    path = Path(path)
    fmt, elements, body_start = _parse_header(path, blob)
    if fmt == "ascii":
        data = _read_ascii(path, elements, blob[body_start:])
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        buf = memoryview(blob)
        offset = body_start
        data = {}
        for el in elements:
            data[el.name], offset = _read_binary_element(path, el, buf, offset, endian)
    return PlyData(format=fmt, elements=data, counts={el.name: el.count for el in elements})


def _vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    import trimesh

    mesh = trimesh.Trimesh(vertices=points.astype(np.float64), faces=faces, process=False)
    return np.asarray(mesh.vertex_normals, dtype=np.float32)


def read_scan(path: str | Path, labels_path: str | Path | None = None, *, label_property: str = "label") -> ScanPoints:
    """Read a scan (mesh or point cloud with per-vertex colour) for a site build.

    Colours are required (the refinement is colour-aided). Normals come from the file, else from the faces, else
    stay None (the caller estimates them). Labels come from `labels_path` (a PLY with the same vertices and a
    `label` property, as ScanNet's `*.labels.ply`), else from the scan itself when it carries `label`.
    """
    path = Path(path)
    ply = read_ply(path)
    v = ply.vertex
    if not v or not all(k in v for k in ("x", "y", "z")):
        raise InvalidFileError(path, "PLY has no vertex x, y, z")
    color_keys = next((keys for keys in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green",
                       "diffuse_blue")) if all(k in v for k in keys)), None)
    if color_keys is None:
        raise InvalidFileError(path, "PLY has no per-vertex colours (red, green, blue): the map needs colour")
    exact = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    if not np.all(np.isfinite(exact)):
        raise InvalidFileError(path, "PLY has non-finite vertex coordinates")
    _check_precision(path, exact)
    points = exact.astype(np.float32)
    cols = np.stack([v[k] for k in color_keys], axis=1)
    if cols.dtype.kind == "f":
        cols = np.clip(np.round(cols * (255.0 if cols.max() <= 1.0 else 1.0)), 0, 255)
    colors = cols.astype(np.uint8)
    faces = None
    face_el = ply.elements.get("face", {})
    face_key = next((k for k in ("vertex_indices", "vertex_index") if k in face_el), None)
    if face_key is not None and len(face_el[face_key]):
        f = face_el[face_key]
        if f.dtype == object or f.ndim != 2 or f.shape[1] != 3:
            # polygons: fan-triangulate so normals and sampling work on triangles
            tris = [np.stack([np.full(len(p) - 2, p[0]), p[1:-1], p[2:]], axis=1) for p in f if len(p) >= 3]
            f = np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)
        if f.size and (f.min() < 0 or f.max() >= len(points)):
            raise InvalidFileError(path, f"face indices out of range for {len(points)} vertices")
        faces = f.astype(np.int64)
    normals = None
    if all(k in v for k in ("nx", "ny", "nz")):
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float32)
    elif faces is not None and len(faces):
        normals = _vertex_normals(points, faces)
    labels = None
    if labels_path is not None:
        labels_path = Path(labels_path)
        lv = read_ply(labels_path).vertex
        if label_property not in lv:
            raise InvalidFileError(labels_path, f"PLY has no per-vertex '{label_property}' property")
        if len(lv[label_property]) != len(points):
            raise InvalidFileError(
                labels_path, f"has {len(lv[label_property])} vertices but the scan {path.name} has {len(points)}"
            )
        if all(k in lv for k in ("x", "y", "z")):
            lp = np.stack([lv["x"], lv["y"], lv["z"]], axis=1).astype(np.float32)
            # Same vertices in the same order, or the labels belong to another mesh.
            if np.max(np.abs(lp - points)) > 1e-3:
                raise InvalidFileError(labels_path, f"vertices differ from those of the scan {path.name}")
        labels = lv[label_property].astype(np.int64)
    elif label_property in v:
        labels = v[label_property].astype(np.int64)
    scan = ScanPoints(points=points, colors=colors, normals=normals, labels=labels, faces=faces)
    return _referenced(scan) if faces is not None and len(faces) else scan


def _check_precision(path: Path, xyz: np.ndarray) -> None:
    """InvalidFileError when the scan's coordinates lie so far from the origin that the map's 32-bit floats would
    not keep them to MAX_COORDINATE_STEP_M (a georeferenced scan: at 4,100 km from the origin, a UTM northing, they
    keep 25 cm, and a room built so had half its points merged and 46 made-up objects)."""
    far = float(np.abs(xyz).max()) if len(xyz) else 0.0
    step = float(np.spacing(np.float32(far)))
    if step > MAX_COORDINATE_STEP_M:
        shift = np.round(xyz.min(axis=0)).astype(np.int64)
        raise InvalidFileError(path, f"vertex coordinates reach {far:,.0f} m from the origin, where the map's 32-bit "
                                     f"floats keep only {step * 100:.2g} cm: move the scan near the origin (subtract "
                                     f"({', '.join(str(int(c)) for c in shift)}) from every vertex)")


def _referenced(scan: ScanPoints) -> ScanPoints:
    """A mesh's vertices that some face uses, with their colours, normals and labels, and the faces renumbered: a
    vertex no face uses is no surface of the scan (decimation's leftovers, stray points), and three such vertices
    2 km away stretched the build's floor plan over 2 km and ran it out of memory."""
    used = np.zeros(len(scan.points), dtype=bool)
    used[scan.faces.ravel()] = True
    if used.all():
        return scan
    keep = np.flatnonzero(used)
    renumber = np.full(len(scan.points), -1, dtype=np.int64)
    renumber[keep] = np.arange(len(keep))
    pick = lambda a: None if a is None else a[keep]  # noqa: E731
    return ScanPoints(points=scan.points[keep], colors=scan.colors[keep], normals=pick(scan.normals),
                      labels=pick(scan.labels), faces=renumber[scan.faces])


def write_ply(path: str | Path, vertex: dict[str, np.ndarray], faces: np.ndarray | None = None) -> None:
    """Write a binary little-endian PLY (see `ply_bytes`)."""
    Path(path).write_bytes(ply_bytes(vertex, faces))


def scan_ply_bytes(points: np.ndarray, colors: np.ndarray, faces: np.ndarray | None = None,
                   labels: np.ndarray | None = None) -> bytearray:
    """A scan PLY as `read_scan` reads it: x, y, z (points (n, 3), their dtype kept), red, green, blue (colors (n, 3)
    uint8), the per-vertex NYU40 `label` (labels (n,)) when given, and the faces."""
    vertex = {axis: points[:, k] for k, axis in enumerate("xyz")}
    vertex |= {channel: colors[:, k] for k, channel in enumerate(("red", "green", "blue"))}
    if labels is not None:
        vertex["label"] = labels
    return ply_bytes(vertex, faces)


def ply_bytes(vertex: dict[str, np.ndarray], faces: np.ndarray | None = None) -> bytearray:
    """Encode a binary little-endian PLY.

    vertex : property name -> (N,) array (dtype kept: float32, uint8, int32, int16, ...), in the given order.
    faces : (M, 3) int vertex indices, optional.
    """
    names = list(vertex)
    n = len(vertex[names[0]]) if names else 0
    arrays = {k: np.asarray(a) for k, a in vertex.items()}
    for k, a in arrays.items():
        if a.shape != (n,):
            raise InvalidArgument(f"vertex property {k!r} has shape {a.shape}, expected ({n},)")
    dtype = np.dtype([(k, "<" + arrays[k].dtype.str[1:]) for k in names])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {_NUMPY_TO_PLY[arrays[k].dtype.str[1:]]} {k}" for k in names]
    face_bytes = b""
    if faces is not None:
        faces = np.asarray(faces)
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        ft = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        ft["n"] = 3
        ft["v"] = faces
        face_bytes = ft.tobytes()
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    # The vertex table is filled in place in the output, which is returned as it is (a table, its bytes and their
    # concatenation were three copies of a 100-room building's 0.6 GB map at once).
    out = bytearray(len(head) + n * dtype.itemsize + len(face_bytes))
    out[:len(head)] = head
    table = np.frombuffer(out, dtype=dtype, count=n, offset=len(head))
    for k in names:
        table[k] = arrays[k]
    out[len(head) + table.nbytes:] = face_bytes
    return out
