"""Wire schemas shared by the service and the clients (pydantic, `extra="forbid"`).

A frame travels as binary image parts (PNG/JPEG, see `service/codec.py`) plus one `FrameMeta` JSON document; the
answer is `LocalizationResult.to_dict()` plus `request_id` and `site_version`; every error is one `ErrorBody`.
Matrices are 4×4 row-major lists of floats: `T_color_depth` moves depth-camera points into the colour camera,
`pose_prior` is a `T_map_camera` (colour camera -> map). Metres everywhere.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, Strict, field_validator, model_validator

from cadreg.labels import label_set_name

WIRE_VERSION = 1
MAX_TOP_K = 20
MAX_SEARCH_REGIONS = 256

# Numbers on the wire are strict: JSON `true` is not 1 (pydantic's lax mode takes a bool, or a numeric string, for a
# number). A float field still takes a JSON integer.
WireInt = Annotated[int, Strict()]
WireFloat = Annotated[float, Strict()]


class _Wire(BaseModel):
    # NaN and inf are never valid on the wire: JSON parsers accept them, so refuse them here, once.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Intrinsics(_Wire):
    """Pinhole intrinsics in pixels, pixel-centre convention (u - cx); the size comes from the image itself."""

    fx: WireFloat = Field(gt=0, description="focal length along x, pixels")
    fy: WireFloat = Field(gt=0, description="focal length along y, pixels")
    cx: WireFloat = Field(description="principal point x, pixels (pixel-centre convention)")
    cy: WireFloat = Field(description="principal point y, pixels (pixel-centre convention)")


# The farthest a map coordinate the wire takes may lie from the map's origin, metres: beyond any building, and
# far inside what the localizer's arithmetic handles (a search centre of 1e300 m overflowed in its grid cells).
MAX_COORDINATE_M = 1e6
# A map coordinate: [x, y, z] of a search region's centre.
Coordinate = Annotated[float, Strict(), Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]


def _check_matrix4(value: list[list[float]] | None) -> list[list[float]] | None:
    if value is None:
        return None
    if len(value) != 4 or any(len(row) != 4 for row in value):
        raise ValueError("must be a 4x4 matrix (4 rows of 4 numbers)")
    if not all(math.isfinite(x) for row in value for x in row):
        raise ValueError("must hold finite numbers only")
    if any(abs(value[i][3]) > MAX_COORDINATE_M for i in range(3)):
        raise ValueError(f"its translation must lie within {MAX_COORDINATE_M:g} m of the origin")
    return value


class SearchRegionIn(_Wire):
    """Where the camera is, as the client knows it: a ball (`center` + `radius_m`, map frame, metres) or the ids
    of site regions (`GET /v1/sites/{site_id}` lists them). Hypotheses whose camera lies elsewhere (outside the ball,
    or the regions' boxes grown by `site.regions.CAMERA_MARGIN_M`) are not considered."""

    center: list[Coordinate] | None = Field(None, min_length=3, max_length=3,
                                            description="[x, y, z], map frame, metres (each within 1e6 m)")
    radius_m: WireFloat | None = Field(None, gt=0, le=100_000, description="radius of the ball, metres")
    region_ids: list[Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9._-]+$")]] | None = Field(
        None, min_length=1, max_length=MAX_SEARCH_REGIONS, description="region ids of the site")

    @model_validator(mode="after")
    def _one_form(self) -> "SearchRegionIn":
        ball = self.center is not None or self.radius_m is not None
        if ball == (self.region_ids is not None):
            raise ValueError("give either center and radius_m, or region_ids")
        if ball and (self.center is None or self.radius_m is None):
            raise ValueError("a ball needs both center and radius_m")
        return self


