"""Typed, validated algorithm parameters, in sections (frozen pydantic models, `extra="forbid"`).

The paper's defaults live here: δ = 1.5 m (graph edges), γ = 3 m (ROI radius), ε = 1e-3 (refinement stop).
Components receive plain values from these sections; runners (CLI, service) build them once.
Each section is owned by the stage it configures; add fields with bounds and a comment saying why.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


# --- site build -------------------------------------------------------------------------------------------------


class EnhanceConfig(_Section):
    """Map enhancement (paper §2.2)."""

    box_dilation_m: float = Field(0.05, ge=0, description="raw points within the CAD's oriented box grown by this are replaced")
    cad_sample_spacing_m: float = Field(0.01, gt=0, description="mean spacing of points sampled on CAD surfaces")
    color_transfer_k: int = Field(4, ge=1, description="removed raw points averaged per CAD point for its colour")
    raw_voxel_m: float = Field(0.01, ge=0, description="voxel down-sampling of the raw scan before enhancement (0 = off)")
    sample_edge_m: float = Field(0.1, ge=0, description="a scan mesh's triangles with an edge longer than this get "
                                 "points sampled on them (a decimated mesh leaves the map sparse; 0 = off)")
    sample_spacing_m: float = Field(0.015, gt=0, description="mean spacing of the points sampled on those triangles")


class GraphConfig(_Section):
    """Objects and semantic graph (paper §2.3.2)."""

    edge_max_m: float = Field(1.5, gt=0, description="δ: centroid pairs at most this far apart get an edge")
    cluster_tolerance_m: float = Field(0.05, gt=0, description="class-wise Euclidean clustering of uncovered labelled map points")
    min_cluster_points: int = Field(50, ge=1, description="smaller clusters are noise, not objects")
    stacked_merge_overlap: float = Field(
        0.5, ge=0, le=1, description="same-class clusters one above the other (seat and base of a swivel chair) "
        "merge when their horizontal boxes overlap by this fraction of the smaller; 1 = only full cover, 0 = off")
    remnant_margin_m: float = Field(
        0.15, ge=0, description="a cluster of a CAD's class lying within this of the CAD's box is a leftover of that "
        "object (labels bleed past the CAD), not an object of its own")


class PartitionConfig(_Section):
    """A building scanned in one piece, cut into regions: its storeys, their rooms, found from their floor plans, and
    the rooms too long for one region cut into tiles (`site/partition.py`)."""

    above_m: float = Field(8.0, ge=0, description="a map no wider than this along x and y stays one region (a room); "
                           "0 keeps every map one region")
    tile_m: float = Field(6.0, gt=0, description="a room longer than this along x or y (a corridor, a hall) is cut "
                          "into equal tiles of at most this a side")
    cell_m: float = Field(0.1, gt=0, description="the floor plan's cell")
    wall_from_m: float = Field(1.2, ge=0, description="points this high above the floor and up to wall_to_m are "
                               "walls on the floor plan (above most furniture, below door lintels)")
    wall_to_m: float = Field(1.9, gt=0, description="see wall_from_m")
    door_m: float = Field(1.0, gt=0, description="free floor narrower than this (a doorway) does not hold a room: "
                          "rooms are the free floor wider than this, grown back out to the walls")
    min_room_m2: float = Field(1.0, ge=0, description="a room's core (its floor wider than door_m) smaller than this "
                               "is taken in by its neighbours")
    min_storey_m2: float = Field(4.0, gt=0, description="surfaces facing up that cover this much of the plan, "
                                 "2 m or more above the floor below, are the floor of a storey above it")

    @model_validator(mode="after")
    def _band(self) -> "PartitionConfig":
        if self.wall_to_m <= self.wall_from_m:
            raise ValueError(f"wall_to_m ({self.wall_to_m}) must lie above wall_from_m ({self.wall_from_m})")
        return self


class SiteBuildConfig(_Section):
    enhance: EnhanceConfig = EnhanceConfig()
    graph: GraphConfig = GraphConfig()
    partition: PartitionConfig = PartitionConfig()


class AutoCadConfig(_Section):
    """Automatic CAD alignment (`site build --auto-cad`): find the furniture of the classes a CAD library covers and
    fit its models, upright (z up), by yaw, translation and anisotropic scale. Defaults measured on scene0470."""

    min_instance_points: int = Field(150, ge=10, description="smaller clustered instances get no CAD (too little "
                                     "to fit seven parameters to)")
    fit_points: int = Field(1500, ge=100, description="instance points and CAD surface samples used in the search "
                            "and the ICP (random subsets: the cost is linear in them)")
    yaw_sweep_deg: float = Field(15.0, gt=0, le=90, description="coarse yaw sweep, besides the 4 axes of the "
                                 "instance's minimum-area footprint rectangle")
    refine_hypotheses: int = Field(5, ge=1, description="best yaw hypotheses (≥ 20° apart) per model refined by "
                                   "ICP: the Chamfer score of a coarse hypothesis is a poor guide to its basin")
    icp_iterations: int = Field(12, ge=1, description="ICP rounds (correspondences, then a least-squares step)")
    icp_max_correspondence_m: float = Field(0.10, gt=0, description="first ICP round's pairing distance; it "
                                            "shrinks to a third of this by the last round")
    anisotropy_sigma: float = Field(0.15, gt=0, description="how far (log of the ratio) the fit may change a "
                                    "model's horizontal proportions before it costs like 1 cm of misfit per point: "
                                    "chairs of a kind differ by ~10 %, and free proportions let a wrong yaw fit")
    base_fraction: float = Field(0.2, ge=0, lt=0.9, description="the lowest share of an instance's height (legs, "
                                 "a swivel base, casters) is left out of the yaw and scale search and the ICP, on "
                                 "the scan and on the model: it is what differs most between models of a class, and "
                                 "a swivel chair's star base turns independently of its seat, so fitting it pulls "
                                 "the seat and back off their yaw and proportions; the bottom stays on the support")
    cover_footprint: bool = Field(True, description="after the fit, grow the CAD's horizontal scales until its box "
                                  "covers the footprint of the instance's points that the CAD explains")
    cover_explained_m: float = Field(0.06, gt=0, description="points within this of the fitted CAD are the ones its "
                                     "box grows to cover (robust 0.5–99.5 %); farther ones are label bleed onto a "
                                     "wall or the floor. Twice inlier_m: a library model is rarely the object itself")
    same_model_margin: float = Field(0.1, ge=0, description="objects of a class in one room are mostly of one kind: "
                                     "the model that fits the class's instances best overall is kept for an instance "
                                     "unless another fits it better by more than this share of its truncated Chamfer "
                                     "score (partial scans of one chair are weak evidence between similar models); "
                                     "0 picks each instance's best")
    score_truncation_m: float = Field(0.05, gt=0, description="distances are capped at this in the Chamfer "
                                      "score, so unseen CAD parts (a chair's hidden legs) cost a bounded amount")
    support_search_m: float = Field(0.3, ge=0, description="the surface an object stands on is sought among "
                                    "upward-facing unlabelled/structure points this far around its footprint")
    inlier_m: float = Field(0.03, gt=0, description="a point this close to the other side counts as covered")
    # Acceptance thresholds. A library model is rarely the scanned object itself: on scene0470 the 7 annotated
    # (human) alignments measure 0.6–3.7 cm median scan -> CAD, 44–81 % scan coverage, 2.0–4.8 cm median CAD -> scan
    # and 34–67 % CAD coverage; an automatic fit must be about as good as those to be kept.
    max_median_scan_to_cad_m: float = Field(0.04, gt=0, description="accept: median distance of the instance's "
                                            "points to the aligned CAD surface at most this")
    min_scan_coverage: float = Field(0.4, ge=0, le=1, description="accept: at least this share of the instance's "
                                     "points within inlier_m of the CAD (the CAD explains the scan)")
    max_median_cad_to_scan_m: float = Field(0.06, gt=0, description="accept: median distance of CAD samples to the "
                                            "instance's points at most this (looser: scans miss hidden parts)")
    min_cad_coverage: float = Field(0.25, ge=0, le=1, description="accept: at least this share of the CAD samples "
                                    "within inlier_m of the instance (the scan supports the CAD)")
    annotated_margin_m: float = Field(0.15, ge=0, description="with --scan2cad too, an instance whose box centre "
                                      "lies in an annotated CAD's box grown by this is that annotated object")
    workers: int = Field(2, ge=1, description="processes aligning instances in parallel (the machine's cores)")
    seed: int = Field(0, description="seed of the point subsets and CAD surface samples (builds are repeatable)")


# --- localization -----------------------------------------------------------------------------------------------


class FrameConfig(_Section):
    """Frame -> points (paper eq. 1–2)."""

    min_depth_m: float = Field(0.1, ge=0)
    max_depth_m: float = Field(6.0, gt=0)
    pixel_stride: int = Field(2, ge=1, description="use every n-th depth pixel: halves time at no loss (DESIGN §9)")
    stride_reference_pixels: int = Field(640 * 480, ge=1, description="a depth image of more pixels is sampled with "
                                         "the stride that takes as many of them as pixel_stride (and the tracking "
                                         "stride) takes of one this size (`points.stride_for`): the points, and what "
                                         "every later stage costs, stay bounded whatever the image's size")
    voxel_size_m: float = Field(0.03, gt=0, description="voxel down-sampling of the frame points for clustering and scoring")
    min_points: int = Field(100, ge=1, description="fewer valid depth points than this is no frame to register "
                            "(too few for a plane, a cluster and a GICP)")
    score_points: int = Field(300, ge=20, description="frame points used to score each hypothesis on the distance field")
    fit_points: int = Field(800, ge=20, description="frame points whose label and colour agreement with the map rank "
                            "the coarse-aligned hypotheses (enough for a 1 % resolution, cheap enough for 20 poses)")
    check_points: int = Field(2000, ge=20, description="frame points of the final fitness and inlier RMSE")
    # The sensor's depth noise along its rays, σ(z) = a + b·(z − z0)² (`camera.axial_noise_sigma_m`): what the
    # refinement assumes of a frame (`RefineConfig.noise_reference_m`). The defaults are the Kinect's (Nguyen et al.
    # 2012), as structured-light sensors (Kinect, Structure, RealSense) go; a time-of-flight sensor is quieter.
    axial_noise_a_m: float = Field(0.0012, ge=0, description="constant part of the sensor's depth noise σ, metres")
    axial_noise_b_per_m: float = Field(0.0019, ge=0, description="quadratic part of σ, metres per metre²")
    axial_noise_z0_m: float = Field(0.4, ge=0, description="depth at which σ is smallest, metres")


class ClusterConfig(_Section):
    """Class-wise Euclidean clustering of the frame (paper §2.3.1)."""

    tolerance_m: float = Field(0.07, gt=0, description="points of one class closer than this are one object (> 2 voxels)")
    min_points: int = Field(25, ge=1, description="smaller clusters (at the frame voxel size) are label noise")


class MatchConfig(_Section):
    """Coarse graph matching (paper §2.4). δ, the edge length of scan graphs, is the site's own (its build
    parameters, `Site.edge_max_m`): scan and map graphs must be built alike to be compared."""

    alpha: float = Field(0.5, ge=0, description="weight of node similarity S_V in Sim")
    beta: float = Field(0.5, ge=0, description="weight of edge similarity S_E in Sim")
    top_k: int = Field(5, ge=1, description="hypotheses reported in the result")
    yaw_step_deg: float = Field(10.0, gt=0, le=90, description="yaw sweep for single-object hypotheses (gravity known)")
    pair_tolerance_m: float = Field(0.4, gt=0, description="centroid distances of matched pairs may differ by this "
                                    "(partially seen objects have shifted centroids)")
    dense_below_objects: int = Field(2, ge=0, description="with at most this many scan objects, single-object "
                                     "hypotheses also try offset centroids")
    offset_step_m: float = Field(0.2, gt=0, description="grid step of those offsets")
    max_offset_m: float = Field(0.6, ge=0, description="largest offset (also capped at half the node's extent)")
    match_radius_m: float = Field(0.6, gt=0, description="a scan object within this of a map node of its class matches it")
    score_tau_m: float = Field(0.1, gt=0, description="distance-field inlier scale of the geometric check")
    screen_keep: int = Field(300, ge=1, description="hypotheses kept after the quick geometric screen")
    sim_weight: float = Field(0.25, ge=0, le=1, description="share of Sim in the coarse ranking (the rest is geometric)")
    candidates: int = Field(8, ge=1, description="distinct best hypotheses pulled in by a coarse GICP and re-ranked")
    semantic_weight: float = Field(0.5, ge=0, le=1, description="share of label agreement with the map in the "
                                   "ranking of coarse-aligned hypotheses")
    color_weight: float = Field(0.3, ge=0, le=1, description="share of colour agreement with the map in that ranking")
    ambiguity_margin: float = Field(0.03, ge=0, description="a distinct runner-up within this fitness of the best is ambiguous")
    confident_margin: float = Field(0.1, gt=0, description="a best that beats its distinct runner-up by this much "
                                    "score keeps its whole confidence; a tie halves it")
    refine_contenders: int = Field(3, ge=1, description="when ambiguous, this many best hypotheses are refined fully")
    max_see_through: float = Field(0.1, ge=0, le=1, description="a pose at which more than this share of the map "
                                   "in view lies in front of the frame's depth (space the sensor saw empty) is uncertain")
    min_ok_confidence: float = Field(0.5, ge=0, le=1, description="below this confidence an answer is uncertain, not ok")
    min_depth_agreement: float = Field(0.75, ge=0, le=1, description="a pose at which the frame's depth agrees with "
                                       "the map's surfaces in less than this share of the view the two share (render "
                                       "and compare, `ViewCheck.depth_agreement`) is uncertain")
    min_depth_agreement_passed_over: float = Field(0.9, ge=0, le=1, description="the same for an answer taken "
                                                   "after every better-ranked pose saw through the map: their scores "
                                                   "of 0 are no rival's, and it must agree with the map on its own")
    # 0.4 cm until the slide probe (slide_*) tested what it stands for: right label-free answers in the 10- and
    # 100-room buildings slid 0.41-0.56 cm and were held `uncertain` (10 rooms: 6 of the 8 unique views missed);
    # at 0.6 cm, and at 0.8, no set gained a wrong `ok` (scene0470 renders, the buildings, the mixed building,
    # Replica office0, 7-Scenes both ways).
    max_pose_std_m: float = Field(0.006, gt=0, description="a pose the geometry alone found (not the graph) whose "
                                  "covariance leaves it a standard deviation σ above this along some direction may "
                                  "slide (one wall, a floor and a wall): with a close rival it is uncertain, not "
                                  "ambiguous; else its confidence is scaled by this / σ and the slide probe "
                                  "(slide_*) decides whether it is ok. A tracked pose (`tracking.py`) above it is "
                                  "uncertain, the session following it")
    objects_pin_share: float = Field(0.1, ge=0, le=1, description="a graph answer whose matched objects hold less "
                                     "than this share of the frame's points is probed for sliding as a pose the "
                                     "geometry alone found is")
    slide_probe_m: float = Field(0.25, gt=0, description="a pose the geometry alone found is moved this far along the "
                                 "two directions the frame's surfaces constrain least (`Localizer._slides`)")
    slide_fitness_ratio: float = Field(0.99, gt=0, le=1, description="moved there, a frame that keeps this share of "
                                       "its fitness ...")
    slide_agreement_drop: float = Field(0.01, ge=0, le=1, description="... and loses no more than this of its depth "
                                        "agreement fits as well there: the pose slides, and is uncertain")
    # Chroma only (CIE a*, b*): lightness follows shading, exposure and highlights. Right `ok` answers kept at
    # least 0.62 (7-Scenes, colour a few pixels off the depth) and 0.72 (3DMatch); three confident wrong answers at
    # a robot's height, close views of the orange door placed in another, white corner, had -0.44 to -0.07.
    min_chroma_correlation: float = Field(0.25, ge=-1, le=1, description="a pose at which the chroma (a*, b*) of "
                                          "the frame's colours correlates with the map's less than this is "
                                          "uncertain: the frame shows another place of the same shape")
    # Right `ok` answers of the one-room sets without labels (renders by hand and at a robot's height, Replica,
    # 7-Scenes both ways) correlated 0.6 or more; the two wrong `ok` answers of the robot-height renders of seed 23,
    # views of bare walls placed 1.2 and 2.8 m off, 0.46 and 0.28, and the second look found both right. At 0.7
    # since the thirty-ninth session: a robot-height view of two chairs before a wall, placed before another wall
    # 1.4 m and 85 degrees off, correlated 0.58-0.63 in the draws of its noise that went wrong (its truth 0.95),
    # and the look found the truth in each. The look holds no answer back (one that wins again is claimed): it
    # costs time where colours follow the map's weakly, the real RedKitchen frames (right answers 0.62-0.86, a
    # quarter of them under 0.7) and a camera's colour faults (right answers down to 0.26).
    second_look_chroma: float = Field(0.7, ge=-1, le=1, description="in one room, an answer of the label-free "
                                      "search whose chroma correlates with the map's less than this (or than "
                                      "min_chroma_correlation) takes the search's next leaves that "
                                      "min_chroma_correlation does not rule out (`Localizer._second_look`); it is "
                                      "claimed unless min_chroma_correlation rules it out")
    chroma_min_std: float = Field(3.0, ge=0, description="the correlation is taken only where the map's chroma spreads "
                                  "at least this much (CIE Lab units, both axes together), and the frame's too or the "
                                  "frame's anywhere (a frame in colour that is grey where the map is not correlates "
                                  "near 0): a grey room's chroma is sensor noise, and a map or a camera without "
                                  "colour says nothing")
    refine_points: int = Field(1500, ge=100, description="frame points (after the refinement's voxel grid) one fine "
                               "refinement uses at most: its cost is bounded by points × iterations × contenders")
    distinct_translation_m: float = Field(0.3, gt=0)
    distinct_rotation_deg: float = Field(15.0, gt=0)


# The fine refinement's implementations (`localize.refine.refine`): named here, where the config checks them, so that
# the CLI lists them without importing the localizer.
RefineMethod = Literal["color_gicp", "small_gicp", "open3d_colored_icp"]
REFINE_METHODS: tuple[str, ...] = get_args(RefineMethod)


class RefineConfig(_Section):
    """Fine refinement (paper §2.5)."""

    roi_radius_m: float = Field(3.0, gt=0, description="γ: the map is cropped to this radius around the hypothesis")
    epsilon: float = Field(1e-3, gt=0, description="ε: stop when the update is below this")
    method: RefineMethod = "small_gicp"
    map_points: Literal["raw", "enhanced", "both"] = Field("raw", description="which map the frame is refined against")
    fine_voxel_m: float = Field(0.025, gt=0, description="map resolution for small_gicp")
    coarse_voxel_m: float = Field(0.08, gt=0, description="map and frame resolution of the coarse check of hypotheses")
    source_voxel_m: float = Field(0.04, gt=0, description="frame resolution for the fine refinement")
    noise_reference_m: float = Field(0.02, ge=0, description="a frame whose refinement points are noisier than "
                                     "this (σ, FrameConfig's model) in a tenth of them is refined a second time "
                                     "with a point up to 2^k times noisier kept one per voxel 2^k times "
                                     "source_voxel_m (`points.noise_octaves`), and the pose that fits the frame "
                                     "better is kept. Half the voxel: a quieter point's voxel holds a surface, a "
                                     "noisier one's a scatter. 0: never")
    max_correspondence_m: float = Field(0.1, gt=0)
    wide_voxel_m: float = Field(0.1, gt=0, description="voxel of the Gaussian map small_gicp's wide pass pairs frame "
                                "points with (VGICP; `refine.WIDE_PASS`)")
    max_iterations: int = Field(10, ge=1, description="per GICP pass; a start the coarse stage got right converges "
                                "in 2–6 (2 / 4 / 17 at p50 / p90 / p99 on 7-Scenes), and a wrong one spent its budget "
                                "oscillating: 30 -> 18 cut the 7-Scenes p99 by a quarter to a third, 18 -> 10 by a "
                                "quarter again, with the same answers")
    grid_max_iterations: int = Field(18, ge=1, description="the same for a building's GICP on its region maps "
                                     "(`grid_gicp.py`): its starts, pulled onto the field, took 7-9 iterations a pass "
                                     "on average at 100 rooms, and a twin's refinement cut at 10 lost a right "
                                     "label-free answer")
    color_scales_m: tuple[float, ...] = Field((0.08, 0.04, 0.02), min_length=1, description="colour GICP scales, coarse to fine")
    color_weight_m: float = Field(0.05, ge=0, description="λ: metres of joint-space distance per unit of Lab/100")
    inlier_m: float = Field(0.05, gt=0, description="a frame point this close to the map is an inlier")
    min_fitness: float = Field(0.5, ge=0, le=1, description="below this inlier fraction the result is low_overlap")


class LabelFreeConfig(_Section):
    """The label-free coarse stage (`localize/bbs.py`): with the frame's up direction known, a branch-and-bound
    search over (x, y, z, yaw) on max-pooled score grids of the map built once per site. It joins the graph's
    hypotheses whenever those are weak (FallbackConfig.min_graph_fitness), so labels add to it, not replace it."""

    enabled: bool = True
    voxel_m: float = Field(0.1, gt=0, description="finest grid cell: the translation step of the search's leaves "
                           "(the coarse GICP that follows pulls in a start this far off)")
    levels: int = Field(4, ge=1, le=7, description="pyramid levels above the finest: a root node covers 2^levels cells a side")
    tau_m: float = Field(0.15, gt=0, description="a cell whose centre is d from the map scores max(0, 1 − (d/τ)²)")
    reach_m: float = Field(4.0, gt=0, description="frame points farther than this from the camera are left out "
                           "of the search (the grid is padded by it: memory grows with it)")
    camera_margin_m: float = Field(1.0, ge=0, description="the camera may stand this far outside the box of the map "
                                   "(a map that holds only what lies ahead of the camera)")
    max_cells: int = Field(32_000_000, ge=10_000, description="cells of one pyramid level at most (one byte each, "
                           "levels + 1 bytes a cell in all); the cell grows by a quarter until the map fits. A leaf "
                           "coarser than τ loses poses (its sample lies up to a cell off the pose, and the score "
                           "falls within τ): 32 M cells keep a 100-room building at 12.5 cm, where 8 M made 19.5")
    points: int = Field(128, ge=20, description="frame points scored per node: the cost of a node")
    yaw_step_deg: float = Field(3.0, gt=0, le=30, description="yaw step of the search")
    max_nodes: int = Field(1200, ge=10, description="nodes kept per level, highest bounds first: bounds the cost "
                           "of any frame (levels × 8 × max_nodes × points lookups)")
    keep_ratio: float = Field(0.85, gt=0, le=1, description="leaves scoring at least this share of the best are "
                              "hypotheses (rivals are kept for the verification to judge)")
    candidates: int = Field(5, ge=1, description="distinct best leaves pulled in by the coarse GICP")
    exact_leaves: int = Field(3, ge=0, description="distinct leaves taken besides, the best of the search's leaves by "
                              "the frame's score on the site's exact distance field (MatchConfig.score_tau_m): on a "
                              "close view the search's bounds tie among many leaves, a small patch fitting anywhere "
                              "at its coarse cells, and the exact field tells them apart (in a one-room site they "
                              "join the second look's reserve)")
    reserve: int = Field(20, ge=0, description="in a one-room site, the next distinct leaves kept for a second look "
                         "when the answer's colours are not the map's (MatchConfig.min_chroma_correlation): those "
                         "at which the frame's colours follow the map's are pulled in and refined as well")


class FallbackConfig(_Section):
    """Geometric global registration when the graph has too little to say."""

    enabled: bool = True
    voxel_size_m: float = Field(0.05, gt=0, description="FPFH + RANSAC resolution")
    fpfh_max_points: int = Field(12000, ge=100, description="the last resort describes and matches the frame on "
                                 "voxel_size_m voxels, or on the coarser ones that leave at most this many: real frames "
                                 "have 2-11 k (RedKitchen, 3DMatch), a depth image of noise 60-180 k, which took 5-21 s "
                                 "(0.6 s so)")
    grid_step_m: float = Field(0.2, gt=0, description="position step of `fallback.floor_grid_search` (kept for "
                               "callers; the localizer's label-free stage is LabelFreeConfig's search)")
    yaw_step_deg: float = Field(10.0, gt=0, le=90, description="yaw step of `fallback.floor_grid_search`")
    min_graph_fitness: float = Field(0.9, ge=0, le=1, description="below this coarse fitness the graph's best is "
                                     "checked against the fallback too")
    skip_agreement: float = Field(0.95, ge=0, le=1.01, description="... unless its depth agrees with the map's "
                                  "surfaces in at least this share of the view (`ViewCheck.depth_agreement`); above "
                                  "1 the fallbacks always run below min_graph_fitness")
    max_up_disagreement_deg: float = Field(25.0, gt=0, le=180, description="an FPFH + RANSAC pose that tilts the "
                                           "frame's up direction further than this from the map's is refused")


class TrackConfig(_Section):
    """Tracking of a session's frames (a stream device, or HTTP with `session_id`): the next frame is refined from
    the pose its motion predicts instead of localized from nothing (`localize/tracking.py`). Defaults measured on
    7-Scenes RedKitchen at 30 fps against a map fused from other frames of the sequence."""

    enabled: bool = Field(True, description="off: every session frame is localized globally (mode 'global')")
    pixel_stride: int = Field(7, ge=1, description="every n-th depth pixel of a tracked frame: a start centimetres "
                              "off needs fewer points than a search. On 7-Scenes stride 7 tracks as well as 5 with half "
                              "the points (median error 3.40 against 3.46 cm on the same 121 frames), and 5 as well "
                              "as 2")
    coarse_correspondence_m: float = Field(0.2, gt=0, description="the coarse GICP from the prediction pairs points "
                                           "this far apart: how far the prediction may be off")
    coarse_iterations: int = Field(10, ge=1)
    fine_voxel_m: float = Field(0.065, gt=0, description="frame resolution of the fine (point-to-plane) ICP of a "
                                "tracked frame: on 7-Scenes 6.5 cm tracks as well as 5 (median error 3.43 against 3.37 "
                                "cm on the same 167 frames) at 1.7 ms less a frame")
    fine_correspondence_m: float = Field(0.1, gt=0)
    fine_iterations: int = Field(12, ge=1, description="a tracked start is centimetres off: a dozen rounds converge")
    check_points: int = Field(1000, ge=20, description="frame points of a tracked frame's fitness")
    min_fitness: float = Field(0.4, ge=0, le=1, description="a tracked pose is answered when at least this share "
                               "of the frame lies on the map (lower than RefineConfig.min_fitness since the motion "
                               "agrees too); `ok` when its confidence also reaches MatchConfig.min_ok_confidence, "
                               "as a search's, else `uncertain`")
    coast_fitness: float = Field(0.1, ge=0, le=1, description="below min_fitness but above this (the camera looks past "
                                 "the map's edge), a frame whose correction is small is answered low_overlap and the "
                                 "session follows it without a global search; below, tracking has failed")
    max_correction_m: float = Field(0.05, gt=0, description="accept only when the refinement moved the prediction "
                                    "by at most this (at 30 fps corrections are 0.2–2 cm): a larger pull is a slide "
                                    "onto other surfaces, or a kidnap")
    max_correction_deg: float = Field(3.0, gt=0, le=180, description="the same bound on rotation (0.1–1.5° seen)")
    max_speed_m_s: float = Field(1.0, gt=0, description="how fast the camera may move: a frame that comes dt after "
                                 "its state may be corrected by up to this × dt (at least max_correction_m, at most "
                                 "coarse_correspondence_m), e.g. the first frame after a relocalization, whose motion "
                                 "is not known yet, or one after dropped frames")
    max_turn_deg_s: float = Field(60.0, gt=0, description="the same bound on turning, degrees a second (at least "
                                  "max_correction_deg)")
    max_gap_s: float = Field(1.0, gt=0, description="a session frame this long after its last accepted one is "
                             "localized globally (with the prediction as a prior): constant velocity is stale by then")
    search_interval_s: float = Field(1.0, ge=0, description="after a global search that found no pose, the session's "
                                     "next one waits this long (frame time); frames in between are answered at "
                                     "once from the cheap tracking attempt. A search costs 10–50 tracked frames: "
                                     "searching every frame of a stream in unmapped space would drop most of them")
    max_hypotheses: int = Field(4, ge=1, le=16, description="distinct hypotheses a session keeps tracking after an "
                                "ambiguous answer (each costs one tracking refinement per frame)")
    hypothesis_margin: float = Field(0.1, ge=0, le=1, description="an ambiguous answer's hypotheses within this score "
                                     "of its best are tracked")
    clear_margin: float = Field(0.05, ge=0, le=1, description="a tracked hypothesis whose fitness falls this far "
                                "behind the best's is pruned; the session answers 'ok' once one is left")


class RegionConfig(_Section):
    """Regions of a building-scale site (`localize/regions.py`): the rooms a frame may be in."""

    max_cached: int = Field(8, ge=1, description="regions whose refinement maps a localizer keeps built (least "
                            "recently used dropped): a worker's memory is bounded by this, not by the building")
    max_verified: int = Field(48, ge=1, description="regions whose best graph hypotheses are pulled onto the map "
                              "(on the stored distance field) and compared along the frame's rays: the graph match "
                              "ranks regions, and tied rooms beyond this are reported unverified")
    tie_margin: float = Field(0.06, ge=0, le=1, description="regions whose best graph hypothesis ranks within this "
                              "of the best region's are all verified (repeated rooms tie): none is dropped unseen")
    screen_per_region: int = Field(1, ge=1, description="hypotheses of every region kept through the quick screen "
                                   "besides MatchConfig.screen_keep overall")
    per_region: int = Field(1, ge=1, description="distinct graph hypotheses of each tied region compared along the "
                            "frame's rays (a room's best by the graph is often a turned copy of the view's pose)")
    contender_margin: float = Field(0.1, ge=0, le=1, description="distinct candidates whose view agreement lies "
                                    "within this of the best's are refined too (MatchConfig.refine_contenders at most)")
    twin_agreement: float = Field(0.92, ge=0, le=1, description="a distinct candidate at which the map shows the "
                                  "same as at the answer along this share of the frame's rays is a twin: the answer "
                                  "is ambiguous, however the frame's noise ranks the two")
    # Raising it (the thirtieth session tried 0.75) also leaves a cut search's copies waiting more often
    # (`RefineStage._copies_wait`): the deeper look's own bar is deeper_view_agreement.
    min_view_agreement: float = Field(0.6, ge=0, le=1, description="below this view agreement the graph's best "
                                      "is weak in a building and the fallbacks join, and the answer of a label-free "
                                      "search cut at its node cap leaves its copies to the deeper search")
    # A label-free search cut at its node cap may pass the frame's pose by, and the pose it found instead fits the
    # frame's points as well as the truth would (a self-similar corner, a turned room): how well that pose shows the
    # frame along its rays is then what tells. Over eleven building sets without labels (6-30 rooms, 1640 renders;
    # every search cut), the `ok` answers showing the frame 0.6-0.7 were wrong 6 times in 33, those showing it 0.7
    # or more 3 times in 546 (below min_view_agreement, 0.6, the deeper search ran already). Searched deeper, three
    # of the six are right and two `uncertain` (`docs/buildings-history.md`, thirty-eighth session).
    deeper_view_agreement: float = Field(0.7, ge=0, le=1, description="in a building, below this view agreement "
                                         "the answer of a label-free search cut at its node cap has the building "
                                         "searched again, deeper")
    min_one_object_view_agreement: float = Field(0.8, ge=0, le=1, description="the same for a best pose that rests "
                                                 "on one matched object (or none): one object, a whiteboard seen in "
                                                 "part, pins a pose less than several do")
    # In a building a pose is ranked along the frame's rays against every room's, and each copy of its room is
    # looked at there: the depth gate only has to catch a pose whose surfaces lie elsewhere. The map's furniture
    # is the CAD models, a few centimetres off the real chairs and tables and filling in what the scan never saw,
    # and a view from 0.4-0.5 m up, under the tables, shows the right pose's depth agreeing on 0.59-0.71 of the
    # rays (10 rooms at robot height: three unique views held `uncertain` at confidence 0.87-0.94). On the
    # building sets, every answer held by the 0.75 of one room (MatchConfig) at 0.5 or more that was wrong had a
    # confidence under 0.5 and a rival within 0.01; one room's gate holds wrong answers at 0.83-0.95.
    min_depth_agreement: float = Field(0.55, ge=0, le=1, description="MatchConfig.min_depth_agreement in a "
                                       "building, where the depth agreement is measured along the frame's rays "
                                       "through the whole map (`FieldView.shared`)")
    search_max_nodes: int = Field(3000, ge=10, description="the label-free search's nodes kept per level in a "
                                  "building's search box of several regions, at least (LabelFreeConfig.max_nodes in "
                                  "one room, and in a box of one region): a building's search box holds many rooms, "
                                  "and at 1200 the search cut its way past the view's room")
    search_nodes_per_region: int = Field(80, ge=0, description="the label-free search's nodes kept per level in a "
                                         "building for each region its search box covers, when that is more than "
                                         "search_max_nodes: a building's coarse levels tie (`bbs.highest`), the more "
                                         "the larger it is (8000 a level at 100 rooms)")
    object_tiebreak_share: float = Field(0.05, gt=0, le=1, description="poses that look the same along the frame's "
                                         "rays are told apart by the frame's labelled objects when one explains this "
                                         "share of the frame's view (pixels) more than every other "
                                         "(`Localizer._told_by_objects`); and a copy of the answer's room that lacks "
                                         "an object holding this share is no twin of the view (`_shows_objects`)")
    # The copies of the answer's view are always looked at; those of each runner-up that ties with it only while the
    # frame's twin check has rendered fewer rays than this (rays times poses, every refine run of the frame
    # together: the second and the deeper look go on from what the first spent). On the 100-room benchmark a
    # frame's twin check renders 0.08-0.14 M at the median and 0.70 M at most; a flat plane of depth, which every
    # copy of every contender shows alike, rendered 3.3 M (1.1 s of the 1.9 s it still took once the copies were
    # merged in one call; 5.0 s before).
    twin_check_rays: int = Field(1_000_000, ge=0, description="rays (times poses) the twin check of a frame may "
                                 "render before it stops looking at the copies of tied runner-ups' views: the "
                                 "answer then has a rival (margin 0, not `ok`) unless the frame's objects or depth "
                                 "put such a runner-up first, whose copies are then looked at")
    halo_m: float = Field(3.0, ge=0, description="a region's refinement map also holds its neighbours' points this "
                          "far outside its box: γ (RefineConfig.roi_radius_m) covers the whole region of interest")


class LocalizeConfig(_Section):
    frame: FrameConfig = FrameConfig()
    cluster: ClusterConfig = ClusterConfig()
    match: MatchConfig = MatchConfig()
    label_free: LabelFreeConfig = LabelFreeConfig()
    refine: RefineConfig = RefineConfig()
    fallback: FallbackConfig = FallbackConfig()
    track: TrackConfig = TrackConfig()
    regions: RegionConfig = RegionConfig()


# --- rendering and fusion (query frames from a mesh; maps from recorded frames) ---------------------------------


class NoiseConfig(_Section):
    """Kinect-like depth noise for rendered frames (axial σ(z) = a + b·(z − z0)², Nguyen et al. 2012)."""

    axial_a_m: float = Field(0.0012, ge=0, description="constant part of the axial depth noise σ")
    axial_b_per_m: float = Field(0.0019, ge=0, description="quadratic part of σ, metres per metre²")
    axial_z0_m: float = Field(0.4, ge=0, description="depth at which σ is smallest")
    edge_jump_m: float = Field(0.08, gt=0, description="a 4-neighbour this much nearer or farther marks a depth edge")
    edge_dropout_p: float = Field(0.6, ge=0, le=1, description="probability of losing a pixel on a depth edge")
    grazing_start_deg: float = Field(70.0, ge=0, le=90, description="incidence angle where grazing dropout begins")
    grazing_full_deg: float = Field(82.0, ge=0, le=90, description="incidence angle beyond which no depth returns")
    random_dropout_p: float = Field(0.01, ge=0, le=1, description="uniform random loss of depth pixels")
    min_depth_m: float = Field(0.4, ge=0, description="the sensor sees nothing nearer")
    max_depth_m: float = Field(6.0, gt=0, description="the sensor sees nothing farther")
    color_sigma: float = Field(2.0, ge=0, description="Gaussian colour noise, 8-bit levels")


class RenderConfig(_Section):
    """Query-frame rendering: cameras and how a person walking the room holds one (z up)."""

    depth_width: int = Field(640, gt=0)
    depth_height: int = Field(480, gt=0)
    depth_fx: float = Field(577.87, gt=0, description="ScanNet's depth camera")
    depth_fy: float = Field(577.87, gt=0)
    depth_cx: float = Field(319.5)
    depth_cy: float = Field(239.5)
    color_width: int | None = Field(None, gt=0, description="None = the depth camera's size and intrinsics")
    color_height: int | None = Field(None, gt=0)
    baseline_m: float = Field(0.025, description="depth -> colour offset along x when the colour camera differs")
    height_min_m: float = Field(1.2, ge=0, description="camera height above the floor")
    height_max_m: float = Field(1.75, ge=0)
    pitch_min_deg: float = Field(15.0, ge=-90, le=90, description="downward pitch")
    pitch_max_deg: float = Field(45.0, ge=-90, le=90)
    roll_max_deg: float = Field(5.0, ge=0, le=90)
    min_clearance_m: float = Field(0.3, ge=0, description="reject camera positions nearer than this to any surface")
    min_valid_fraction: float = Field(0.5, ge=0, le=1, description="reject views with fewer valid depth pixels")
    min_visible_objects: int = Field(1, ge=0, description="keep views that see at least this many object instances")
    min_object_fraction: float = Field(0.005, ge=0, le=1, description="an object counts as seen above this image fraction")
    max_attempts_per_frame: int = Field(500, ge=1, description="give up when this many candidate poses fail in a row")
    color_format: Literal["png", "jpg"] = "png"


class FuseConfig(_Section):
    """TSDF fusion of recorded frames into a map (Open3D VoxelBlockGrid)."""

    voxel_size_m: float = Field(0.012, gt=0)
    sdf_trunc_voxels: float = Field(4.0, gt=0, description="truncation distance in voxels")
    depth_max_m: float = Field(4.0, gt=0, description="depth beyond this is not fused")
    block_resolution: int = Field(16, ge=4, le=32)
    block_count: int = Field(60000, ge=1000, description="initial hash-map capacity (grows on demand)")
    weight_threshold: float = Field(2.0, ge=0, description="surface points need this much integration weight")
    label_frame_stride: int = Field(5, ge=1, description="vote labels from every n-th labelled frame")
    label_depth_tolerance_m: float = Field(0.03, gt=0, description="a label vote needs the point within this of the depth")


# --- reading a LocalizeConfig from a file (`cadreg serve` and `cadreg bench --localize-config`) ---------------


def config_problems(exc: ValidationError) -> str:
    """pydantic's errors as one line: `<dotted field>: <why>; ...`."""
    return "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}" for e in exc.errors())


def load_localize_config(path: str | Path) -> LocalizeConfig:
    """The LocalizeConfig in a `.toml` or `.json` file (sections as tables / objects, e.g. `[match] top_k = 2`);
    anything missing keeps the code's default. Raises ConfigError naming the file and the field."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise ConfigError(f"bad localize config {path}: expected a .toml or .json file")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"bad localize config {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"bad localize config {path}: unreadable: {exc}") from None
    try:
        doc = tomllib.loads(text) if suffix == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        # one line: the start-up error is a single line on stderr
        why = " ".join(str(exc).split())
        raise ConfigError(f"bad localize config {path}: not valid {suffix[1:].upper()}: {why}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"bad localize config {path}: the top level must be a table of sections")
    try:
        return LocalizeConfig.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(f"bad localize config {path}: {config_problems(exc)}") from None
