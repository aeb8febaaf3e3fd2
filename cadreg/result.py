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
    UNCERTAIN = "uncertain"  # a pose with weak support or a close rival: in `hypotheses`, not claimed
    NO_OBJECTS = "no_objects"
    NO_MATCH = "no_match"
    LOW_OVERLAP = "low_overlap"
    FAILED = "failed"


SUCCESS_STATUSES = (Status.OK, Status.AMBIGUOUS)


@dataclass
class Hypothesis:
    """One pose hypothesis as reported (`LocalizationResult.hypotheses`), after its coarse GICP.

    T_map_camera : (4, 4) float64, colour camera -> map, metres.
    sim, s_v, s_e : the paper's Sim = α·S_V + β·S_E and its node and edge terms (eq. 6–8), in [0, 1]; 0 for
        hypotheses not from the graph.
    geometric_score : geometric fitness weighted by label and colour agreement with the map, in [0, 1] (what
        hypotheses are ranked by); in a building, the view agreement (share of the frame's rays along which the map
        shows what the frame measured, `localize/field_view.py`).
    matches : (scan object index, map node id) pairs the hypothesis rests on.
    source : "graph" | "prior" | "fallback:<name>"; in a building also "graph:unverified" / "fallback:bbs:unverified"
        (a tied room there was no budget to verify: reported as found) and "twin" (the answer's view moved into a
        room that repeats the answer's, `localize/twins.py`).
    region : id of the site region the pose looks into (a building's room; the site's id for a one-room site).
    """

    T_map_camera: np.ndarray
    sim: float
    s_v: float
    s_e: float
    geometric_score: float
    matches: list[tuple[int, str]] = field(default_factory=list)  # (scan object index, map node id)
    source: str = "graph"  # graph | fallback | prior
    region: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "T_map_camera": np.asarray(self.T_map_camera).tolist(),
            "sim": float(self.sim),
            "s_v": float(self.s_v),
            "s_e": float(self.s_e),
            "geometric_score": float(self.geometric_score),
            "matches": [[int(i), str(n)] for i, n in self.matches],
            "source": self.source,
            "region": self.region,
        }


@dataclass
class ScanObject:
    """An object found in the frame: its graph class, centroid (colour-camera frame, metres) and point count (at
    the frame's voxel size)."""

    cls: str
    centroid: list[float]
    points: int

    def to_dict(self) -> dict[str, Any]:
        return {"class": self.cls, "centroid": [float(x) for x in self.centroid], "points": int(self.points)}


@dataclass
class Match:
    """Scan object `scan_object` (index into `Diagnostics.scan_objects`) matched to map node `node_id` of class
    `cls`."""

    scan_object: int
    node_id: str
    cls: str

    def to_dict(self) -> dict[str, Any]:
        return {"scan_object": int(self.scan_object), "node_id": self.node_id, "class": self.cls}


@dataclass
class Refinement:
    """The fine refinement: `method` (one of the refinement methods), `iterations`, `fitness` (share of the frame's
    points within the inlier distance of the map, in [0, 1]), `inlier_rmse_m` (their RMSE, metres), `converged`."""

    method: str = ""
    iterations: int = 0
    fitness: float = 0.0
    inlier_rmse_m: float = 0.0
    converged: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Roi:
    """The region of interest of the refinement (paper §2.5).

    center : [x, y, z] of the frame's centre under the refined pose, map frame, metres. radius_m : γ, metres.
    points : map points (at the fitness resolution) within the radius. frame_points : frame points refined.
    """

    center: list[float]
    radius_m: float
    points: int
    frame_points: int

    def to_dict(self) -> dict[str, Any]:
        return {"center": [float(x) for x in self.center], "radius_m": float(self.radius_m),
                "points": int(self.points), "frame_points": int(self.frame_points)}


@dataclass
class Diagnostics:
    """The evidence behind a result.

    scan_objects : objects found in the frame. matches : of the winning graph hypothesis. roi : the refinement's
    region of interest, None when nothing was refined. refinement : the fine refinement, None likewise.
    stage_ms : wall milliseconds per stage (points, cluster, gravity, match, verify, fallback, refine; a tracked
        frame: points, track; a session frame whose tracking failed also points_tried, track_tried).
    method : which path produced the pose: "cadreg" (the graph) | "fallback:<name>" | "prior" | "track".
    mode : for a session's frame (`localize/tracking.py`), how it was answered: "tracked" (refined from the
        session's motion prediction), "relocalized" (the session's tracking failed or went stale: localized
        globally with the prediction as a prior) or "global" (a new session: localized from nothing); None for
        a frame outside any session.
    site_id, bundle_version : the site and bundle that answered. frame_points : valid depth points used.
    notes : what a person reading the result should know (up source, refused fallbacks, close rivals).
    """

    scan_objects: list[ScanObject] = field(default_factory=list)
    matches: list[Match] = field(default_factory=list)
    roi: Roi | None = None
    refinement: Refinement | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)
    method: str = "cadreg"
    site_id: str = ""
    bundle_version: str = ""
    frame_points: int = 0
    notes: list[str] = field(default_factory=list)
    mode: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "scan_objects": [o.to_dict() for o in self.scan_objects],
            "matches": [m.to_dict() for m in self.matches],
            "roi": self.roi.to_dict() if self.roi else None,
            "refinement": self.refinement.to_dict() if self.refinement else None,
            "stage_ms": {k: float(v) for k, v in self.stage_ms.items()},
            "method": self.method,
            "site_id": self.site_id,
            "bundle_version": self.bundle_version,
            "frame_points": int(self.frame_points),
            "notes": list(self.notes),
            "mode": self.mode,
        }


@dataclass
class LocalizationResult:
    """The answer to one frame (DESIGN §5).

    status : see `Status`. T_map_camera : (4, 4) float64 colour camera -> map, metres; None unless the status is
    `ok` or `ambiguous`. confidence : in [0, 1] (`localize.stages.confidence`). covariance : (6, 6) over
    (rx, ry, rz, tx, ty, tz), rad² / m², or None. hypotheses : the best `top_k`, best first. diagnostics : the
    evidence. frame_id : echoed from the frame.
    """

    status: Status
    T_map_camera: np.ndarray | None = None
    confidence: float = 0.0
    covariance: np.ndarray | None = None
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
