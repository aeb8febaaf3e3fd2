"""How close automatic CAD alignments come to an annotation (issue 13's acceptance figures).

    compare_alignments(annotated, auto, tolerance) -> [ObjectCheck]   one row per annotated object
    format_checks(rows) -> str                                        the table `cadreg site autocad-check` prints

Both sides are Scan2CAD scan records (`cadreg.io.scan2cad.Scan2CADScan`): an annotation, and what
`cadreg site build --auto-cad` writes. Each annotated object is paired with the nearest (horizontally) unused
automatic CAD of its class; the errors are those of the CADs' oriented boxes: centre (horizontal and height), yaw
of the CAD's x axis modulo the annotated model's rotational symmetry, and extents along the CAD axes (horizontal
extents sorted for models symmetric under 90° turns, whose axes are interchangeable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.scan2cad import AlignedModel, Scan2CADScan
from ..labels import synset_class
from .autocad import SYM_2, SYM_4, SYM_INF, SYM_NONE, SYM_PERIOD_DEG
from .objects import affine_box

_PAIR_RADIUS_M = 0.5  # an automatic CAD farther than this from an annotated object is not its alignment


@dataclass(frozen=True)
class Tolerance:
    horizontal_m: float = 0.05
    height_m: float = 0.10
    yaw_deg: float = 15.0
    extent_rel: float = 0.15


@dataclass
class ObjectCheck:
    """One annotated object against its automatic alignment (None fields: no automatic CAD near it)."""

    cls: str
    annotated_cad_id: str
    sym: str
    center: np.ndarray
    auto_cad_id: str | None = None
    auto_cls: str | None = None
    horizontal_m: float | None = None
    height_m: float | None = None
    yaw_deg: float | None = None
    extent_rel: float | None = None
    fit: dict | None = None
    ok: bool = False


@dataclass
class _Box:
    cls: str
    cad_id: str
    sym: str
    center: np.ndarray
    extent: np.ndarray  # along the CAD axes x, y (up), z
    yaw_deg: float      # of the CAD x axis in the map's xy plane
    fit: dict | None


def _box(scan: Scan2CADScan, m: AlignedModel, fit: dict | None = None) -> _Box:
    A = scan.A_scan_cad(m)
    center = np.zeros(3) if m.center is None else m.center
    half = np.full(3, 0.5) if m.bbox is None else m.bbox
    c, e, _ = affine_box(A, center - half, center + half)
    x_axis = A[:3, 0]
    return _Box(synset_class(m.catid_cad), f"{m.catid_cad}/{m.id_cad}", m.sym or SYM_NONE, c, e,
                float(np.degrees(np.arctan2(x_axis[1], x_axis[0]))), fit)


def _yaw_error(a_deg: float, b_deg: float, sym: str) -> float:
    period = SYM_PERIOD_DEG.get(sym, 360.0)
    if period == 0:
        return 0.0
    d = (a_deg - b_deg) % period
    return float(min(d, period - d))


def _extent_error(auto: np.ndarray, ann: np.ndarray, sym: str) -> float:
    if sym in (SYM_4, SYM_INF):
        auto = np.array([*sorted(auto[[0, 2]]), auto[1]])
        ann = np.array([*sorted(ann[[0, 2]]), ann[1]])
    return float(np.max(np.abs(auto - ann) / ann))


def compare_alignments(annotated: Scan2CADScan, auto: Scan2CADScan, fits: list[dict | None] | None = None,
                       tolerance: Tolerance = Tolerance()) -> list[ObjectCheck]:
    """One ObjectCheck per annotated model, in the annotation's order. `fits`: per automatic model, its fit."""
    fits = fits or [None] * len(auto.aligned_models)
    ann_boxes = [_box(annotated, m) for m in annotated.aligned_models]
    auto_boxes = [_box(auto, m, f) for m, f in zip(auto.aligned_models, fits)]
    pairs = sorted((float(np.linalg.norm(a.center[:2] - b.center[:2])), i, j)
                   for i, a in enumerate(ann_boxes) for j, b in enumerate(auto_boxes) if a.cls == b.cls)
    used_a: set[int] = set()
    used_b: set[int] = set()
    match: dict[int, int] = {}
    for d, i, j in pairs:
        if d <= _PAIR_RADIUS_M and i not in used_a and j not in used_b:
            match[i] = j
            used_a.add(i)
            used_b.add(j)
    rows = []
    for i, a in enumerate(ann_boxes):
        row = ObjectCheck(a.cls, a.cad_id, a.sym, a.center)
        if i in match:
            b = auto_boxes[match[i]]
            row.auto_cad_id, row.auto_cls, row.fit = b.cad_id, b.cls, b.fit
            row.horizontal_m = float(np.linalg.norm(b.center[:2] - a.center[:2]))
            row.height_m = float(abs(b.center[2] - a.center[2]))
            row.yaw_deg = _yaw_error(b.yaw_deg, a.yaw_deg, a.sym)
            row.extent_rel = _extent_error(b.extent, a.extent, a.sym)
            row.ok = (row.horizontal_m <= tolerance.horizontal_m and row.height_m <= tolerance.height_m
                      and row.yaw_deg <= tolerance.yaw_deg and row.extent_rel <= tolerance.extent_rel
                      and b.cls == a.cls)
        rows.append(row)
    return rows


_SYM_SHORT = {SYM_NONE: "none", SYM_2: "2", SYM_4: "4", SYM_INF: "inf"}


def format_checks(rows: list[ObjectCheck], tolerance: Tolerance = Tolerance()) -> str:
    """The per-object table and a summary line."""
    head = (f"{'class':<15} {'sym':<4} {'annotated centre [m]':<21} {'auto model':<42} {'dxy cm':>6} {'dz cm':>6} "
            f"{'yaw °':>6} {'ext %':>6} {'scan→cad cm':>11} {'cov scan/cad':>12}  ok")
    lines = [head]
    for r in rows:
        c = r.center
        centre = f"({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})"
        if r.auto_cad_id is None:
            lines.append(f"{r.cls:<15} {_SYM_SHORT.get(r.sym, r.sym):<4} {centre:<21} {'(none)':<42} "
                         f"{'-':>6} {'-':>6} {'-':>6} {'-':>6} {'-':>11} {'-':>12}  no")
            continue
        f = r.fit or {}
        d = f.get("median_scan_to_cad_m")
        cov = (f"{f['scan_coverage']:.2f}/{f['cad_coverage']:.2f}" if "scan_coverage" in f else "-")
        lines.append(
            f"{r.cls:<15} {_SYM_SHORT.get(r.sym, r.sym):<4} {centre:<21} {r.auto_cad_id:<42} "
            f"{100 * r.horizontal_m:>6.1f} {100 * r.height_m:>6.1f} {r.yaw_deg:>6.1f} {100 * r.extent_rel:>6.1f} "
            f"{'-' if d is None else f'{100 * d:.1f}':>11} {cov:>12}  {'yes' if r.ok else 'no'}")
    n_ok = sum(r.ok for r in rows)
    lines.append(f"{n_ok} of {len(rows)} annotated objects within {100 * tolerance.horizontal_m:.0f} cm "
                 f"horizontally, {100 * tolerance.height_m:.0f} cm in height, {tolerance.yaw_deg:.0f}° yaw "
                 f"(modulo symmetry), {100 * tolerance.extent_rel:.0f} % extents, same class")
    return "\n".join(lines)
