"""Typed, validated algorithm parameters, in sections (frozen pydantic models, `extra="forbid"`).

The paper's defaults live here: δ = 1.5 m (graph edges), γ = 3 m (ROI radius), ε = 1e-3 (refinement stop).
Components receive plain values from these sections; runners (CLI, service) build them once.
Each section is owned by the stage it configures; add fields with bounds and a comment saying why.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


# --- site build -------------------------------------------------------------------------------------------------


class EnhanceConfig(_Section):
    """Map enhancement (paper §2.2)."""

    box_dilation_m: float = Field(0.05, ge=0, description="raw points within the CAD's oriented box grown by this are replaced")
    cad_sample_spacing_m: float = Field(0.01, gt=0, description="mean spacing of points sampled on CAD surfaces")
    color_transfer_k: int = Field(4, ge=1, description="removed raw points averaged per CAD point for its colour")
    raw_voxel_m: float = Field(0.01, ge=0, description="voxel down-sampling of the raw scan before enhancement (0 = off)")


class GraphConfig(_Section):
    """Objects and semantic graph (paper §2.3.2)."""

    edge_max_m: float = Field(1.5, gt=0, description="δ: centroid pairs at most this far apart get an edge")
    cluster_tolerance_m: float = Field(0.05, gt=0, description="class-wise Euclidean clustering of uncovered labelled map points")
    min_cluster_points: int = Field(50, ge=1, description="smaller clusters are noise, not objects")


class SiteBuildConfig(_Section):
    enhance: EnhanceConfig = EnhanceConfig()
    graph: GraphConfig = GraphConfig()


# --- localization -----------------------------------------------------------------------------------------------


class FrameConfig(_Section):
    """Frame -> points (paper eq. 1–2)."""

    min_depth_m: float = Field(0.1, ge=0)
    max_depth_m: float = Field(6.0, gt=0)
    pixel_stride: int = Field(2, ge=1, description="use every n-th depth pixel: halves time at no loss (DESIGN §9)")
    voxel_size_m: float = Field(0.02, gt=0, description="voxel down-sampling of the frame points")


class ClusterConfig(_Section):
    """Class-wise Euclidean clustering of the frame (paper §2.3.1)."""

    tolerance_m: float = Field(0.05, gt=0)
    min_points: int = Field(30, ge=1)


class MatchConfig(_Section):
    """Coarse graph matching (paper §2.4)."""

    alpha: float = Field(0.5, ge=0, description="weight of node similarity S_V in Sim")
    beta: float = Field(0.5, ge=0, description="weight of edge similarity S_E in Sim")
    top_k: int = Field(5, ge=1)


class RefineConfig(_Section):
    """Fine refinement (paper §2.5)."""

    roi_radius_m: float = Field(3.0, gt=0, description="γ: the map is cropped to this radius around the hypothesis")
    epsilon: float = Field(1e-3, gt=0, description="ε: stop when the update is below this")
    method: Literal["color_gicp", "small_gicp", "open3d_colored_icp"] = "color_gicp"


class FallbackConfig(_Section):
    """Geometric global registration when the graph has too little to say."""

    voxel_size_m: float = Field(0.05, gt=0)


class LocalizeConfig(_Section):
    frame: FrameConfig = FrameConfig()
    cluster: ClusterConfig = ClusterConfig()
    match: MatchConfig = MatchConfig()
    refine: RefineConfig = RefineConfig()
    fallback: FallbackConfig = FallbackConfig()
