"""The bundled demo site: a procedural 6 m x 5 m x 2.6 m room written as real site-build inputs.

`write_demo_inputs(dir)` writes what a user would bring for a real building, and `build_demo_site(out_dir)` builds
it through the same `build_site` path as real data:

    demo_room_vh_clean.ply       the "scan": a labelled triangle mesh (x y z, red green blue, NYU40 `label`), z up,
                                 metres, furniture as scanned (densely meshed, vertices jittered by a few mm)
    scan2cad_demo.json           Scan2CAD-format alignments of the CAD-annotated furniture
    cad/<synset>/<id>/models/model_normalized.obj   ShapeNet-style CAD models (y up, centred, unit bbox diagonal)

The room: wood-plank floor, four walls each of its own hue with gradients and bands, a ceiling; a door (NYU40 8), a
window (9) and a whiteboard (30) on the walls; a table with a row of three identical chairs (deliberate ambiguity),
a fourth chair of another model at its end, a desk with a chair by the window, a cabinet and a bin in a corner, a
bookshelf, a sofa and one more chair. The sofa and that last chair have no CAD (they become clustering nodes); all
else is CAD-aligned. The layout is asymmetric so one view can be told from another.

Everything is computed in memory; files are written through `cadreg.io` (the only file I/O of the core).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ..config import SiteBuildConfig
from ..errors import InvalidArgument
from ..geometry import R_to_quat_wxyz, make_T
from ..io.bundle_files import write_bundle_dir
from ..io.ply import scan_ply_bytes

ROOM_X_M, ROOM_Y_M, ROOM_Z_M = 6.0, 5.0, 2.6
SITE_ID = "demo_room"
SCAN_NAME = "demo_room_vh_clean.ply"
SCAN2CAD_NAME = "scan2cad_demo.json"
_GRID_M = 0.05  # scan vertex spacing: about ScanNet's vh_clean_2 density
_SCAN_JITTER_M = 0.003

# NYU40 ids
WALL, FLOOR, CABINET, CHAIR, SOFA, TABLE, DOOR, WINDOW, BOOKSHELF, CEILING, WHITEBOARD, OTHERFURNITURE = (
    1, 2, 3, 5, 6, 7, 8, 9, 10, 22, 30, 39)


@dataclass(frozen=True)
class DemoInputs:
    """Paths of the written demo inputs."""

    root: Path
    scan_ply: Path
    scan2cad_json: Path
    cad_root: Path


@dataclass(frozen=True)
class Placement:
    """One piece of furniture: model name, NYU40 label, position on the floor (x, y), heading, CAD or not."""

    model: str
    label: int
    xy: tuple[float, float]
    yaw_deg: float
    color: tuple[int, int, int]
    cad: bool


# model name -> (ShapeNet synset, CAD id)
CAD_IDS: dict[str, tuple[str, str]] = {
    "chair_a": ("03001627", "demo0000chair0a"),
    "chair_b": ("03001627", "demo0000chair0b"),
    "table": ("04379243", "demo0000table00"),
    "desk": ("04379243", "demo0000desk000"),
    "cabinet": ("02933112", "demo000cabinet0"),
    "bin": ("02747177", "demo0000bin0000"),
    "bookshelf": ("02871439", "demo0bookshelf0"),
    "sofa": ("04256520", "demo00000sofa00"),
}

LAYOUT: tuple[Placement, ...] = (
    Placement("table", TABLE, (2.2, 2.4), 0.0, (150, 100, 60), True),
    # three identical chairs in a row on the table's far side: the ambiguity case
    Placement("chair_a", CHAIR, (1.6, 3.05), 180.0, (40, 60, 140), True),
    Placement("chair_a", CHAIR, (2.2, 3.05), 180.0, (40, 60, 140), True),
    Placement("chair_a", CHAIR, (2.8, 3.05), 180.0, (40, 60, 140), True),
    Placement("chair_b", CHAIR, (3.3, 2.35), 90.0, (170, 40, 40), True),
    Placement("chair_b", CHAIR, (1.85, 1.7), -8.0, (170, 40, 40), False),  # un-annotated chair
    Placement("desk", TABLE, (5.6, 2.0), 90.0, (200, 190, 170), True),
    Placement("chair_a", CHAIR, (5.0, 2.1), -90.0, (30, 120, 60), True),
    Placement("cabinet", CABINET, (5.45, 4.72), 180.0, (110, 110, 120), True),
    Placement("bin", OTHERFURNITURE, (4.75, 4.78), 0.0, (60, 160, 60), True),
    Placement("bookshelf", BOOKSHELF, (3.55, 4.83), 180.0, (120, 80, 40), True),
    Placement("sofa", SOFA, (0.45, 1.3), -90.0, (80, 90, 70), False),
)

# wall panels: (name, label, wall, (a0, a1) along the wall, (z0, z1), thickness m, colour)
PANELS = (
    ("door", DOOR, "y0", (4.3, 5.2), (0.0, 2.1), 0.04, (140, 90, 50)),
    ("window", WINDOW, "x1", (2.9, 4.3), (0.9, 2.1), 0.03, (170, 210, 235)),
    ("whiteboard", WHITEBOARD, "y1", (0.9, 2.7), (0.9, 2.0), 0.02, (245, 245, 240)),
)


# --- parametric furniture (z up, origin at the floor centre of the footprint, front = +y) -------------------------


def _box(size: tuple[float, float, float], center: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=size, transform=make_T(t=center))


def furniture_mesh(model: str) -> trimesh.Trimesh:
    """The parametric model `model` as one trimesh (metres, z up, front = +y, origin on the floor)."""
    parts: list[trimesh.Trimesh] = []
    if model in ("chair_a", "chair_b"):
        w, d, h = (0.46, 0.46, 0.46) if model == "chair_a" else (0.50, 0.48, 0.47)
        back_h = 0.42 if model == "chair_a" else 0.55
        leg = 0.035
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(_box((leg, leg, h - 0.05), (sx * (w / 2 - leg / 2), sy * (d / 2 - leg / 2), (h - 0.05) / 2)))
        parts.append(_box((w, d, 0.05), (0, 0, h - 0.025)))
        parts.append(_box((w, 0.04, back_h), (0, -d / 2 + 0.02, h + back_h / 2)))
        if model == "chair_b":  # arm rests tell model b from model a
            for sx in (-1, 1):
                parts.append(_box((0.04, d * 0.8, 0.03), (sx * (w / 2 - 0.02), 0.0, h + 0.22)))
                parts.append(_box((0.03, 0.03, 0.22), (sx * (w / 2 - 0.02), d * 0.35, h + 0.11)))
    elif model in ("table", "desk"):
        L, W, H = (1.6, 0.8, 0.75) if model == "table" else (1.2, 0.6, 0.74)
        leg = 0.06 if model == "table" else 0.04
        parts.append(_box((L, W, 0.04), (0, 0, H - 0.02)))
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(_box((leg, leg, H - 0.04), (sx * (L / 2 - 0.08), sy * (W / 2 - 0.08), (H - 0.04) / 2)))
        if model == "desk":  # a drawer block under one side
            parts.append(_box((0.4, W - 0.1, 0.35), (L / 2 - 0.25, 0, H - 0.04 - 0.175)))
    elif model == "cabinet":
        parts.append(_box((0.9, 0.45, 1.1), (0, 0, 0.55)))
        for sx in (-1, 1):
            parts.append(_box((0.03, 0.03, 0.15), (sx * 0.06, 0.235, 0.75)))
    elif model == "bin":
        parts.append(trimesh.creation.cylinder(radius=0.15, height=0.36, sections=24, transform=make_T(t=(0, 0, 0.18))))
    elif model == "bookshelf":
        W, D, H, t = 0.9, 0.32, 1.8, 0.025
        parts += [_box((t, D, H), (sx * (W / 2 - t / 2), 0, H / 2)) for sx in (-1, 1)]
        parts += [_box((W - 2 * t, D, t), (0, 0, z)) for z in (t / 2, 0.45, 0.9, 1.35, H - t / 2)]
        parts.append(_box((W, 0.01, H), (0, -D / 2 + 0.005, H / 2)))
    elif model == "sofa":
        L, D = 2.0, 0.85
        parts.append(_box((L, D, 0.42), (0, 0, 0.21)))
        parts.append(_box((L, 0.2, 0.45), (0, -D / 2 + 0.1, 0.42 + 0.225)))
        parts += [_box((0.18, D, 0.25), (sx * (L / 2 - 0.09), 0, 0.42 + 0.125)) for sx in (-1, 1)]
    else:
        raise InvalidArgument(f"unknown demo model {model!r}")
    return trimesh.util.concatenate(parts)


# --- ShapeNet-style CAD and Scan2CAD alignment --------------------------------------------------------------------

# ShapeNet models are y up: (x, y, z)_zup -> (x, z, -y)_yup.
_R_YUP_ZUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _normalization(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """(bbox centre in metres, bbox diagonal in metres) of a metric model: ShapeNet centres and scales to 1."""
    lo, hi = mesh.bounds
    return (lo + hi) / 2.0, float(np.linalg.norm(hi - lo))


def cad_model(model: str) -> trimesh.Trimesh:
    """The ShapeNet-normalised CAD of `model`: y up, bbox centred at the origin, bbox diagonal 1."""
    mesh = furniture_mesh(model)
    c, s = _normalization(mesh)
    v = (mesh.vertices - c) @ _R_YUP_ZUP.T / s
    return trimesh.Trimesh(v, mesh.faces, process=False)


def T_room_model(p: Placement) -> np.ndarray:
    """Model frame (metric, z up, origin on the floor) -> room frame."""
    yaw = np.radians(p.yaw_deg)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    return make_T(R, (p.xy[0], p.xy[1], 0.0))


def scan2cad_trs(p: Placement) -> dict:
    """Scan2CAD `trs` of a placement: p_scan = T(t) R(q) S(s) p_cad with the scan's own trs the identity."""
    c, s = _normalization(furniture_mesh(p.model))
    T = T_room_model(p)
    R = T[:3, :3] @ _R_YUP_ZUP.T
    t = T[:3, 3] + T[:3, :3] @ c
    return {"translation": t.tolist(), "rotation": R_to_quat_wxyz(R).tolist(), "scale": [s, s, s]}


