"""The localizer: one RGB-D frame -> T_map_camera in a site's map, with no initial guess.

`localize` reads as its stages (DESIGN §1; the values between them are in `stages.py`):

    scan        frame -> points, class-wise clusters (the scan graph), up direction and floor
    hypotheses  coarse graph matching scored by Sim and a distance-field check (match.py)
    verify      a coarse GICP pulls each distinct hypothesis (and a client's prior) in, ranked by geometry, labels
                and colour; when the graph's best is weak (no labels, no objects, no match) the label-free
                search joins (branch-and-bound over x, y, z, yaw, `bbs.py`), FPFH + RANSAC only without an up
    refine      fine refinement inside the region of interest of the best, and of its close rivals; in a building,
                the copies of its view in the rooms that repeat it (`building_views.py`)
    result      status, confidence and diagnostics

Everything site-dependent is built once in `from_site` and reused for every frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import small_gicp

from ..config import LocalizeConfig
from ..errors import InvalidArgument, InvalidFrame
from ..frame import Frame
from ..geometry import make_Ts, rotation_between, transform_points
from ..result import Diagnostics, Hypothesis, LocalizationResult, Match, Refinement, Roi, ScanObject, Status
from ..pointset import PointSet
from ..site.bundle import Site
from ..site.regions import CAMERA_MARGIN_M, Region
from .cluster import cluster_objects
from .color_gicp import rgb_to_lab
from .bbs import GridPyramid, map_direction_histogram, polish, yaw_candidates
from .building_views import BuildingViews, Renders
from . import field_kernels, grid_gicp, match, point_tree
from . import twins as room_twins
from .fallback import FpfhRansac
from .field_view import FieldView, align_on_field
from .twins import SHAPE_POINTS, RoomTwins
from .gravity import estimate_floor, map_floor_height, map_up_axis, planar_normals
from .match import (Hypotheses, MapGraph, distinct_best, distinct_pairs, gravity_hypotheses, kabsch_hypotheses,
                    score_graph)
from .points import FramePoints, frame_to_points, voxel_downsample
from .refine import GICP_NEIGHBORS, REFINE_METHODS, RefineMap, RefineOutcome, crop_to_roi
from .regions import RegionIndex, RegionMaps, region_cloud
from .score import DistanceField, ViewCheck, score_poses
from .stages import (Candidate, Choice, Refined, Scan, StageTimer, answer_status, confidence, low_overlap_confidence,
                     pose_std_m)
from .tracking import Tracked, TrackState, track_frame

# The quick screen of every graph hypothesis uses a third of the scoring points (at least this many): enough to
# drop the hopeless ones, three times cheaper than the full check of those kept.
SCREEN_SHARE = 3
MIN_SCREEN_POINTS = 20
# A building's first look at its graph hypotheses keeps this many times what the screen keeps (`_hypotheses`),
# on a copy of the field with cells this many times as large (`DistanceField.coarsened`).
FIRST_LOOK_WIDER = 8
FIRST_LOOK_COARSENING = 4
# Cheapest first. FPFH + RANSAC runs only when the label-free search could not (no up direction): it costs
# ten times more and, knowing nothing of gravity, is no better where the search finds nothing.
FALLBACKS = ("bbs", "fpfh-ransac")
# A building's FPFH + RANSAC registers against one room's box grown by this (walls scanned a little outside it).
ROOM_MARGIN_M = 0.3
# A point budget's voxel grows by this factor until the points fit (`_voxel_budget`).
VOXEL_GROWTH = 1.15
# Distinct candidates refined beyond the contenders when every contender sees through the map: two, since a
# frame of a place the map lacks sees through it at every pose, and each costs a refinement.
EXTRA_CONTENDERS = 2
# A rival (any contender but the best) seeing through the map this many times MatchConfig.max_see_through at its
# coarse pose is not refined: of about 800 refinements of 7-Scenes frames, none that started above 1.5 times it
# ended at or below it (the largest start of one that did: 1.1 times), and such rivals were most of the cost of
# frames looking past the map's edge.
HOPELESS_SEE_THROUGH = 1.5
# Frame points of the coarse GICP of each hypothesis, at most. 600 (was 1000): the labelled renders' median fell by
# an eighth (verify is 8 coarse GICPs), with the same answers there and on 7-Scenes, and 3 more right poses in the
# 10-room building.
COARSE_POINTS = 600
# A hypothesis whose coarse GICP would hand over more than this share of its points far from the map gets a cloud
# of the others (`_coarse_align`): rebuilding one costs 0.5 ms, so hypotheses with a few far points keep the shared one.
COARSE_FAR_SHARE = 0.25
# A refinement whose whole-frame fitness fell by more than this from its start slid (see `_refine`).
SLIDE_TOLERANCE = 0.01
# The field alignment of a building's hypotheses (`field_view.align_on_field`): from a reach of half a metre (the
# field's truncation) down to 6 cm in 15 steps. On the 10-room benchmark's frames, poses 40 cm and 5° off came
# within 5 cm / 5° in 86 % of the cases (72 % from a 25 cm reach in 10 steps; 20 cm off: 98 %), at 1.4 ms each.
FIELD_ALIGN_ITERATIONS = 15
FIELD_ALIGN_REACH_M = (0.5, 0.06)
# A refinement settles into the basin it starts in: a candidate farther than this from every refined pose is
# another start (`_near_contender`), even when it is no distinct hypothesis (MatchConfig.distinct_translation_m).
NEAR_REACH_M = 0.1
NEAR_REACH_DEG = 5.0
# Flat-surface normals sampled for the yaw candidates of the label-free search when the up estimate gave none.
YAW_NORMAL_POINTS = 1000
# The label-free search's leaves are polished (`bbs.polish`) twice, the second round only for those its first left
# within RegionConfig.tie_margin and this of the best: the second round's half steps raised a leaf's score by at
# most 0.12 (the 100-room frames without labels: 245 leaves a frame, 52 within 0.16 after the first round), and
# only leaves that end within the tie margin are ranked by room. 100 rooms without labels: median -3 %, p90 -8 %,
# every answer the same. One room takes the same cut (its five leaves; every answer the same on its sets too).
POLISH_LATER_GAIN = 0.14
# An object's top is the 98th percentile of its points along up: the highest 2 % are mixed pixels and noise.
TOP_PERCENTILE = 98


def compile_loops() -> None:
    """Compile (or load from numba's cache) every compiled loop the localizer runs: `Localizer.warm` at a server's
    start, the Dockerfile at build time."""
    for module in (field_kernels, grid_gicp, match, point_tree, room_twins):
        module.warm()


@dataclass(eq=False)
class RefineRun:
    """What the refinements of one frame's contenders share (`Localizer._refine`).

    contenders : the candidates refined first, the best first. near : in one room, the contender `_near_contender`
    added (then every score is weighed by depth agreement), else None. source : the frame points the refinement
    draws on (`_refine_source`); roi_points : those within γ of the frame's centre, within the point budget;
    roi_frame_points : how many lay within γ before the budget. center_camera : the centre of the ROI, camera
    frame. renders : a building's refined poses' renders. whole : the whole frame within the budget, made when a
    refinement slid (`_unslid`)."""

    scan: Scan
    method: str
    diag: Diagnostics
    contenders: list[Candidate]
    near: Candidate | None
    source: FramePoints
    roi_points: FramePoints
    roi_frame_points: int
    center_camera: np.ndarray
    renders: Renders
    whole: FramePoints | None = None


class Localizer(BuildingViews):
    """Localize frames in one site. Build with `from_site`; `localize` is read-only and may be called repeatedly.

    up : (3,) unit vector opposite to gravity, map frame. floor_height_m : the floor's height along `up`, metres.
    graph : the site's semantic graph as arrays. field : distance field over the whole map (raw and enhanced).
    maps : the site's regions and, per region, the map the refinement and the agreement scores use
    (`RefineConfig.map_points`) and the free-space check (`regions.py`): a pose uses those of the region it looks
    into. node_region : (k,) int, the region (index into `maps.regions`) of each graph node. The refine stage's
    steps that only a building takes are its base class's (`building_views.BuildingViews`).
    """

    def __init__(self, site: Site, config: LocalizeConfig, *, up: np.ndarray, floor_height_m: float, graph: MapGraph,
                 field: DistanceField, maps: RegionMaps) -> None:
        self.site = site
        self.config = config
        self.up = up
        self.floor_height_m = floor_height_m
        self.graph = graph
        self.field = field
        self.maps = maps
        region_of = {n: k for k, r in enumerate(maps.regions) for n in r.nodes}
        self.node_region = np.array([region_of.get(i, -1) for i in graph.ids], dtype=np.int64)
        # Each region's floor along up, as the bundle states it (a building's rooms need not share one), else the
        # map's; and under each graph node, its region's.
        self.region_floor_m = {r.id: floor_height_m if r.floor_m is None else r.floor_m for r in maps.regions}
        self.node_floor_m = np.array([self.region_floor_m[maps.regions[k].id] if k >= 0 else floor_height_m
                                      for k in self.node_region], dtype=np.float64)
        self._fpfh: FpfhRansac | None = None
        self._whole: RefineMap | None = None
        self._pyramid: tuple[GridPyramid, np.ndarray | None] | None = None
        self.twins = (RoomTwins(graph, self.node_region, up, len(maps.regions), field=field,
                                bounds=np.array([r.bounds for r in maps.regions]),
                                sample=lambda k: _region_sample(maps.site, maps.regions[k], SHAPE_POINTS))
                      if len(maps) > 1 else None)
        # A building's first look at its graph hypotheses reads a coarse copy of the field (`_hypotheses`).
        self.first_look_field = field.coarsened(FIRST_LOOK_COARSENING) if len(maps) > 1 else None

    @classmethod
    def from_site(cls, site: Site, config: LocalizeConfig = LocalizeConfig()) -> "Localizer":
        """Build every per-site search structure (distance field, small_gicp map, KD-trees) once; in a building
        (several regions) the field is the one the bundle stores, and the per-region structures are built on use."""
        maps = RegionMaps(site, config)
        surfaces = _surface_sample(site, maps)
        surface_xyz = surfaces.points.astype(np.float64)
        surface_normals = surfaces.normals.astype(np.float64)
        # As the site states it (a fused map), else from the map's surfaces: +z for ScanNet and the demo.
        up = site.up if site.up is not None else map_up_axis(surface_normals)
        up = up / np.linalg.norm(up)
        if site.field_grid is not None:
            field = DistanceField.from_grid(site.field_grid)
        else:
            field = DistanceField(surface_xyz if len(maps) == 1 else site.cloud("both").points.astype(np.float64))
        return cls(
            site, config, up=up,
            floor_height_m=map_floor_height(surface_xyz, surface_normals, up),
            graph=MapGraph.from_site(site, up),
            field=field,
            maps=maps,
        )

    def maps_at(self, T_map_camera: np.ndarray, center_camera: np.ndarray) -> RegionIndex:
        """The search structures of the region that holds the pose's region of interest: the frame's centre
        (`center_camera`, colour-camera frame) placed by the pose (`regions.py`)."""
        return self.maps.at(T_map_camera[:3, :3] @ center_camera + T_map_camera[:3, 3])

    def region_of(self, T_map_camera: np.ndarray) -> str:
        """The id of the region the camera of a pose stands in (what a hypothesis names)."""
        return self.maps.region_at(T_map_camera[:3, 3]).id

    @property
    def refine_map(self) -> RefineMap:
        """The whole site's refinement map: the one region's of a one-room site; built on first use for a
        building (for the baselines of the bench, which search the whole map: the localizer itself uses
        `maps_at`)."""
        if len(self.maps) == 1:
            return self.maps.index(self.maps.regions[0]).refine_map
        if self._whole is None:
            rc = self.config.refine
            cloud = self.site.cloud(rc.map_points)
            self._whole = RefineMap(cloud.points.astype(np.float64), cloud.rgb01(), cloud.class_index,
                                    fine_voxel_m=rc.fine_voxel_m, coarse_voxel_m=rc.coarse_voxel_m,
                                    color_scales_m=rc.color_scales_m, color_weight_m=rc.color_weight_m)
        return self._whole

    @property
    def view_check(self) -> ViewCheck:
        """The free-space check of a one-room site (a building's are per region: `maps_at`)."""
        if len(self.maps) != 1:
            raise InvalidArgument("a site of several regions has a free-space check per region: use maps_at")
        return self.maps.index(self.maps.regions[0]).view_check

    def warm(self) -> "Localizer":
        """Build now what is otherwise built on first use (the map's FPFH features for the fallback, about a second
        a site; the compiled loops, `compile_loops`), so that a long-running server does not make its first requests
        pay for it."""
        if len(self.maps) == 1:
            self.refine_map.fine_target()
            self.refine_map.wide_voxels(self.config.refine.wide_voxel_m)
            self.refine_map.coarse_target()
            self.refine_map.fit_lab  # noqa: B018  (made on first read)
        # A building's FPFH features (the last resort, with no up direction) would cost seconds and a copy of
        # the whole map in every worker: built on first use there.
        if self.config.fallback.enabled and len(self.maps) == 1:
            self.fpfh()
        if self.config.label_free.enabled:
            self.pyramid()
        compile_loops()
        return self

    def pyramid(self) -> tuple[GridPyramid, np.ndarray | None]:
        """The label-free search's grid pyramid of this site and the map's histogram of wall directions (built on
        first use, or by `warm`: about a second and (levels + 1) bytes a cell, LabelFreeConfig.max_cells at most)."""
        if self._pyramid is None:
            lf = self.config.label_free
            surfaces = _surface_sample(self.site, self.maps)
            # A building's occupied cells come from its stored field: its points stay where they lie.
            occupied = surfaces.points if len(self.maps) == 1 else self.field.surface_points(lf.voxel_m / 2)
            pyr = GridPyramid(self.field, occupied, self.up, voxel_m=lf.voxel_m, levels=lf.levels, tau_m=lf.tau_m,
                              reach_m=lf.reach_m, margin_m=lf.camera_margin_m, max_cells=lf.max_cells)
            normals = surfaces.normals.astype(np.float64)
            self._pyramid = (pyr, map_direction_histogram(normals @ pyr.R_level_map.T))
        return self._pyramid

    def fpfh(self) -> FpfhRansac:
        """The FPFH + RANSAC registrar of this site (map features computed on first use)."""
        if self._fpfh is None:
            self._fpfh = FpfhRansac(self.refine_map.xyz, voxel_m=self.config.fallback.voxel_size_m)
        return self._fpfh

    # ------------------------------------------------------------------------------------------------------------
    def localize(self, frame: Frame, *, top_k: int | None = None, method: str | None = None,
                 progress: Callable[[int, int], None] | None = None) -> LocalizationResult:
        """Register one frame: scan -> hypotheses -> verify -> refine -> result.

        top_k : hypotheses to report (default MatchConfig.top_k). method : refinement method, one of
        `REFINE_METHODS` (default RefineConfig.method). progress(done, total) : called after each stage.
        Raises InvalidFrame for a frame that cannot be registered, InvalidArgument for an unknown method.
        """
        method, top_k = self._check_request(frame, method, top_k)
        diag = Diagnostics(site_id=self.site.site_id, bundle_version=self.site.version)
        timer = StageTimer(diag.stage_ms, progress)
        scan = self._scan(frame, diag, timer)
        with timer("match"):
            hyp = self._hypotheses(scan)
        candidates = self._verify(scan, hyp, frame.T_map_camera_prior, diag, timer)
        if not candidates:
            return self._no_pose(scan, diag, frame.frame_id)
        with timer("refine"):
            choice = self._refine(scan, candidates, method, diag)
        return self._result(scan, candidates, choice, top_k, diag, frame.frame_id)

    def track(self, frame: Frame, state: TrackState | None, *, t_s: float, top_k: int | None = None,
              may_search: bool = True) -> Tracked:
        """One frame of a session: refined from the motion prediction of `state` when it is live (no clustering,
        no graph match), else localized globally with the prediction as a prior (`tracking.py`). Returns the result
        (`diagnostics.mode` = tracked | relocalized | global) and the session's next state. t_s : this frame's
        time, seconds, on the clock of `state.t_s`. may_search : False while another frame of the session is
        being searched (a runner with several frames of a session in flight): a frame that does not track is
        then answered `no_match` at once instead of starting a second search."""
        return track_frame(self, frame, state, t_s=t_s, top_k=top_k, may_search=may_search)

    # --- stages -------------------------------------------------------------------------------------------------
    def _check_request(self, frame: Frame, method: str | None, top_k: int | None) -> tuple[str, int]:
        if not isinstance(frame, Frame):
            raise InvalidFrame(f"expected a Frame, got {type(frame).__name__}")
        frame.validate()
        if frame.search_region is not None:
            frame.search_region.resolve(self.maps.regions)  # unknown region ids: InvalidFrame naming them
        method = method or self.config.refine.method
        if method not in REFINE_METHODS:
            raise InvalidArgument(f"unknown refinement method {method!r}; choose one of {REFINE_METHODS}")
        return method, self.config.match.top_k if top_k is None else int(top_k)

    def _scan(self, frame: Frame, diag: Diagnostics, timer: StageTimer) -> Scan:
        """Frame -> Scan: points (eq. 1–2), class-wise clusters (§2.3.1), up direction; and the fixed samples the
        later stages score with (seeded: the same frame gives the same answer)."""
        fc = self.config.frame
        with timer("points"):
            points = frame_to_points(frame, pixel_stride=fc.pixel_stride, min_depth_m=fc.min_depth_m,
                                     max_depth_m=fc.max_depth_m)
            if len(points) < fc.min_points:
                raise InvalidFrame(f"only {len(points)} valid depth points in range {fc.min_depth_m}–{fc.max_depth_m} m")
            down = voxel_downsample(points, fc.voxel_size_m)
            diag.frame_points = len(points)
        with timer("cluster"):
            class_index = np.full(len(down), -1, dtype=np.int64)
            labelled = down.labels >= 0
            if labelled.any():
                class_index[labelled] = self.site.classes_for_labels(frame.label_set, down.labels[labelled])
            cc = self.config.cluster
            clusters = cluster_objects(down.xyz, class_index, tolerance_m=cc.tolerance_m, min_points=cc.min_points)
            diag.scan_objects = [ScanObject(self.site.classes[c.cls], c.centroid.tolist(), len(c.index)) for c in clusters]
        with timer("gravity"):
            floor = estimate_floor(down.xyz, down.labels, frame.label_set, gravity_camera=frame.gravity_camera)
            if floor is not None:
                diag.notes.append(f"up from {floor.source}"
                                  + (f", camera {floor.height_m:.2f} m above floor" if floor.height_m else ""))
        rng = np.random.default_rng(0)
        score = rng.choice(len(down), min(fc.score_points, len(down)), replace=False)
        fit = rng.choice(len(down), min(fc.fit_points, len(down)), replace=False)
        check = rng.choice(len(points), min(fc.check_points, len(points)), replace=False)
        return Scan(points, down, class_index, clusters, floor, score_xyz=down.xyz[score], fit_xyz=down.xyz[fit],
                    fit_lab=rgb_to_lab(down.rgb[fit]), fit_cls=class_index[fit] if labelled.any() else None,
                    check_xyz=points.xyz[check],
                    zbuf=ViewCheck.zbuffer(down.xyz, frame.depth_intrinsics), K=frame.depth_intrinsics,
                    center_camera=points.xyz.mean(axis=0), search=frame.search_region,
                    view=FieldView(frame) if len(self.maps) > 1 else None)

    def _hypotheses(self, scan: Scan) -> Hypotheses:
        """Scan graph x map graph -> the distinct best pose hypotheses (at most MatchConfig.candidates): a quick
        geometric screen of all, then Sim (eq. 6–8) and the full distance-field check of those kept."""
        hyp = self._within_search(self._graph_hypotheses(scan), scan)
        if not len(hyp):
            return hyp
        mc = self.config.match
        centroids = np.array([c.centroid for c in scan.clusters])
        classes = np.array([c.cls for c in scan.clusters])
        screen_xyz = scan.score_xyz[: max(MIN_SCREEN_POINTS, len(scan.score_xyz) // SCREEN_SHARE)]
        if len(self.maps) > 1:
            # A building's graph gives 30-150 k hypotheses (every node of a class, every yaw), and the screen's
            # gathers from its field took 50-430 ms a frame at 100 rooms: a first look with a quarter of the
            # points keeps FIRST_LOOK_WIDER times as many as the screen will for the full one. It reads the
            # coarse field (a lower bound of the distance): a 100-room frame's first look 45 -> 15 ms.
            first = score_poses(self.first_look_field, screen_xyz[: max(MIN_SCREEN_POINTS, len(screen_xyz) // 4)],
                                hyp.R, hyp.t, tau_m=mc.score_tau_m)
            hyp = hyp.take(self._screened(hyp, first, wider=FIRST_LOOK_WIDER))
        screen = score_poses(self.field, screen_xyz, hyp.R, hyp.t, tau_m=mc.score_tau_m)
        hyp = hyp.take(self._screened(hyp, screen))
        score_graph(hyp, centroids, classes, self.graph, match_radius_m=mc.match_radius_m,
                    edge_max_m=self.site.edge_max_m, alpha=mc.alpha, beta=mc.beta)
        hyp.geometric = score_poses(self.field, scan.score_xyz, hyp.R, hyp.t, tau_m=mc.score_tau_m)
        rank = hyp.geometric * (1.0 - mc.sim_weight + mc.sim_weight * hyp.sim)
        if len(self.maps) == 1:
            keep = distinct_best(hyp.R, hyp.t, np.argsort(-rank), count=mc.candidates,
                                 min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg)
            return hyp.take(np.array(keep, dtype=np.int64))
        keep, unverified = self._region_candidates(hyp, rank, self._seed_regions(hyp), count=mc.candidates)
        scan.unverified = [self._unverified_hypothesis(hyp, i, "graph:unverified") for i in unverified]
        return hyp.take(np.array(keep, dtype=np.int64))

    def _within_search(self, hyp: Hypotheses, scan: Scan) -> Hypotheses:
        """The hypotheses whose camera lies in the client's search region (all of them without one)."""
        if scan.search is None or not len(hyp):
            return hyp
        return hyp.take(np.flatnonzero(scan.search.allows(hyp.t, self.maps.regions)))

    def _seed_regions(self, hyp: Hypotheses) -> np.ndarray:
        """(h,) int: the region of the map node each hypothesis was seeded by (-1 for none): what groups the
        graph's hypotheses by room without a look-up per hypothesis."""
        node = hyp.seed[:, 1]
        return np.where(node >= 0, self.node_region[np.maximum(node, 0)], -1)

    def _screened(self, hyp: Hypotheses, screen: np.ndarray, *, wider: int = 1) -> np.ndarray:
        """Indices of the hypotheses kept after the quick screen: the MatchConfig.screen_keep best and, in a
        building, also the RegionConfig.screen_per_region best of every region, so that a room the screen's few
        points rank a little lower (repeated rooms tie) still has its hypotheses scored; `wider` times as many of
        each for a first look."""
        order = np.argsort(-screen)
        keep = order[: wider * self.config.match.screen_keep]
        if len(self.maps) == 1:
            return keep
        region = self._seed_regions(hyp)[order]
        # positions in `order`, grouped by region, best first: a stable sort of 16-bit keys is a radix sort (a
        # 100-room frame's 100-300 k hypotheses grouped in 1 ms, not 10 as 64-bit keys took)
        key = region + 1  # -1 (no region) first
        by_region = np.argsort(key.astype(np.int16) if len(self.maps) < np.iinfo(np.int16).max else key, kind="stable")
        grouped = region[by_region]
        first_of_group = np.ones(len(grouped), dtype=bool)
        first_of_group[1:] = grouped[1:] != grouped[:-1]
        position = np.arange(len(grouped))
        in_region_rank = position - np.maximum.accumulate(np.where(first_of_group, position, 0))
        per_region = order[by_region[in_region_rank < wider * self.config.regions.screen_per_region]]
        return np.union1d(keep, per_region)

    def _region_candidates(self, hyp: Hypotheses, rank: np.ndarray, region: np.ndarray, *,
                           count: int) -> tuple[list[int], list[int]]:
        """Hypotheses ranked by region (DESIGN §1: the coarse stage ranks regions): every region whose best
        hypothesis ranks within RegionConfig.tie_margin of the best region's is verified (up to
        RegionConfig.max_verified; beyond, its best hypothesis is returned unverified: the answer cannot be ok while
        it stands), and the remaining of `count` places go to the distinct best hypotheses of the verified regions.
        region : (h,) region index of each hypothesis. Returns (indices to verify, indices of tied regions' best
        hypotheses left unverified)."""
        mc, rg = self.config.match, self.config.regions
        order = np.argsort(-rank)
        _, first = np.unique(region[order], return_index=True)
        region_best = order[np.sort(first)]  # the best hypothesis of each region, best region first
        tied = region_best[rank[region_best] >= rank[order[0]] - rg.tie_margin]
        # Each tied room's best few distinct hypotheses: the graph's best in a room is often a turned or shifted
        # copy of the view's pose (objects matched to their twins across the room), the right one a little lower.
        keep = []
        for r in region[tied[: rg.max_verified]]:
            keep += distinct_best(hyp.R, hyp.t, order[region[order] == r], count=rg.per_region,
                                  min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg)
        verified = region[region_best[: max(rg.max_verified, 1)]]
        for i in distinct_best(hyp.R, hyp.t, order[np.isin(region[order], verified)], count=count,
                               min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg):
            if len(keep) >= max(count, len(tied[: rg.max_verified])):
                break
            if i not in keep and all(self._distinct(hyp.T(i), hyp.T(k)) for k in keep):
                keep.append(i)
        return keep, [int(i) for i in tied[rg.max_verified:]]

    def _unverified_hypothesis(self, hyp: Hypotheses, i: int, source: str) -> Hypothesis:
        """A hypothesis reported as it is (no coarse GICP): a tied room there was no budget to verify."""
        T = hyp.T(i)
        term = lambda values: float(values[i]) if len(values) == len(hyp) else 0.0  # noqa: E731 (fallbacks: no Sim)
        matches = ([(int(k), self.graph.ids[a]) for k, a in enumerate(hyp.assignment[i]) if a >= 0]
                   if len(hyp.assignment) == len(hyp) else [])
        return Hypothesis(T, term(hyp.sim), term(hyp.s_v), term(hyp.s_e), term(hyp.geometric), matches=matches,
                          source=source, region=self.region_of(T))

    def _graph_hypotheses(self, scan: Scan) -> Hypotheses:
        """With up known: pairs fix yaw and translation, single objects sweep yaw; without: triples by Kabsch."""
        clusters, floor = scan.clusters, scan.floor
        if not clusters or len(self.graph.ids) == 0:
            return Hypotheses.empty()
        centroids = np.array([c.centroid for c in clusters])
        classes = np.array([c.cls for c in clusters])
        mc = self.config.match
        if floor is not None:
            R_level = rotation_between(floor.up_camera, self.up)
            # The camera's height along up over each node's own floor (a building's rooms need not share one).
            camera_up_m = None if floor.height_m is None else self.node_floor_m + floor.height_m
            # Few objects: little to go on, so search single-object offsets densely as well.
            offset = mc.offset_step_m if len(clusters) <= mc.dense_below_objects else 0.0
            up_camera = R_level.T @ self.up
            tops = np.array([np.percentile(scan.down.xyz[c.index] @ up_camera, TOP_PERCENTILE) for c in clusters])
            return gravity_hypotheses(centroids, classes, self.graph, R_level=R_level, up=self.up,
                                      camera_height_m=camera_up_m, yaw_step_deg=mc.yaw_step_deg,
                                      pair_tolerance_m=mc.pair_tolerance_m, offset_step_m=offset,
                                      max_offset_m=mc.max_offset_m, scan_top=tops)
        if len(clusters) >= 3:
            return kabsch_hypotheses(centroids, classes, self.graph, pair_tolerance_m=mc.pair_tolerance_m)
        return Hypotheses.empty()

    def _verify(self, scan: Scan, hyp: Hypotheses, prior: np.ndarray | None, diag: Diagnostics,
                timer: StageTimer) -> list[Candidate]:
        """Hypotheses (+ the client's prior) -> candidates after a coarse GICP, best first; the fallbacks join when
        the graph's best is weak (FallbackConfig.min_graph_fitness)."""
        fb = self.config.fallback
        with timer("verify"):
            # At most COARSE_POINTS frame points (a coarser grid for a frame that spans a large room): each
            # candidate's coarse GICP costs a KD-tree query of each per iteration.
            coarse = _voxel_budget(scan.down, self.config.refine.coarse_voxel_m, COARSE_POINTS)
            source = small_gicp.preprocess_points(coarse.xyz, self.config.refine.coarse_voxel_m,
                                                  num_neighbors=GICP_NEIGHBORS)[0]
            candidates = self._align(hyp, source, scan)
            if prior is not None:
                # A client's pose prior is one more hypothesis, checked like the others (never trusted blindly).
                candidates += self._align(_single(prior), source, scan, origin="prior")
        best = max((c.score for c in candidates), default=0.0)
        # Below this the graph's best is weak: its coarse fitness, or in a building its view agreement, held higher
        # when the best rests on one object (a 4-room building's view of a wall and part of a whiteboard was
        # answered `ok` 1.2 m along the wall, view agreement 0.71, the whiteboard matched; the label-free search
        # found the view's pose at 0.77).
        enough = fb.min_graph_fitness if scan.view is None else self._view_bar(candidates)
        if fb.enabled and best < enough and not self._best_agrees_along_rays(candidates, scan, diag):
            with timer("fallback"):
                rooms = self._candidate_regions(candidates)
                for name in FALLBACKS:
                    if name == "fpfh-ransac" and scan.floor is not None and self.config.label_free.enabled:
                        break
                    found = self._fallback(name, scan, diag.notes, rooms)
                    if found is not None:
                        found = self._within_search(found, scan)
                        # A pose the graph has already found stays the graph's (it carries the matches).
                        candidates += [c for c in self._align(found, source, scan, origin=f"fallback:{name}")
                                       if all(self._distinct(c.T_map_camera, g.T_map_camera) for g in candidates)]
                        best = max([best] + [c.score for c in candidates])
                        if best >= enough:
                            break
        # Stable: among equal scores the graph's order (its ranking) stands.
        candidates = sorted(candidates, key=lambda c: -c.score)
        if scan.view is not None:
            # Hypotheses of one room pulled onto the field often meet at one pose: each is listed once.
            poses = np.array([c.T_map_camera for c in candidates]).reshape(-1, 4, 4)
            earlier_alike = np.tril(~self._distinct_pairs(poses, poses), k=-1)  # [k, j]: j < k at k's pose
            candidates = [c for c, alike in zip(candidates, earlier_alike) if not alike.any()]
        return candidates

    def _view_bar(self, candidates: list[Candidate]) -> float:
        """The view agreement a building's best candidate needs for the fallbacks not to join
        (RegionConfig.min_view_agreement; min_one_object_view_agreement when it rests on at most one object)."""
        rg = self.config.regions
        best = max(candidates, key=lambda c: c.score, default=None)
        if best is None or int(np.sum(best.assignment >= 0)) > 1:
            return rg.min_view_agreement
        return max(rg.min_view_agreement, rg.min_one_object_view_agreement)

    def _best_agrees_along_rays(self, candidates: list[Candidate], scan: Scan, diag: Diagnostics) -> bool:
        """The best candidate is the graph's, and its coarse pose, weak by its score, renders as the frame measured
        it (depth agreement of at least FallbackConfig.skip_agreement): then the fallbacks are not run. Its score
        is what the fitness makes it, and furniture the map's CAD models stand in for is not the real thing (the
        demo's frame 6 puts a fifth of its points more than 5 cm from the map at a pose 1.1 cm off, score 0.79,
        and its depth agrees with the map in 96 % of the view: the label-free search then spent 95 ms to find
        nothing better)."""
        skip = self.config.fallback.skip_agreement
        if not candidates or scan.zbuf is None or skip > 1.0 or scan.view is not None:
            return False  # (a building's candidates are scored by their depth along the frame's rays already)
        best = max(candidates, key=lambda c: c.score)
        if best.hypothesis.source != "graph":
            return False  # a client's prior (a tracked prediction) is checked, never the reason to search less
        T = best.T_map_camera
        # A pose from which the map is out of sight shows no agreement at all (unseen=0).
        agreement = self.maps_at(T, scan.center_camera).view_check.depth_agreement(T, scan.zbuf, scan.K, unseen=0.0)
        if agreement < skip:
            return False
        diag.notes.append(f"fallbacks not run: the best coarse pose (score {best.score:.2f}) agrees with the map's "
                          f"depth in {100 * agreement:.0f} % of the view")
        return True

    def _refine(self, scan: Scan, candidates: list[Candidate], method: str, diag: Diagnostics) -> Choice:
        """Candidates -> Choice: fine refinement of the best inside the region of interest, and of its distinct
        rivals within the ambiguity margin (up to MatchConfig.refine_contenders), re-ranked after refinement."""
        run = self._refine_run(scan, candidates, method, diag)
        refine = partial(self._refine_contender, run)
        refined = [refine(c) for c in run.contenders]
        taken_next = self._refine_past_see_through(run, refined, candidates, refine)
        if scan.view is not None:
            has_rival, margin, rivals = self._rank_building(run, refined, candidates, refine)
        else:
            rivals = None
            has_rival, margin = self._rank_room(refined, candidates, diag)
        if scan.unverified:
            diag.notes.append(f"{len(scan.unverified)} more regions tied with the best and were not verified")
            has_rival, margin = True, 0.0
        return self._choice(run, refined, taken_next, has_rival, margin, rivals)

    def _refine_run(self, scan: Scan, candidates: list[Candidate], method: str, diag: Diagnostics) -> RefineRun:
        """What the contenders' refinements share: the contenders (in one room the best, its distinct rivals within
        the ambiguity margin and the near contender; in a building `_view_contenders`) and the frame points of the
        region of interest."""
        mc, rc = self.config.match, self.config.refine
        best = candidates[0]
        if scan.view is None:
            contenders = [best] + [c for c in candidates[1:mc.refine_contenders] if best.score - c.score < mc.ambiguity_margin
                                   and self._distinct(c.T_map_camera, best.T_map_camera)]
            near = self._near_contender(candidates, contenders)
            if near is not None:
                contenders.append(near)
        else:
            near = None
            contenders = self._view_contenders(candidates, scan.center_camera)
        # Region of interest (paper §2.5, radius γ about the frame's centre under the hypothesis). The map's search
        # structures are built once per site rather than cropped per frame; leaving out the frame points farther
        # than γ from their centroid has the same effect, since correspondences are sought only a few centimetres
        # from each frame point.
        source = self._refine_source(scan, method)
        roi_points, center_camera = crop_to_roi(source, rc.roi_radius_m, scan.center_camera)
        # The cost of a refinement is bounded by its inputs: at most MatchConfig.refine_points frame points
        # (`_budget`), for at most refine_contenders hypotheses, each at most twice (the slide check in
        # `_refine_contender`).
        return RefineRun(scan, method, diag, contenders, near, source, self._budget(roi_points, method), len(roi_points),
                         center_camera, Renders())

    def _refine_contender(self, run: RefineRun, c: Candidate) -> Refined:
        """One contender refined and scored: in a building by its view agreement along the frame's rays, in one
        room by its agreement score, both lowered by how far the frame sees through the map there."""
        scan, mc = run.scan, self.config.match
        maps = self.maps_at(c.T_map_camera, run.center_camera)
        if c is not run.contenders[0] and scan.zbuf is not None:
            see = maps.view_check.see_through(c.T_map_camera, scan.zbuf, scan.K)
            if see > HOPELESS_SEE_THROUGH * mc.max_see_through:
                # A rival the frame sees through this far at its coarse pose never refined into a credible
                # one: it keeps that pose and a score of 0, as its refinement would have earned.
                return Refined(0.0, RefineOutcome(c.T_map_camera, None, 0, False, run.method), c, see)
        out = self._refine_one(maps.refine_map, run.roi_points, c.T_map_camera, run.method)
        if run.roi_frame_points < len(run.source):
            out = self._unslid(run, maps.refine_map, c, out)
        see = 0.0 if scan.zbuf is None else self.maps_at(out.T_map_camera, run.center_camera).view_check.see_through(
            out.T_map_camera, scan.zbuf, scan.K)
        if scan.view is not None:
            # Along the frame's rays the map in front of the measured depth already counts against the pose.
            return Refined(float(scan.view.agreement(self._render_of(scan, run.renders, out))[0]), out, c, see)
        # A pose at which the frame sees through the map ranks below one at which it does not, whatever its
        # fit: the same factor as in the confidence.
        score = self._agreement_score(out.T_map_camera, scan) * max(0.0, 1.0 - see / mc.max_see_through)
        if run.near is not None and scan.zbuf is not None:
            # Two basins of one hypothesis are told apart as the sensor sees them: the labels that ranked them
            # are what put them side by side (`_near_contender`).
            score *= maps.view_check.depth_agreement(out.T_map_camera, scan.zbuf, scan.K)
        return Refined(score, out, c, see)

    def _unslid(self, run: RefineRun, refine_map: RefineMap, c: Candidate, out: RefineOutcome) -> RefineOutcome:
        """The ROI leaves out the frame's far points; when those were what held the pose along some direction (a
        corner whose far wall lies beyond γ), the refinement slides and the whole frame fits worse than at its
        start. Then the whole frame (within the same point budget) refines it, and the better fit is kept."""
        rc = self.config.refine
        fit = lambda T: refine_map.fitness(transform_points(T, run.scan.check_xyz), inlier_m=rc.inlier_m)[0]  # noqa: E731
        if fit(out.T_map_camera) >= fit(c.T_map_camera) - SLIDE_TOLERANCE:
            return out
        if run.whole is None:
            run.whole = self._budget(run.source, run.method)
        again = self._refine_one(refine_map, run.whole, c.T_map_camera, run.method)
        if fit(again.T_map_camera) > fit(out.T_map_camera):
            run.diag.notes.append("the ROI refinement slid: refined with the whole frame")
            return again
        return out

    def _refine_past_see_through(self, run: RefineRun, refined: list[Refined], candidates: list[Candidate],
                                 refine: Callable[[Candidate], Refined]) -> Candidate | None:
        """When every contender puts the map in front of what the frame measured, the next distinct candidates (at
        most EXTRA_CONTENDERS more) are refined into `refined` until one does not. Returns the candidate so taken,
        else None."""
        if not all(r.see_through > self.config.match.max_see_through for r in refined):
            return None
        tried = [r.T_map_camera for r in refined]
        limit = len(refined) + EXTRA_CONTENDERS
        for c in candidates[1:]:
            if len(refined) >= limit:
                break
            if any(c is k for k in run.contenders) or not all(self._distinct(c.T_map_camera, T) for T in tried):
                continue
            refined.append(refine(c))
            tried.append(refined[-1].T_map_camera)
            if refined[-1].see_through <= self.config.match.max_see_through:
                run.diag.notes.append(f"the best {len(refined) - 1} poses saw through the map: took the next")
                return c
        return None

    def _rank_building(self, run: RefineRun, refined: list[Refined], candidates: list[Candidate],
                       refine: Callable[[Candidate], Refined]) -> tuple[bool, float, list[Candidate]]:
        """In a building: the refined contenders ranked by view agreement, the copies of the best's view looked at
        (and promoted when they show the frame better), the rivals that look the same along the frame's rays found
        and, when there are some, ordered by the frame's objects and fit (`building_views.py`). Returns (has a
        distinct rival, margin, rivals)."""
        scan, diag, renders, center_camera = run.scan, run.diag, run.renders, run.center_camera
        mc = self.config.match
        refined.sort(key=lambda r: -r.score)
        self._report_refined(refined, candidates)
        twins = self._twin_views(scan, refined[0].T_map_camera, center_camera, candidates, renders, len(refined),
                                 refined[0].score)
        for r in refined[1:]:
            # A contender the answer cannot be told from: the copies of its view are looked at too. The truth's
            # room may be a copy of the runner-up's room-relative view, not of the answer's (a room lacking
            # a chair the frame sees shows the right view a little worse than another room a wrong one).
            if refined[0].score - r.score >= mc.ambiguity_margin or not self._distinct(r.T_map_camera,
                                                                                     refined[0].T_map_camera):
                continue
            more = self._twin_views(scan, r.T_map_camera, center_camera, candidates, renders, len(refined),
                                    refined[0].score)
            twins += [t for t in more if all(self._distinct(t.T_map_camera, u.T_map_camera) for u in twins)]
        twins = self._promote_twins(scan, refined, twins, refine, candidates, renders, center_camera)
        candidates.extend(t.candidate for t in twins)
        has_rival, margin, rivals = self._view_rivals(refined + twins, renders, candidates, scan)
        diag.notes.append(f"refined {len(refined)} of the best poses, view agreement "
                          + ", ".join(f"{r.score:.3f}" for r in refined)
                          + (f"; {len(rivals)} distinct poses look the same along the frame's rays" if rivals else ""))
        if rivals and scan.clusters:
            before = refined[0].candidate
            told = self._told_by_objects(scan, refined, rivals, refine, candidates, diag)
            if told and refined[0].candidate is not before:
                # The objects put a rival first: the copies of its view were never looked at (the twin check
                # ran from the pose it replaced). A copy that shows the frame as well stands as its rival.
                # (A 100-room view repeated in four rooms was answered `ok` in one of them this way.)
                twins = self._promoted_twins(scan, refined, center_camera, candidates, renders)
                if twins:
                    told = False
                    rivals = rivals + twins
                    diag.notes.append(f"{len(twins)} copies of the objects' pose show the frame as well")
            if told:
                # The frame's objects rule the other poses out: no rival stands, whatever the view margin.
                has_rival, margin, rivals = False, mc.confident_margin, []
        if rivals:
            self._closest_fit_first(scan, refined, rivals, refine, candidates, diag)
        return has_rival, margin, rivals

    def _rank_room(self, refined: list[Refined], candidates: list[Candidate], diag: Diagnostics) -> tuple[bool, float]:
        """In one room: the refined contenders ranked by score; (has a distinct rival, margin), with a rival standing
        whenever a distinct candidate as close as the contenders was left unrefined."""
        mc = self.config.match
        best = candidates[0]
        if len(refined) > 1:
            refined.sort(key=lambda r: -r.score)
            diag.notes.append(f"refined {len(refined)} close hypotheses, scores " + ", ".join(f"{r.score:.3f}" for r in refined))
            has_rival, margin = self._rival_margin([r.score for r in refined], [r.T_map_camera for r in refined])
        else:
            has_rival, margin = self._rival_margin([c.score for c in candidates], [c.T_map_camera for c in candidates])
        # A distinct candidate as close to the best as the contenders, but beyond the refine_contenders refined,
        # was never ruled out: the answer cannot claim to be the one.
        unexamined = [c for c in candidates[1:] if best.score - c.score < mc.ambiguity_margin
                      and not any(c is r.candidate for r in refined)
                      and all(self._distinct(c.T_map_camera, r.T_map_camera) for r in refined)]
        if unexamined:
            diag.notes.append(f"{len(unexamined)} more distinct hypotheses as close as the refined ones were not refined")
            has_rival, margin = True, 0.0
        return has_rival, margin

    def _choice(self, run: RefineRun, refined: list[Refined], taken_next: Candidate | None, has_rival: bool,
                margin: float, rivals: list[Candidate] | None) -> Choice:
        """The winner, refined[0], with its fit to the map and its agreement with the frame's depth."""
        scan, rc, center_camera = run.scan, self.config.refine, run.center_camera
        out, winner, see = refined[0].outcome, refined[0].candidate, refined[0].see_through
        fitness, rmse = self.maps_at(out.T_map_camera, center_camera).refine_map.fitness(
            transform_points(out.T_map_camera, scan.check_xyz), inlier_m=rc.inlier_m)
        if scan.view is not None:
            # In a building, along the frame's rays through the whole map: a region's map holds its neighbours
            # only 3 m out, and a view over the low walls of a composed building reaches farther.
            agreement, coverage = scan.view.shared(self._render_of(scan, run.renders, out))
        elif scan.zbuf is None:
            agreement, coverage = 1.0, 1.0
        else:
            agreement, coverage = self.maps_at(out.T_map_camera, center_camera).view_check.compare_depth(
                out.T_map_camera, scan.zbuf, scan.K, scan.check_xyz)
        passed_over = winner is taken_next
        return Choice(winner, out, margin, has_rival, fitness, rmse, center_camera, run.roi_frame_points, see, agreement,
                      coverage, rivals, passed_over)

    def _near_contender(self, candidates: list[Candidate], contenders: list[Candidate]) -> Candidate | None:
        """In one room: the best candidate within RegionConfig.contender_margin of the best's score that lies beyond
        the refinement's reach of every contender (NEAR_REACH_M, NEAR_REACH_DEG) though not distinct from the best
        (MatchConfig.distinct_translation_m): to the graph one hypothesis, to the refinement another basin, and it
        is refined too, so that the geometry picks between them. A segmenter's labels shift a door's or a
        whiteboard's centroid along its wall: a scene0470 view of a door, its whiteboard left unlabelled, ranked a
        pose 26 cm along the wall 0.04 above the right one (depth agreement 0.82 against 0.98), which was never
        refined, and was answered `ok`, confidence 0.93."""
        best, margin = candidates[0], self.config.regions.contender_margin
        starts = np.array([k.T_map_camera for k in contenders])
        for c in candidates[1:]:
            if best.score - c.score >= margin:
                break  # (sorted best first)
            if any(c is k for k in contenders) or self._distinct(c.T_map_camera, best.T_map_camera):
                continue
            beyond = distinct_pairs(c.T_map_camera[None], starts, min_translation_m=NEAR_REACH_M,
                                    min_rotation_deg=NEAR_REACH_DEG)
            if beyond.all():
                return c
        return None

    def _rival_margin(self, scores: list[float], poses: list[np.ndarray]) -> tuple[bool, float]:
        """(has a distinct rival, margin) of poses sorted best first (refined contenders, or the candidates when
        only the best was refined): the rival is the best pose distinct from the winner, wherever it ranks. A
        runner-up that converged onto the winner is the winner again, not a rival, and must not hide a distinct
        pose behind it (two twin rooms refined to 0.962 and 0.947 with a copy of the first between them were
        answered `ok` with the whole score as margin)."""
        for score, T in zip(scores[1:], poses[1:]):
            if self._distinct(T, poses[0]):
                return True, scores[0] - score
        return False, scores[0]

    def _refine_source(self, scan: Scan, method: str) -> FramePoints:
        """The frame points the refinement draws on: the scan's voxel grid (FrameConfig.voxel_size_m) when it is no
        coarser than small_gicp's own (RefineConfig.source_voxel_m), else every point. Its point budget then grids
        a ninth of the points: on 7-Scenes frames gridding all of them took 18 ms of a 100 ms frame."""
        if method == "small_gicp" and self.config.frame.voxel_size_m <= self.config.refine.source_voxel_m:
            return scan.down
        return scan.points

    def _budget(self, points: FramePoints, method: str) -> FramePoints:
        """The refinement's input: at its own resolution or, when that leaves more than MatchConfig.refine_points,
        at a coarser one that does not (a voxel grid, not a random sample: thin structure such as a door frame
        keeps its points). The others sample their own scales (down to 2 cm) and get the points as they are."""
        if method != "small_gicp":
            return points
        return _voxel_budget(points, self.config.refine.source_voxel_m, self.config.match.refine_points)

    def _refine_one(self, refine_map: RefineMap, points: FramePoints, T_start: np.ndarray, method: str):
        rc = self.config.refine
        return refine_map.refine(points, T_start, method=method, epsilon=rc.epsilon, source_voxel_m=rc.source_voxel_m,
                                 max_correspondence_m=rc.max_correspondence_m, max_iterations=rc.max_iterations,
                                 grid_max_iterations=rc.grid_max_iterations, wide_voxel_m=rc.wide_voxel_m)

    def _result(self, scan: Scan, candidates: list[Candidate], choice: Choice, top_k: int, diag: Diagnostics,
                frame_id: str | None) -> LocalizationResult:
        """Choice -> result: `low_overlap` when too little of the frame lies on the map, `ambiguous` when a
        distinct rival is within the ambiguity margin, `uncertain` when the pose's support is weak (the frame sees
        through the map there, or the confidence is low), else `ok`; confidence from `stages.confidence`."""
        mc, rc = self.config.match, self.config.refine
        out, winner = choice.outcome, choice.candidate
        T = out.T_map_camera
        # A copy's pose carried over from a graph answer rests on the same objects, in its own room.
        by_objects = winner.hypothesis.source == "graph" or (winner.hypothesis.source == "twin"
                                                             and bool(np.any(winner.assignment >= 0)))
        diag.method = "cadreg" if by_objects else winner.hypothesis.source
        diag.refinement = Refinement(method=out.method, iterations=out.iterations, fitness=choice.fitness,
                                     inlier_rmse_m=choice.rmse_m, converged=out.converged)
        center = transform_points(T, choice.center_camera[None])[0]
        in_roi = self.maps_at(T, choice.center_camera).refine_map.roi_count(center, rc.roi_radius_m)
        diag.roi = Roi(center.tolist(), rc.roi_radius_m, in_roi, choice.roi_frame_points)
        if by_objects:
            diag.matches = [Match(i, self.graph.ids[a], self.site.classes[scan.clusters[i].cls])
                            for i, a in enumerate(winner.assignment) if a >= 0]
        hypotheses = [c.hypothesis for c in candidates[:top_k]]
        # How far the frame's geometry lets the pose slide: one wall, or a floor and one wall, fit anywhere along
        # them. On the scene0470 renders without labels the four confident wrong answers (0.50-0.93) could slide
        # 0.44-1.15 cm (one standard deviation) and every right one at most 0.28; on 7-Scenes the right ones 0.34.
        # Only a pose the geometry alone found is held to it: the graph's object matches pin a pose along the
        # directions the refinement leaves free (it does not move it there), and in the 10-room building right
        # graph answers could slide 0.44-0.54 cm. The limit was 0.4 cm before the slide probe (`_slides`) tested
        # what it stands for; right label-free answers in the buildings slide 0.41-0.56 cm (MatchConfig).
        std = pose_std_m(out.covariance)
        slide = 0.0 if by_objects else std

        def trust_for(pose_std: float) -> float:
            return confidence(choice.support, choice.rmse_m, choice.margin, inlier_m=rc.inlier_m,
                              confident_margin=mc.confident_margin, see_through=choice.see_through,
                              max_see_through=mc.max_see_through, pose_std=pose_std, max_pose_std=mc.max_pose_std_m)

        trust = trust_for(slide)
        # An answer taken after every better-ranked pose saw through the map has no rival left standing (their
        # scores are 0), and a margin over none says nothing: it must agree with the map's depth on its own (a
        # scene0470 render was answered `ok` 0.86 m and 34 degrees off, depth agreement 0.79, margin 0.52 over two
        # poses that saw through; the right answers taken so agreed in 97.5-99 % of the view).
        min_depth_agreement = (max(mc.min_depth_agreement, mc.min_depth_agreement_passed_over) if choice.passed_over
                               else mc.min_depth_agreement)
        status = answer_status(choice.fitness, choice.margin, choice.has_rival, choice.see_through, trust,
                               min_fitness=rc.min_fitness, ambiguity_margin=mc.ambiguity_margin,
                               max_see_through=mc.max_see_through, min_ok_confidence=mc.min_ok_confidence,
                               pose_std=slide, max_pose_std=mc.max_pose_std_m,
                               depth_agreement=choice.depth_agreement, min_depth_agreement=min_depth_agreement)
        # The slide probe (`_slides`) holds a graph answer too when its matched objects are a small part of the
        # frame: slivers of a door and a whiteboard under a view over a low wall into a neighbour's curtain were
        # answered `ok` 38 cm and 11 degrees off in a composed building.
        matched = sum(len(scan.clusters[i].index) for i, a in enumerate(winner.assignment) if a >= 0)
        pinned = by_objects and matched >= mc.objects_pin_share * len(scan.down)
        slides = status == Status.OK and not pinned and self._slides(scan, T, choice.center_camera,
                                                                        choice.depth_agreement)
        if slides:
            # As unpinned as the covariance's limit twice over: uncertain, its confidence halved. (Only an answer
            # that would be `ok`: an ambiguous one lists its rivals, and claims none of them either.)
            trust, status = trust_for(max(slide, 2.0 * mc.max_pose_std_m)), Status.UNCERTAIN
        diag.notes.append(f"trust: fitness {choice.fitness:.3f}, rmse {100 * choice.rmse_m:.2f} cm, margin "
                          f"{choice.margin:.3f}, see-through {choice.see_through:.3f}, pose std {100 * std:.2f} cm, "
                          f"depth agreement {choice.depth_agreement:.3f}, map coverage {choice.coverage:.3f}")
        if status == Status.LOW_OVERLAP:
            diag.notes.append(f"fitness {choice.fitness:.2f} below {rc.min_fitness}")
            return LocalizationResult(Status.LOW_OVERLAP, None, confidence=low_overlap_confidence(choice.fitness),
                                      hypotheses=hypotheses, diagnostics=diag, frame_id=frame_id)
        if status == Status.OK and len(self.maps) > 1 and winner.hypothesis.source == "fallback:fpfh-ransac":
            # In a building, a pose FPFH + RANSAC found (it keeps one pose, in one room): a room repeating the view
            # elsewhere was never ruled out. (A pose of the label-free search is: the rooms that repeat its room
            # were looked at along the frame's rays, `_twin_views`. Before that check, answers of a search cut at
            # its node cap were held back here too: 10-room benchmark without labels, unique views 9 % -> 77 %.)
            diag.notes.append("uncertain: FPFH + RANSAC did not look at every room a repeated view may be in")
            status = Status.UNCERTAIN
        if status == Status.UNCERTAIN:
            # Weak support: the refined pose goes first among the hypotheses, but it is not claimed.
            diag.notes.append(f"uncertain: confidence {trust:.2f}, see-through {choice.see_through:.2f}, "
                              f"pose std {100 * std:.2f} cm, depth agreement {choice.depth_agreement:.2f}"
                              + (f"; {100 * mc.slide_probe_m:.0f} cm along the frame's least constrained direction "
                                 "it fits as well" if slides else ""))
            # Listed once: the candidates at the refined pose (the winner's coarse pose, a few millimetres off) are
            # not listed beside it.
            best = replace(winner.hypothesis, T_map_camera=T)
            apart = self._distinct_from_all([h.T_map_camera for h in hypotheses], [T])
            others = [h for h, keep in zip(hypotheses, apart) if keep]
            return LocalizationResult(Status.UNCERTAIN, None, confidence=trust, hypotheses=[best] + others[:top_k - 1],
                                      diagnostics=diag, frame_id=frame_id)
        if status == Status.AMBIGUOUS:
            hypotheses += self._rivals(candidates[top_k:], choice) + scan.unverified
        return LocalizationResult(status, T, confidence=trust,
                                  covariance=out.covariance, hypotheses=hypotheses, diagnostics=diag, frame_id=frame_id)

    def _slides(self, scan: Scan, T_map_camera: np.ndarray, center_camera: np.ndarray, agreement: float) -> bool:
        """Whether the frame fits as well slide_probe_m away along the directions its surfaces constrain least.
        agreement : the frame's depth agreement at T_map_camera (`Choice.depth_agreement`, measured as
        `_depth_agreement` measures it).

        A close view of a curtain, a plain wall or a corner fits anywhere along it, and the refinement's covariance
        does not say so (GICP's plane-shaped covariances make it certain along planes: 0.2-0.3 cm of pose std for
        Replica office0 views placed 0.75-2.3 m off, fitness 0.95-1.0). The two smallest eigenvectors of the frame's
        surface-normal scatter are the directions the geometry leaves freest; moved along each, both ways, a pose
        the frame does not pin keeps its fitness and its depth agreement (the edges of bounded surfaces move in
        the view otherwise). Renders of scene0470 without labels, Replica office0 and 7-Scenes RedKitchen: the
        three wrong `ok` answers of Replica kept 1.00-1.05 of their fitness and lost no agreement; no right
        answer kept more than 0.99 and its agreement within 0.014 at once."""
        mc, rc = self.config.match, self.config.refine
        normals = scan.floor.normals if scan.floor is not None and scan.floor.normals is not None else None
        if normals is None or len(normals) < 20:
            _, normals = planar_normals(scan.down.xyz, k=12, max_points=500, max_flatness=1.0)
        if len(normals) < 20:
            return False
        _, V = np.linalg.eigh(normals.T @ normals)
        maps = self.maps_at(T_map_camera, center_camera)
        xyz_map = transform_points(T_map_camera, scan.check_xyz)
        fitness, _ = maps.refine_map.fitness(xyz_map, inlier_m=rc.inlier_m)
        for axis in (0, 1):
            for sign in (1.0, -1.0):
                shift = T_map_camera[:3, :3] @ V[:, axis] * (sign * mc.slide_probe_m)
                moved, _ = maps.refine_map.fitness(xyz_map + shift, inlier_m=rc.inlier_m)
                if moved < mc.slide_fitness_ratio * fitness:
                    continue
                T_moved = T_map_camera.copy()
                T_moved[:3, 3] += shift
                if self._depth_agreement(T_moved, scan, center_camera) >= agreement - mc.slide_agreement_drop:
                    return True
        return False

    def _depth_agreement(self, T_map_camera: np.ndarray, scan: Scan, center_camera: np.ndarray) -> float:
        """How the frame's depth agrees with the map's at a pose, as the answer's is measured (`_refine`, from the
        renders and the z-buffer comparison it has at hand): along the frame's rays through the whole map in a
        building, else on the pose's region map; 1.0 without depth."""
        if scan.view is not None:
            return scan.view.shared(scan.view.render(self.field, T_map_camera)[0])[0]
        if scan.zbuf is None:
            return 1.0
        return self.maps_at(T_map_camera, center_camera).view_check.depth_agreement(T_map_camera, scan.zbuf, scan.K)

    def _rivals(self, rest: list[Candidate], choice: Choice) -> list[Hypothesis]:
        """Candidates beyond top_k that an ambiguous answer still lists: every distinct one within the ambiguity
        margin of the best (a client must see every room a repeated view may be in, not only the first few)."""
        if choice.rivals is not None:
            return [c.hypothesis for c in rest if any(c is r for r in choice.rivals)]
        best = choice.candidate.score
        return [c.hypothesis for c in rest if best - c.score < self.config.match.ambiguity_margin]

    def _no_pose(self, scan: Scan, diag: Diagnostics, frame_id: str | None) -> LocalizationResult:
        """No hypothesis survived: `no_objects` when the frame showed none, else `no_match`."""
        seen = bool(scan.clusters)
        diag.notes.append("no hypothesis: " + ("no map node matches the scan objects" if seen else "no objects in view"))
        return LocalizationResult(Status.NO_MATCH if seen else Status.NO_OBJECTS, diagnostics=diag, frame_id=frame_id)

    # --- helpers ------------------------------------------------------------------------------------------------
    def _candidate_regions(self, candidates: list[Candidate]) -> list[Region]:
        """In a building, the regions of the graph's candidates (at most RegionConfig.max_verified, best first):
        where the label-free search looks when the graph found something but nothing strong (a search over the
        whole building costs as many rooms as it has). [] for a one-room site or when the graph found nothing."""
        if len(self.maps) == 1:
            return []
        rooms: list[Region] = []
        for c in sorted(candidates, key=lambda c: -c.score):
            region = self.maps.region_at(c.T_map_camera[:3, 3])
            if region not in rooms:
                rooms.append(region)
        return rooms[: self.config.regions.max_verified]

    def _fallback(self, name: str, scan: Scan, notes: list[str], rooms: list[Region]) -> Hypotheses | None:
        """Hypotheses of one fallback method, or None when it cannot run (the label-free search needs up) or
        found nothing the frame's up direction allows."""
        fb, floor = self.config.fallback, scan.floor
        if name == "bbs":
            return self._label_free(scan, notes, rooms)
        registrar = self._fpfh_in_reach(scan, rooms, notes)
        if registrar is None:
            return None
        T, _ = registrar.register(scan.down.xyz)
        if floor is not None:
            # FPFH + RANSAC knows nothing of gravity: on a bare wall it happily returns the camera upside down.
            tilt = np.degrees(np.arccos(np.clip((T[:3, :3] @ floor.up_camera) @ self.up, -1.0, 1.0)))
            if tilt > fb.max_up_disagreement_deg:
                notes.append(f"fallback fpfh-ransac refused: its pose tilts up by {tilt:.0f}° from the {floor.source}'s")
                return None
        hyp = _single(T)
        hyp.geometric = score_poses(self.field, scan.score_xyz, hyp.R, hyp.t, tau_m=self.config.match.score_tau_m)
        return hyp

    def _fpfh_in_reach(self, scan: Scan, rooms: list[Region], notes: list[str]) -> FpfhRansac | None:
        """The FPFH + RANSAC registrar this frame may use: the whole map's in a one-room site; in a building the one
        of a single room (its region map, features computed on first use and kept with it): the room the client's
        search region names or centres on, else the graph's best candidate room. None, with a note, when neither
        exists: the whole building's features would cost seconds a room and a copy of the building per worker, for
        a pose a building could not trust anyway (any other room may repeat the view)."""
        if len(self.maps) == 1:
            return self.fpfh()
        room = None
        if scan.search is not None:
            named = scan.search.resolve(self.maps.regions)
            room = named[0] if len(named) == 1 else (self.maps.region_at(scan.search.center) if not named else None)
        elif rooms:
            room = rooms[0]
        if room is None:
            notes.append("fallback fpfh-ransac skipped: in a building it searches one room (name one in search_region)")
            return None
        index = self.maps.index(room)
        if index.fpfh is None:
            # The room's own box, not its refinement map: that holds a halo of the neighbours' points (3 m), and
            # their features and RANSAC over them took 18 s for one frame of a 100-room site.
            xyz = index.refine_map.xyz
            lo, hi = room.bounds[0] - ROOM_MARGIN_M, room.bounds[1] + ROOM_MARGIN_M
            index.fpfh = FpfhRansac(xyz[np.all((xyz >= lo) & (xyz <= hi), axis=1)],
                                    voxel_m=self.config.fallback.voxel_size_m)
        return index.fpfh

    def _label_free(self, scan: Scan, notes: list[str], rooms: list[Region]) -> Hypotheses | None:
        """The label-free search (bbs.py): level the frame by its up, pick the yaws its walls allow, branch and
        bound over (x, y, z, yaw) — over the client's search region, else over `rooms` (a building's candidate
        regions), else over the whole site; the distinct best leaves as hypotheses. None without an up direction."""
        lf, floor = self.config.label_free, scan.floor
        if not lf.enabled or floor is None:
            return None
        pyr, map_hist = self.pyramid()
        R_up = rotation_between(floor.up_camera, np.array([0.0, 0.0, 1.0]))
        rng = np.random.default_rng(1)
        pick = rng.choice(len(scan.down), min(lf.points, len(scan.down)), replace=False)
        normals = floor.normals if floor.normals is not None else planar_normals(scan.down.xyz, max_points=YAW_NORMAL_POINTS)[1]
        yaws = yaw_candidates(normals @ R_up.T, map_hist, step_deg=lf.yaw_step_deg)
        labelled_floor = floor.source == "floor" and floor.height_m is not None
        points_level = scan.down.xyz[pick] @ R_up.T
        rc = self.config.regions
        found = []
        for box, floor_m, covered in self._search_boxes(scan, pyr.R_level_map, rooms):
            # The budget grows with the rooms the box covers: their coarse levels tie (`bbs.highest`). A box of one
            # room (a candidate's, a region the client names) keeps a room's: at the building's minimum, the
            # graph's weak candidates' rooms searched one by one cost ten times the whole building (a 100-room
            # frame's 48 rooms: 3.3 M nodes, 430 ms); at a room's, every answer of the labelled building sets
            # (10, 16, 100 rooms, mixed; clean and with harsh label noise) stayed, means 3-11 % lower.
            max_nodes = lf.max_nodes if len(self.maps) == 1 or covered == 1 else max(
                rc.search_max_nodes, rc.search_nodes_per_region * covered)
            z_range = None
            if labelled_floor and floor_m is not None:
                # A labelled floor gives the camera's height: only a band about it is searched.
                z_level = floor_m + floor.height_m  # heights along up are the level frame's z
                z_range = (z_level - 2 * lf.voxel_m, z_level + 2 * lf.voxel_m)
            found.append(pyr.search(points_level, yaws, z_range_level=z_range, box_level=box,
                                    keep_ratio=lf.keep_ratio, max_nodes=max_nodes))
        poses = np.concatenate([f[0] for f in found])
        scores = np.concatenate([f[1] for f in found])
        order = np.argsort(-scores, kind="stable")
        poses, scores = poses[order], scores[order]
        stats = found[0][2]
        for f in found[1:]:
            stats.nodes += f[2].nodes
            stats.capped |= f[2].capped
            stats.best = max(stats.best, f[2].best)
        mc = self.config.match
        # In a building the same view may fit in many rooms: more distinct leaves are kept (a room's own leaves
        # would otherwise crowd its twins out), then ranked by room.
        count = lf.candidates if len(self.maps) == 1 else lf.candidates * (1 + self.config.regions.max_verified)
        hyp = pyr.hypotheses(poses, scores, R_up, count=count, min_translation_m=mc.distinct_translation_m,
                             min_rotation_deg=mc.distinct_rotation_deg)
        hyp = polish(self.field, scan.score_xyz, hyp, self.up, step_m=lf.voxel_m / 2, step_deg=lf.yaw_step_deg / 2,
                     later_within=self.config.regions.tie_margin + POLISH_LATER_GAIN)
        if len(self.maps) > 1 and len(hyp):
            keep, unverified = self._region_candidates(hyp, hyp.geometric, self.maps.indices_at(hyp.t),
                                                       count=lf.candidates)
            scan.unverified += [self._unverified_hypothesis(hyp, i, "fallback:bbs:unverified") for i in unverified]
            hyp = hyp.take(np.array(keep, dtype=np.int64))
        notes.append(f"label-free search: {len(yaws)} yaws, {stats.nodes} nodes, best leaf {stats.best:.2f}"
                     + (" (node cap reached)" if stats.capped else ""))
        return hyp if len(hyp) else None

    def _search_boxes(self, scan: Scan, R_level_map: np.ndarray,
                      rooms: list[Region]) -> list[tuple[np.ndarray | None, float | None, int]]:
        """(box, floor, regions) of each part of the site the label-free search covers: the box (level frame,
        (2, 3) corners) of camera positions, or None for the whole site; the floor height along up under it, None
        where the regions under it do not share one; and how many regions' boxes it meets. One per region the client
        named, or the client's ball; without a search region one per room of `rooms`, or the whole site when there
        are none."""
        if scan.search is None and not rooms:
            return [(None, self._shared_floor(self.maps.regions), len(self.maps))]
        if scan.search is None or scan.search.region_ids:
            chosen = rooms if scan.search is None else scan.search.resolve(self.maps.regions)
            boxes = [(np.stack([r.bounds[0] - CAMERA_MARGIN_M, r.bounds[1] + CAMERA_MARGIN_M]), self._shared_floor([r]), 1)
                     for r in chosen]
        else:
            lo, hi = scan.search.center - scan.search.radius_m, scan.search.center + scan.search.radius_m
            met = sum(bool(np.all(r.bounds[0][:2] <= hi[:2]) and np.all(lo[:2] <= r.bounds[1][:2]))
                      for r in self.maps.regions)
            boxes = [(np.stack([lo, hi]), self._shared_floor(self.maps.regions), max(met, 1))]
        out = []
        for (lo, hi), floor_m, covered in boxes:
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            level = corners @ R_level_map.T
            out.append((np.stack([level.min(axis=0), level.max(axis=0)]), floor_m, covered))
        return out

    def _shared_floor(self, regions: list[Region]) -> float | None:
        """The floor height along up those regions share (within the label-free search's voxel), else None."""
        floors = np.array([self.region_floor_m[r.id] for r in regions])
        return float(np.median(floors)) if np.ptp(floors) <= self.config.label_free.voxel_m else None

    def _align(self, hyp: Hypotheses, source: small_gicp.PointCloud, scan: Scan, *,
               origin: str = "graph") -> list[Candidate]:
        """Hypotheses -> candidates: in a one-room site a coarse GICP from each and its agreement score; in a
        building (`scan.view`) all pulled onto the stored distance field at once and scored by their depth along
        the frame's rays: no room's map is built to rank the rooms a view may be in. `origin` names where the
        hypotheses came from."""
        if scan.view is None:
            xyz = np.asarray(source.points())[:, :3]
            poses = [self._coarse_align(source, xyz, hyp.T(i), scan) for i in range(len(hyp))]
            return [self._candidate(hyp, i, T, self._agreement_score(T, scan), origin) for i, T in enumerate(poses)]
        R, t = align_on_field(self.field, scan.score_xyz, hyp.R, hyp.t, up=None if scan.floor is None else self.up,
                              iterations=FIELD_ALIGN_ITERATIONS, reach_m=FIELD_ALIGN_REACH_M)
        T = make_Ts(R, t)
        rendered = scan.view.render(self.field, T)
        score = scan.view.agreement(rendered)
        return [self._candidate(hyp, i, T[i], float(score[i]), origin, rendered[i]) for i in range(len(hyp))]

    def _coarse_align(self, source: small_gicp.PointCloud, xyz: np.ndarray, T_map_camera: np.ndarray,
                      scan: Scan) -> np.ndarray:
        """One-room coarse GICP of a hypothesis. When more than COARSE_FAR_SHARE of the frame's points (source,
        its points xyz) lie the field's truncation or more from the map there (0.5 m: the GICP's 0.3 m reach and
        0.2 m for the pose to move, as in `refine.REACH_MARGIN_M`), the GICP runs on the others: small_gicp's
        KD-tree visits most of the map for each far point (a 3DMatch frame's hypotheses on a one-frame map, 60 %
        of their points over 0.5 m off, took 10 ms each instead of 3). A pose with nothing near the map stays."""
        refine_map = self.maps_at(T_map_camera, scan.center_camera).refine_map
        far = ~self.near_map(xyz, T_map_camera)
        if far.mean() > COARSE_FAR_SHARE:
            if (~far).sum() <= GICP_NEIGHBORS:
                return T_map_camera
            source = small_gicp.PointCloud(xyz[~far])
            small_gicp.estimate_covariances(source, num_neighbors=GICP_NEIGHBORS)
        return refine_map.coarse_align(source, T_map_camera)

    def near_map(self, xyz_camera: np.ndarray, T_map_camera: np.ndarray) -> np.ndarray:
        """(n,) bool: which points (camera frame) T_map_camera puts within the distance field's truncation of the
        map (0.5 m). A lookup a point: what keeps points no GICP could pair away from small_gicp's unbounded
        nearest-neighbour search, which visits most of the map for each (the coarse GICP, tracking)."""
        return self.field.lookup(transform_points(T_map_camera, xyz_camera)) < self.field.truncate_m

    def _candidate(self, hyp: Hypotheses, i: int, T: np.ndarray, score: float, origin: str,
                   rendered: np.ndarray | None = None) -> Candidate:
        scored = lambda values: len(values) == len(hyp)  # noqa: E731  (fallback hypotheses carry no Sim terms)
        assignment = hyp.assignment[i] if scored(hyp.assignment) else np.zeros(0, dtype=np.int64)
        h = Hypothesis(T, float(hyp.sim[i]) if scored(hyp.sim) else 0.0, float(hyp.s_v[i]) if scored(hyp.s_v) else 0.0,
                       float(hyp.s_e[i]) if scored(hyp.s_e) else 0.0, score,
                       matches=[(int(k), self.graph.ids[a]) for k, a in enumerate(assignment) if a >= 0],
                       source=origin, region=self.region_of(T))
        return Candidate(T, score, h, assignment, rendered)

    def _agreement_score(self, T_map_camera: np.ndarray, scan: Scan) -> float:
        """Geometric fitness weighted by label and colour agreement of the scan's fit sample placed by T: geometry
        alone cannot tell a wall from the opposite wall or a chair seen from above turned by 90°."""
        mc = self.config.match
        geo, sem, col = self.maps_at(T_map_camera, scan.center_camera).refine_map.agreement(transform_points(T_map_camera, scan.fit_xyz), scan.fit_lab,
                                                  scan.fit_cls, inlier_m=self.config.refine.inlier_m)
        return geo * (1.0 - mc.semantic_weight + mc.semantic_weight * sem) * (1.0 - mc.color_weight + mc.color_weight * col)

    def _distinct(self, Ta: np.ndarray, Tb: np.ndarray) -> bool:
        """Whether two poses ((4, 4)) are distinct hypotheses (MatchConfig.distinct_translation_m or
        distinct_rotation_deg apart)."""
        return bool(self._distinct_pairs(Ta[None], Tb[None])[0, 0])

    def _distinct_pairs(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """A (a, 4, 4), B (b, 4, 4) -> (a, b) bool: `_distinct` of every pair, at once (a 100-room frame asked it of
        170 k pairs of poses, one call each: 7 ms)."""
        mc = self.config.match
        return distinct_pairs(A, B, min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg)

    def _distinct_from_all(self, poses: list[np.ndarray], others: list[np.ndarray]) -> np.ndarray:
        """(len(poses),) bool: whether each of `poses` is distinct from every one of `others` ((4, 4) each)."""
        if not len(poses) or not len(others):
            return np.ones(len(poses), dtype=bool)
        return self._distinct_pairs(np.asarray(poses), np.asarray(others)).all(axis=1)


def _region_sample(site: Site, region: Region, count: int) -> np.ndarray:
    """(m, 3) points of `region`'s own, count <= m < 2 count (all of them when it has fewer): the enhanced map's
    rows of it, evenly strided; map frame."""
    start, stop = region.map_range
    step = max(1, (stop - start) // count)
    xyz = np.asarray(site.map.points[start:stop:step], dtype=np.float64)
    site.release("map", slice(start, stop))
    return xyz


def _surface_sample(site: Site, maps: RegionMaps) -> PointSet:
    """The map points the site-wide constants (up direction, floor height, wall directions) are measured on: all of
    a one-room site; in a building its largest region (its rooms share the floor and, turned by quarter turns,
    the wall directions), so that loading a building does not read all of it."""
    if len(maps) == 1:
        return site.cloud("both")
    largest = max(maps.regions, key=lambda r: r.points)
    return region_cloud(site, largest, "both")


def _voxel_budget(points: FramePoints, voxel_m: float, budget: int) -> FramePoints:
    """`points` on a voxel grid of voxel_m or, when that leaves more than `budget`, of the coarser voxel that does
    not (a grid, not a random sample: thin structure such as a door frame keeps its points). A frame's points lie
    on surfaces, so their count falls about with the voxel's square: one guess, then growth by VOXEL_GROWTH."""
    sparse = voxel_downsample(points, voxel_m)
    if len(sparse) > budget:
        voxel_m *= np.sqrt(len(sparse) / budget)
        sparse = voxel_downsample(points, voxel_m)
        while len(sparse) > budget:
            voxel_m *= VOXEL_GROWTH
            sparse = voxel_downsample(points, voxel_m)
    return sparse


def _single(T_map_camera: np.ndarray) -> Hypotheses:
    """One hypothesis from a pose that no graph seed produced (a prior, an FPFH + RANSAC pose)."""
    return Hypotheses(T_map_camera[None, :3, :3].copy(), T_map_camera[None, :3, 3].copy(), np.array([[-1, -1]]))
