"""Scan2CAD annotation JSON (github.com/skanti/Scan2CAD).

The file is a list of scan records: `id_scan`, the scan's own `trs`, and `aligned_models`, each with `catid_cad`
(ShapeNet synset), `id_cad`, `trs` {translation (3,), rotation quaternion (w, x, y, z), scale (3,)}, `bbox` (half
extents of the CAD in its own frame), `center`, `sym`. A CAD vertex lands in the scan (mesh) frame by
`p_scan = inv(M(trs_scan)) @ M(trs_cad) @ p_cad`, with `M(trs) = T(translation) · R(quaternion) · S(scale)`.

`write_scan2cad` writes such a file (automatic alignments, `cadreg site build --auto-cad`); extra keys per model
(cadreg's `origin` and `fit`) are kept for a person to read and ignored by `read_scan2cad`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidFileError
from ..geometry import R_to_quat_wxyz, quat_wxyz_to_R
from .bundle_files import write_bundle_dir


@dataclass(frozen=True)
class TRS:
    """Translation (3,) metres, rotation quaternion (w, x, y, z), anisotropic scale (3,)."""

    translation: np.ndarray
    rotation_wxyz: np.ndarray
    scale: np.ndarray

    def matrix(self) -> np.ndarray:
        """4×4 float64 M = T · R · S (affine, not rigid when the scale is not 1)."""
        M = np.eye(4)
        M[:3, :3] = quat_wxyz_to_R(self.rotation_wxyz) @ np.diag(self.scale)
        M[:3, 3] = self.translation
        return M

    @classmethod
    def from_affine(cls, A: np.ndarray) -> "TRS":
        """The TRS of a 4×4 affine A = T · R · S (R a rotation, S a positive diagonal scale), as Scan2CAD stores
        it. Raises InvalidArgument when A's linear part is not a rotation times a positive scale."""
        from ..errors import InvalidArgument

        A = np.asarray(A, dtype=np.float64)
        L = A[:3, :3]
        scale = np.linalg.norm(L, axis=0)
        R = L / np.where(scale > 0, scale, 1.0)
        if np.any(scale <= 0) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise InvalidArgument("affine is not translation · rotation · positive scale")
        q = R_to_quat_wxyz(R)
        # Normalised to a fixed point of the reader's own q / |q|, so a written TRS reads back bit for bit
        for _ in range(8):
            q_next = q / np.linalg.norm(q)
            if np.array_equal(q_next, q):
                break
            q = q_next
        return cls(A[:3, 3].copy(), q, scale)

    def to_json(self) -> dict[str, list[float]]:
        return {"translation": [float(x) for x in self.translation],
                "rotation": [float(x) for x in self.rotation_wxyz], "scale": [float(x) for x in self.scale]}


@dataclass(frozen=True)
class AlignedModel:
    catid_cad: str
    id_cad: str
    trs: TRS
    bbox: np.ndarray | None
    center: np.ndarray | None
    sym: str | None


@dataclass(frozen=True)
class Scan2CADScan:
    id_scan: str
    trs: TRS
    aligned_models: tuple[AlignedModel, ...]

    def A_scan_cad(self, model: AlignedModel) -> np.ndarray:
        """4×4 affine taking CAD-model coordinates into the scan (mesh) frame: inv(M(trs_scan)) @ M(trs_cad)."""
        return np.linalg.inv(self.trs.matrix()) @ model.trs.matrix()


def _vec(path: Path, obj: Any, n: int, what: str) -> np.ndarray:
    try:
        v = np.asarray(obj, dtype=np.float64).reshape(n)
    except (TypeError, ValueError) as exc:
        raise InvalidFileError(path, f"{what} must be {n} numbers, got {obj!r}") from exc
    if not np.all(np.isfinite(v)):
        raise InvalidFileError(path, f"{what} has non-finite values")
    return v


def _trs(path: Path, obj: Any, what: str) -> TRS:
    if not isinstance(obj, dict) or not {"translation", "rotation", "scale"} <= set(obj):
        raise InvalidFileError(path, f"{what}.trs needs translation, rotation, scale")
    q = _vec(path, obj["rotation"], 4, f"{what}.trs.rotation")
    if np.linalg.norm(q) < 1e-9:
        raise InvalidFileError(path, f"{what}.trs.rotation is a zero quaternion")
    s = _vec(path, obj["scale"], 3, f"{what}.trs.scale")
    if np.any(s <= 0):
        raise InvalidFileError(path, f"{what}.trs.scale must be positive, got {s.tolist()}")
    return TRS(_vec(path, obj["translation"], 3, f"{what}.trs.translation"), q / np.linalg.norm(q), s)


def read_scan2cad(path: str | Path) -> list[Scan2CADScan]:
    """Read a Scan2CAD annotation file (a list of scan records, or one record). Raises InvalidFileError."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise InvalidFileError(path, f"cannot read: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InvalidFileError(path, f"not valid JSON: {exc}") from exc
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data:
        raise InvalidFileError(path, "expected a non-empty list of Scan2CAD scan records")
    scans = []
    for i, rec in enumerate(data):
        what = f"record {i}"
        if not isinstance(rec, dict) or "trs" not in rec or not isinstance(rec.get("aligned_models"), list):
            raise InvalidFileError(path, f"{what} needs 'trs' and a list 'aligned_models'")
        models = []
        for j, m in enumerate(rec["aligned_models"]):
            mw = f"{what}.aligned_models[{j}]"
            if not isinstance(m, dict) or not {"catid_cad", "id_cad", "trs"} <= set(m):
                raise InvalidFileError(path, f"{mw} needs catid_cad, id_cad and trs")
            models.append(AlignedModel(
                catid_cad=str(m["catid_cad"]),
                id_cad=str(m["id_cad"]),
                trs=_trs(path, m["trs"], mw),
                bbox=_vec(path, m["bbox"], 3, f"{mw}.bbox") if "bbox" in m else None,
                center=_vec(path, m["center"], 3, f"{mw}.center") if "center" in m else None,
                sym=m.get("sym"),
            ))
        scans.append(Scan2CADScan(str(rec.get("id_scan", "")), _trs(path, rec["trs"], what), tuple(models)))
    return scans


def select_scan(scans: list[Scan2CADScan], scan_name: str, path: str | Path = "scan2cad") -> Scan2CADScan:
    """The record whose `id_scan` the scan file name starts with (scene0470_00_vh_clean_2.ply -> scene0470_00),
    or the only record. Raises InvalidFileError when none or several match."""
    if len(scans) == 1:
        return scans[0]
    hits = [s for s in scans if s.id_scan and scan_name.startswith(s.id_scan)]
    if len(hits) != 1:
        raise InvalidFileError(path, f"{len(hits)} records match the scan {scan_name!r} (of {len(scans)})")
    return hits[0]


def write_scan2cad(path: str | Path, records: list[dict[str, Any]]) -> None:
    """Write Scan2CAD records (JSON-able dicts: `id_scan`, `trs`, `aligned_models`, ...) as a Scan2CAD file."""
    path = Path(path)
    write_bundle_dir(path.parent, {path.name: (json.dumps(records, indent=1) + "\n").encode()})