# --- the scan ------------------------------------------------------------------------------------------------------


def _grid(origin: np.ndarray, u: np.ndarray, v: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle origin + a·u + b·v (a, b in [0, 1]) meshed on a grid; faces wound so the normal is u × v."""
    nu = max(1, int(np.ceil(np.linalg.norm(u) / spacing_m)))
    nv = max(1, int(np.ceil(np.linalg.norm(v) / spacing_m)))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    q0, q1, q2, q3 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([q0, q1, q2], 1), np.stack([q0, q2, q3], 1)])
    return verts, faces


def _wall_color(name: str, p: np.ndarray) -> np.ndarray:
    base = {"y0": (225, 215, 170), "x1": (190, 210, 190), "y1": (200, 205, 225), "x0": (230, 200, 185)}[name]
    along = p[:, 0] if name in ("y0", "y1") else p[:, 1]
    shade = 0.8 + 0.2 * p[:, 2:3] / ROOM_Z_M                                  # brighter towards the ceiling
    band = 1.0 - 0.12 * (np.sin(along * 2.1 + {"y0": 0, "x1": 1, "y1": 2, "x0": 3}[name]) > 0.6)[:, None]
    col = np.asarray(base, float) * shade * band
    col[p[:, 2] < 0.1] *= 0.55                                                # baseboard
    return col


def _floor_color(p: np.ndarray) -> np.ndarray:
    plank = np.floor(p[:, 1] / 0.2).astype(int)
    jitter = ((plank * 7919) % 11) / 10.0 - 0.5                              # per-plank shade
    grain = 0.06 * np.sin(p[:, 0] * 9.0 + plank)
    base = np.array([150.0, 108.0, 70.0])
    return base * (1.0 + 0.18 * jitter[:, None] + grain[:, None] - 0.1 * p[:, 0:1] / ROOM_X_M)


def _room_parts() -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(vertices, faces, colours float, labels) of floor, ceiling, walls and wall panels."""
    X, Y, Z = ROOM_X_M, ROOM_Y_M, ROOM_Z_M
    e = np.eye(3)
    parts = []
    v, f = _grid(np.zeros(3), X * e[0], Y * e[1], _GRID_M)                    # floor, normal +z
    parts.append((v, f, _floor_color(v), np.full(len(v), FLOOR)))
    v, f = _grid(np.array([0, 0, Z]), Y * e[1], X * e[0], _GRID_M * 2)        # ceiling, normal -z
    parts.append((v, f, np.full((len(v), 3), 235.0) - 10 * v[:, :1] / X, np.full(len(v), CEILING)))
    walls = {  # inward normals
        "y0": (np.zeros(3), X * e[0], Z * e[2]),
        "x1": (np.array([X, 0, 0]), Y * e[1], Z * e[2]),
        "y1": (np.array([X, Y, 0]), -X * e[0], Z * e[2]),
        "x0": (np.array([0, Y, 0]), -Y * e[1], Z * e[2]),
    }
    for name, (o, u, w) in walls.items():
        v, f = _grid(o, w, u, _GRID_M)  # normal w x u = z x along = into the room
        parts.append((v, f, _wall_color(name, v), np.full(len(v), WALL)))
    for _, label, wall, (a0, a1), (z0, z1), thick, color in PANELS:
        o, u, _ = walls[wall]
        along = u / np.linalg.norm(u)
        inward = np.cross(e[2], along)
        start = o + along * (a0 if wall in ("y0", "x1") else (np.linalg.norm(u) - a1))
        width = a1 - a0
        center = start + along * width / 2 + inward * thick / 2 + e[2] * (z0 + z1) / 2
        R = np.stack([along, inward, e[2]], axis=1)
        box = trimesh.creation.box(extents=(width, thick, z1 - z0), transform=make_T(R, center))
        v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=_GRID_M)
        col = np.asarray(color, float) * (0.9 + 0.1 * (v[:, 2:3] - z0) / (z1 - z0))
        parts.append((v, f, col, np.full(len(v), label)))
    return parts