class FrameMeta(_Wire):
    """Everything about a frame that is not pixels."""

    frame_id: str | None = Field(None, max_length=256, description="echoed in the result")
    depth_intrinsics: Intrinsics = Field(description="intrinsics of the depth image (its size is the depth PNG's)")
    color_intrinsics: Intrinsics | None = Field(
        None, description="intrinsics of the colour image; None = same camera as depth (colour must then have the depth size)"
    )
    T_color_depth: list[list[WireFloat]] | None = Field(None, description="4x4 depth camera -> colour camera; None = identity")
    depth_scale: WireFloat = Field(1000.0, gt=0, description="depth units per metre (1000 = millimetres)")
    label_set: str = Field("nyu40", min_length=1, max_length=64, description="label set of the `labels` image")
    gravity: list[WireFloat] | None = Field(
        None, min_length=3, max_length=3, description="gravity ('down') [gx, gy, gz] in the colour camera frame"
    )
    pose_prior: list[list[WireFloat]] | None = Field(None, description="4x4 T_map_camera prior (colour camera -> map)")
    top_k: WireInt | None = Field(
        None, ge=1, le=MAX_TOP_K, description="hypotheses to return; None = the service's configured default (match.top_k)"
    )
    session_id: str | None = Field(
        None, min_length=1, max_length=128, pattern=r"^[A-Za-z0-9._:-]+$",
        description="tracking session: frames of one session are tracked from the last pose (diagnostics.mode); "
        "a zenoh stream device is a session of its own without it",
    )
    search_region: SearchRegionIn | None = Field(
        None, description="restrict the search to a ball or to site regions (a building's rooms)")
    depth_range_m: WireFloat | None = Field(
        None, gt=0, description="the farthest depth (metres) the depth camera measures a surface at, when known (a "
        "Kinect v1 about 4): in a building, a map surface beyond it on a ray the frame has no depth on is not held "
        "against a pose; None = 4 m; either way raised to the farthest depth the frame measured, at most 6 m",
    )
    stamp_s: WireFloat | None = Field(
        None, description="capture time of the frame, seconds on the client's clock: a session's motion is timed by "
        "it when given (by the frame's arrival otherwise); send it for every frame of a session or for none",
    )

    @field_validator("T_color_depth", "pose_prior")
    @classmethod
    def _matrix4(cls, value: list[list[float]] | None) -> list[list[float]] | None:
        return _check_matrix4(value)

    @field_validator("label_set")
    @classmethod
    def _label_set_name(cls, v: str) -> str:
        return label_set_name(v)  # "NYU40" is the set the sites call "nyu40"

    @field_validator("gravity")
    @classmethod
    def _gravity(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and math.sqrt(sum(x * x for x in value)) < 1e-6:
            raise ValueError("gravity must be a non-zero vector")
        return value


class ErrorBody(BaseModel):
    """The one error body of HTTP responses and zenoh `reply_err`."""

    code: str = Field(description="stable machine-readable code, e.g. invalid_frame, unknown_site, overloaded")
    message: str
    request_id: str | None = None
    detail: dict[str, Any] = Field(default_factory=dict)


class PoseOut(BaseModel):
    translation: list[float]
    quaternion_wxyz: list[float]


class LocalizeResponse(BaseModel):
    """`LocalizationResult.to_dict()` plus the request id and the bundle version that answered (DESIGN §5)."""

    model_config = ConfigDict(extra="allow")

    status: str = Field(description="ok | ambiguous | uncertain | no_objects | no_match | low_overlap | failed")
    frame_id: str | None = None
    T_map_camera: list[list[float]] | None = Field(None, description="4x4 colour camera -> map; None unless ok/ambiguous")
    pose: PoseOut | None = None
    confidence: float = 0.0
    covariance: list[list[float]] | None = None
    hypotheses: list[dict[str, Any]] = Field(default_factory=list)
    diagnostics: dict[str, Any] = Field(default_factory=dict)
    request_id: str
    site_id: str
    site_version: str


class SiteSummary(BaseModel):
    site_id: str
    version: str


class SiteList(BaseModel):
    sites: list[SiteSummary]


class RegionInfo(BaseModel):
    id: str = Field(description="region id (a composed building's room name); usable in `search_region.region_ids`")
    bounds: list[list[float]] | None = Field(
        description="[[x0, y0, z0], [x1, y1, z1]] axis-aligned box of the region's points, map frame, metres "
                    "(null for a bundle built before regions)")
    objects: int = Field(description="graph nodes inside the region")
    points: int = Field(description="map and raw points of the region")
    floor_m: float | None = Field(None, description="height of the region's floor along the site's up, metres "
                                  "(a composed building's rooms need not share one); null when the bundle does not say")


class SiteInfo(BaseModel):
    site_id: str
    version: str
    nodes: int = Field(description="objects in the semantic graph")
    edges: int
    points: int = Field(description="points in the enhanced map")
    classes: list[str]
    regions: list[RegionInfo] = Field(default_factory=list, description="the site's regions (rooms of a building)")


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    ready: bool
    sites: list[SiteSummary] = Field(default_factory=list)
    workers_alive: int = 0
    workers: int = 0
