"""The answer to one localization (DESIGN §5), as plain dataclasses with a JSON-able `to_dict`.

`T_map_camera` maps colour-camera points into the map. It is None unless `status` is `ok` or `ambiguous`:
failure is never an identity pose.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from .geometry import R_to_quat_wxyz


class Status(str, Enum):
    OK = "ok"
    AMBIGUOUS = "ambiguous"
    NO_OBJECTS = "no_objects"
    NO_MATCH = "no_match"
    LOW_OVERLAP = "low_overlap"
    FAILED = "failed"


SUCCESS_STATUSES = (Status.OK, Status.AMBIGUOUS)


@dataclass
class Hypothesis:
    T_map_camera: np.ndarray
    sim: float
    s_v: float
    s_e: float
    geometric_score: float
    matches: list[tuple[int, str]] = field(default_factory=list)  # (scan object index, map node id)
    source: str = "graph"  # graph | fallback | prior

    def to_dict(self) -> dict[str, Any]:
        return {
            "T_map_camera": np.asarray(self.T_map_camera).tolist(),
            "sim": float(self.sim),
            "s_v": float(self.s_v),
            "s_e": float(self.s_e),
            "geometric_score": float(self.geometric_score),
            "matches": [[int(i), str(n)] for i, n in self.matches],
            "source": self.source,
        }


@dataclass
class ScanObject:
    cls: str
    centroid: list[float]  # colour-camera frame, metres
    points: int

    def to_dict(self) -> dict[str, Any]:
        return {"class": self.cls, "centroid": [float(x) for x in self.centroid], "points": int(self.points)}


@dataclass
class Match:
    scan_object: int
    node_id: str
    cls: str

    def to_dict(self) -> dict[str, Any]:
        return {"scan_object": int(self.scan_object), "node_id": self.node_id, "class": self.cls}


@dataclass
class Refinement:
    method: str = ""
    iterations: int = 0
    fitness: float = 0.0
    inlier_rmse_m: float = 0.0
    converged: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Diagnostics:
    scan_objects: list[ScanObject] = field(default_factory=list)
    matches: list[Match] = field(default_factory=list)
    roi: dict[str, Any] | None = None  # {"center": [x, y, z], "radius_m": r, "points": map n, "frame_points": n}
    refinement: Refinement | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)
    method: str = "cadreg"  # which path produced the pose: cadreg (graph) | fallback:<name> | prior
    site_id: str = ""
    bundle_version: str = ""
    frame_points: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scan_objects": [o.to_dict() for o in self.scan_objects],
            "matches": [m.to_dict() for m in self.matches],
            "roi": self.roi,
            "refinement": self.refinement.to_dict() if self.refinement else None,
            "stage_ms": {k: float(v) for k, v in self.stage_ms.items()},
            "method": self.method,
            "site_id": self.site_id,
            "bundle_version": self.bundle_version,
            "frame_points": int(self.frame_points),
            "notes": list(self.notes),
        }


@dataclass
class LocalizationResult:
    status: Status
    T_map_camera: np.ndarray | None = None
    confidence: float = 0.0
    covariance: np.ndarray | None = None  # (6, 6) over (rx, ry, rz, tx, ty, tz), rad² / m²
    hypotheses: list[Hypothesis] = field(default_factory=list)
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
    frame_id: str | None = None

    @property
    def succeeded(self) -> bool:
        return self.status in SUCCESS_STATUSES and self.T_map_camera is not None

    def to_dict(self) -> dict[str, Any]:
        pose = None
        if self.T_map_camera is not None:
            T = np.asarray(self.T_map_camera, dtype=float)
            pose = {"translation": T[:3, 3].tolist(), "quaternion_wxyz": R_to_quat_wxyz(T[:3, :3]).tolist()}
        return {
            "status": self.status.value,
            "frame_id": self.frame_id,
            "T_map_camera": None if self.T_map_camera is None else np.asarray(self.T_map_camera).tolist(),
            "pose": pose,
            "confidence": float(self.confidence),
            "covariance": None if self.covariance is None else np.asarray(self.covariance).tolist(),
            "hypotheses": [h.to_dict() for h in self.hypotheses],
            "diagnostics": self.diagnostics.to_dict(),
        }