def _furniture_part(p: Placement, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    mesh = furniture_mesh(p.model)
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=0.04)
    v = v @ T_room_model(p)[:3, :3].T + T_room_model(p)[:3, 3]
    v = v + rng.normal(scale=_SCAN_JITTER_M, size=v.shape)
    h = v[:, 2:3] / max(float(np.ptp(v[:, 2])), 1e-6)
    col = np.asarray(p.color, float) * (0.75 + 0.35 * h) + rng.normal(scale=4.0, size=v.shape)
    return v, f, col, np.full(len(v), p.label)


def demo_scan() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The demo scan mesh: vertices (n, 3) float32 m, faces (m, 3) int64, colours (n, 3) uint8, labels (n,) uint16."""
    rng = np.random.default_rng(20240601)
    parts = _room_parts() + [_furniture_part(p, rng) for p in LAYOUT]
    verts, faces, cols, labs = [], [], [], []
    offset = 0
    for v, f, c, lab in parts:
        verts.append(v)
        faces.append(f + offset)
        cols.append(c)
        labs.append(lab)
        offset += len(v)
    return (np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int64),
            np.clip(np.rint(np.concatenate(cols)), 0, 255).astype(np.uint8),
            np.concatenate(labs).astype(np.uint16))


def demo_scan2cad() -> list[dict]:
    """The Scan2CAD annotation (one record) of the CAD-annotated placements."""
    models = []
    for p in LAYOUT:
        if not p.cad:
            continue
        synset, cad_id = CAD_IDS[p.model]
        cad = cad_model(p.model)
        lo, hi = cad.bounds
        models.append({
            "catid_cad": synset, "id_cad": cad_id, "trs": scan2cad_trs(p),
            "bbox": ((hi - lo) / 2).tolist(), "center": ((hi + lo) / 2).tolist(), "sym": "__SYM_NONE",
        })
    identity = {"translation": [0.0, 0.0, 0.0], "rotation": [1.0, 0.0, 0.0, 0.0], "scale": [1.0, 1.0, 1.0]}
    return [{"id_scan": SITE_ID, "trs": identity, "aligned_models": models}]


def write_demo_inputs(out_dir: str | Path) -> DemoInputs:
    """Write the demo scan, its Scan2CAD JSON and the CAD library into `out_dir`; returns their paths."""
    root = Path(out_dir)
    v, f, c, lab = demo_scan()
    scan = scan_ply_bytes(v, c, f, lab)
    write_bundle_dir(root, {SCAN_NAME: scan,
                            SCAN2CAD_NAME: json.dumps(demo_scan2cad(), indent=1).encode()})
    cad_root = root / "cad"
    for model in sorted({p.model for p in LAYOUT if p.cad}):
        synset, cad_id = CAD_IDS[model]
        obj = trimesh.exchange.obj.export_obj(cad_model(model), include_normals=False, include_texture=False)
        write_bundle_dir(cad_root / synset / cad_id / "models", {"model_normalized.obj": obj.encode()})
    return DemoInputs(root, root / SCAN_NAME, root / SCAN2CAD_NAME, cad_root)


def build_demo_site(
    out_dir: str | Path,
    *,
    config: SiteBuildConfig = SiteBuildConfig(),
    progress: Callable[[int, int], None] | None = None,
):
    """Write the demo inputs under `out_dir/inputs`, build the site through `build_site` (the real-data path) and
    save the bundle in `out_dir/site`. Deterministic. Returns the Site."""
    from .build import build_site

    out = Path(out_dir)
    inputs = write_demo_inputs(out / "inputs")
    site = build_site(inputs.scan_ply, scan2cad_json=inputs.scan2cad_json, cad_root=inputs.cad_root,
                      site_id=SITE_ID, config=config, progress=progress)
    site.save(out / "site")
    return site
