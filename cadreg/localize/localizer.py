"""The localizer: one RGB-D frame -> T_map_camera in a site's map, with no initial guess.

`localize` reads as its stages (DESIGN §1; the values between them are in `stages.py`):

    scan        frame -> points, class-wise clusters (the scan graph), up direction and floor
    hypotheses  coarse graph matching scored by Sim and a distance-field check (match.py)
    verify      a coarse GICP pulls each distinct hypothesis (and a client's prior) in, ranked by geometry, labels
                and colour; when the graph's best is weak (no labels, no objects, no match) the label-free
                search joins (branch-and-bound over x, y, z, yaw, `bbs.py`), FPFH + RANSAC only without an up
                (`fallback_stage.py`)
    refine      fine refinement inside the region of interest of the best, and of its close rivals; in a building,
                the copies of its view in the rooms that repeat it (`refine_stage.py`, `building_views.py`)
    result      status, confidence and diagnostics

Everything site-dependent is built once in `from_site` and reused for every frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np
import small_gicp

from ..config import REFINE_METHODS, LocalizeConfig
from ..errors import InvalidArgument, InvalidFrame
from ..frame import Frame
from ..geometry import make_Ts, rotation_between, transform_points
from ..result import Diagnostics, Hypothesis, LocalizationResult, Match, Refinement, Roi, ScanObject, Status
from ..pointset import PointSet
from ..site.bundle import Site
from ..site.regions import Region
from .cluster import cluster_objects
from .color_gicp import rgb_to_lab
from .bbs import (GridPyramid, building_pyramid, built_with, map_direction_histogram, pyramid_settings,
                  turned_histogram)
from .building_views import SAME_PLACE_DEPTH_MARGIN, BuildingViews
from . import cluster, field_kernels, gravity, grid_gicp, match, point_tree, view_kernels
from . import points as frame_points
from . import twins as room_twins
from .fallback import FpfhRansac
from .fallback_stage import BBS_UNVERIFIED, DEEPER_SEARCH_NODES, FallbackStage
from .field_view import FieldView, align_on_field
from .twins import SHAPE_POINTS, RoomTwins
from .gravity import estimate_floor, map_floor_height, map_up_axis, planar_normals
from .match import (Hypotheses, MapGraph, best_overall_and_by_group, distinct_best, distinct_pairs,
                    gravity_hypotheses, kabsch_hypotheses, score_graph)
from .points import sampled_points, voxel_budget, voxel_downsample, window_colours
from .refine import GICP_NEIGHBORS, RefineMap
from .refine_stage import RefineStage
from .regions import RegionIndex, RegionMaps, region_cloud
from .score import DistanceField, ViewCheck, reference_camera, score_poses
from .stages import (NEAR_REACH_DEG, NEAR_REACH_M, Candidate, Choice, Scan, StageTimer, answer_status, confidence,
                     low_overlap_confidence, pose_std_m)
from .tracking import Tracked, TrackState, track_frame

# The quick screen of every graph hypothesis uses a third of the scoring points (at least this many): enough to
# drop the hopeless ones, three times cheaper than the full check of those kept.
SCREEN_SHARE = 3
MIN_SCREEN_POINTS = 20
# A building's first look at its graph hypotheses keeps this many times what the screen keeps (`_hypotheses`),
# on a copy of the field with cells this many times as large (`DistanceField.coarsened`).
FIRST_LOOK_WIDER = 8
FIRST_LOOK_COARSENING = 4
# `warm` makes the rooms' twins (`RoomTwins.warm`) for at most this long: a building's rows cost the square of its
# rooms (100 rooms: 0.3 s); the rest are made on first use.
TWINS_WARM_S = 2.0
# Cheapest first. FPFH + RANSAC runs only when the label-free search could not (no up direction): it costs
# ten times more and, knowing nothing of gravity, is no better where the search finds nothing.
FALLBACKS = ("bbs", "fpfh-ransac")
# Frame points of the coarse GICP of each hypothesis, at most. 600 (was 1000): the labelled renders' median fell by
# an eighth (verify is 8 coarse GICPs), with the same answers there and on 7-Scenes, and 3 more right poses in the
# 10-room building.
COARSE_POINTS = 600
# The colour gate reads each of its points' colour as the mean of this many pixels each way about its own (5 × 5):
# one pixel's colour is noise enough to hide a grey room's chroma (`points.window_colours`).
COLOUR_WINDOW = 2
# A hypothesis whose coarse GICP would hand over more than this share of its points far from the map gets a cloud
# of the others (`_coarse_align`): rebuilding one costs 0.5 ms, so hypotheses with a few far points keep the shared one.
COARSE_FAR_SHARE = 0.25
# The field alignment of a building's hypotheses (`field_view.align_on_field`): from a reach of half a metre (the
# field's truncation) down to 6 cm in 15 steps. On the 10-room benchmark's frames, poses 40 cm and 5° off came
# within 5 cm / 5° in 86 % of the cases (72 % from a 25 cm reach in 10 steps; 20 cm off: 98 %), at 1.4 ms each.
FIELD_ALIGN_ITERATIONS = 15
FIELD_ALIGN_REACH_M = (0.5, 0.06)
# The label-free search's leaves come polished to half its finest cell (`bbs.polish`, LabelFreeConfig.voxel_m):
# they are pulled in from a reach of that cell down to this, not from the field's truncation. A real frame sees
# more than a fused map holds (what no mapping frame saw), and from half a metre those points, paired with
# whatever surface lay nearest, pulled leaves 2-8 cm from the answer 20-40 cm away into another basin (real
# 7-Scenes RedKitchen frames in a 3-room building, the kitchen fused from other frames of the sequence: of the 137
# frames the kitchen alone answered `ok`, 92 -> 118 got its answer; renders, which show nothing the map lacks,
# did not need the reach: the building sets' answers the same or an `ok` <-> `ambiguous` either way).
LEAF_ALIGN_LAST_REACH_M = 0.05
# An object's top is the 98th percentile of its points along up: the highest 2 % are mixed pixels and noise.
TOP_PERCENTILE = 98


# A one-room answer at which the frame sees more than this share of its points on the map's surfaces from behind is
# not claimed (`Localizer._seen_from_behind`). A scan's own normals (a mesh's, a fused map's) leave at most 12 % of a
# right answer's points seen so; normals a site build estimates for a bare point cloud, turned towards the scan's
# centroid, make a central object's faces that look at the walls seem seen from behind: scene0470 built so, up to
# 49 % at the 200 renders' true poses. An answer from outside the room, 99.7 %.
MAX_SEEN_FROM_BEHIND = 0.8


def compile_loops(field_dtypes: tuple[type[np.generic], ...] = field_kernels.FIELD_DTYPES, *,
                  last_first: bool = False) -> None:
    """Compile (or load from numba's cache) every compiled loop the localizer runs, the field's for the kinds of
    grid given: `Localizer.warm` at a server's start (its site's kind), the Dockerfile at build time (both).
    last_first: module by module in the reverse order. A server's workers start together: on a cold cache (a fresh
    install's first start) two that begin at opposite ends find, by the middle, what the other has compiled in the
    cache, and each compiles about half."""
    steps = [partial(field_kernels.warm, field_dtypes)]
    steps += [module.warm for module in (cluster, frame_points, gravity, grid_gicp, match, point_tree, room_twins,
                                         view_kernels)]
    for step in reversed(steps) if last_first else steps:
        step()


def compile_loops_for(site: Site, *, last_first: bool = False) -> None:
    """`compile_loops` for the kind of grid the site's field holds: a building's stored bytes, else the float metres
    a room's field is built in at load (`Localizer.from_site`). `Localizer.warm` runs it at a server's start, and
    `site build`, `site compose` and `site fuse` when they end, so that the first server or bench on this machine
    reads the loops from numba's cache (0.2 s) instead of compiling them (10 s on one core for a building's; once
    per install and code change)."""
    compile_loops((site.field_grid.grid.dtype.type if site.field_grid is not None else np.float32,),
                  last_first=last_first)


class Localizer(RefineStage, BuildingViews, FallbackStage):
    """Localize frames in one site. Build with `from_site`; `localize` is read-only and may be called repeatedly.

    up : (3,) unit vector opposite to gravity, map frame. floor_height_m : the floor's height along `up`, metres.
    graph : the site's semantic graph as arrays. field : distance field over the whole map (raw and enhanced).
    maps : the site's regions and, per region, the map the refinement and the agreement scores use
    (`RefineConfig.map_points`) and the free-space check (`regions.py`): a pose uses those of the region it looks
    into. node_region : (k,) int, the region (index into `maps.regions`) of each graph node. The refine stage's
    steps are in its base classes `refine_stage.RefineStage` and, those only a building takes,
    `building_views.BuildingViews`; the verify stage's fallbacks in `fallback_stage.FallbackStage`.
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
        self._pyramid: tuple[GridPyramid, np.ndarray | None, list[np.ndarray | None] | None] | None = None
        self.twins = (RoomTwins(graph, self.node_region, up, len(maps.regions),
                                floors=np.array([self.region_floor_m[r.id] for r in maps.regions]), field=field,
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
        up = site.up if site.up is not None else map_up_axis(surface_normals, points=surface_xyz)
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

    def warm(self, *, compile_last_first: bool = False) -> "Localizer":
        """Build now what is otherwise built on first use (the map's FPFH features for the fallback, about a second
        a site; the compiled loops, `compile_loops_for`, in the reverse order if compile_last_first), so that a
        long-running server does not make its first requests pay for it."""
        if len(self.maps) == 1:
            self.refine_map.fine_target()
            self.refine_map.wide_voxels(self.config.refine.wide_voxel_m)
            self.refine_map.coarse_target()
            self.refine_map.fit_lab  # noqa: B018  (made on first read)
        # A building's FPFH features (the last resort, with no up direction) would cost seconds and a copy of
        # the whole map in every worker: built on first use there.
        if self.config.fallback.enabled and len(self.maps) == 1:
            self.fpfh()
        compile_loops_for(self.site, last_first=compile_last_first)
        if self.twins is not None:
            # after the loops are compiled: the budget is for the rows, not for the RANSAC's compilation
            self.twins.warm(TWINS_WARM_S)
        if self.config.label_free.enabled:
            self.pyramid()  # (a building's wall directions read the rows: `RoomTwins.one_of_each`)
        return self

    def pyramid(self) -> tuple[GridPyramid, np.ndarray | None, list[np.ndarray | None] | None]:
        """The label-free search's grid pyramid of this site, the map's histogram of wall directions, and in a
        building each region's own (None in one room; built on first use, or by `warm`: about a second and
        (levels + 1) bytes a cell, LabelFreeConfig.max_cells at most). A building's bundle stores its pyramid: it is
        mapped when it was built with this localizer's up and settings."""
        if self._pyramid is None:
            lf = self.config.label_free
            if len(self.maps) == 1:
                surfaces = self.site.cloud("both")
                pyr = GridPyramid(self.field, surfaces.points, self.up, **pyramid_settings(lf))
                walls = map_direction_histogram(surfaces.normals.astype(np.float64) @ pyr.R_level_map.T)
                region_walls = None
            else:
                stored = self.site.pyramid
                wanted = built_with(self.up, **pyramid_settings(lf))
                pyr = None if stored is None else GridPyramid.from_stored(stored, wanted)
                if pyr is None:
                    pyr = building_pyramid(self.field, self.up, lf)
                walls, region_walls = self._building_wall_directions(pyr.R_level_map)
            self._pyramid = (pyr, walls, region_walls)
        return self._pyramid

    def _building_wall_directions(self, R_level_map: np.ndarray) -> tuple[np.ndarray | None, list[np.ndarray | None]]:
        """A building's histogram of wall directions (`bbs.map_direction_histogram`, level frame): the mean of those
        of the largest region of each set of regions that repeat one another (`RoomTwins.one_of_each` and its
        copies), each region's points read in turn; and each region's own, its set's largest region's turned by
        its turn from it (None for a region of a set without vertical surfaces to speak of).

        Its largest region alone need not share its rooms' directions: a corridor segment's walls face across it
        only, and in a 30-room building with corridors, views without labels of its rooms' other walls had every yaw
        the search tried 74-79° from their own (5 of the 14 repeated views whose truth no hypothesis held). Every
        turned copy of a room would blur them instead: a building of copies of one room keeps its largest room's,
        turned by each copy's turn that is no quarter turn (`bbs.turned_histogram`): ten copies each turned by a
        random angle and scanned in one piece had 95.0 % of their unique views right without labels, 98.3 % so."""
        regions, hists = self.maps.regions, []
        own: list[np.ndarray | None] = [None] * len(regions)
        for k in self.twins.one_of_each():
            members = [(k, np.eye(4))] + self.twins.of(k)
            b, T_b_k = max(members, key=lambda m: regions[m[0]].points)
            largest = regions[b]
            hist = map_direction_histogram(region_cloud(self.site, largest, "both").normals.astype(np.float64)
                                           @ R_level_map.T)
            self.site.release("map", slice(*largest.map_range))
            self.site.release("raw", slice(*largest.raw_range))
            if hist is not None:
                # each member's turn from the largest, about up (level frame)
                turns = [R_level_map @ T[:3, :3] @ T_b_k[:3, :3].T @ R_level_map.T for _, T in members]
                yaws = np.array([np.arctan2(R[1, 0], R[0, 0]) for R in turns])
                hists.append(turned_histogram(hist, yaws))
                for (m, _), yaw in zip(members, yaws):
                    if own[m] is None:
                        own[m] = turned_histogram(hist, yaw[None])
        return (np.mean(hists, axis=0) if hists else None), own

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
        # Only an answer that lies on the map (RefineConfig.min_fitness) is looked at again: one that does not is
        # `low_overlap` whatever its colours, and a frame looking past the map's edge would pay the second look's
        # refinements for nothing (7-Scenes: 50 -> 90-130 ms on such frames).
        if (scan.reserve is not None and choice.fitness >= self.config.refine.min_fitness
                and self._chroma_doubtful(choice.chroma)):
            with timer("fallback"):
                candidates, choice = self._second_look(scan, candidates, choice, method, diag)
        if self._weak_after_a_cut_search(scan, choice):
            with timer("fallback"):
                candidates, choice = self._deeper_look(scan, candidates, choice, method, diag)
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
            points = sampled_points(frame, fc.pixel_stride, reference_pixels=fc.stride_reference_pixels,
                                    min_depth_m=fc.min_depth_m, max_depth_m=fc.max_depth_m, min_points=fc.min_points)
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
            floor = estimate_floor(down.xyz, down.labels, frame.label_set, gravity_camera=frame.gravity_camera,
                                   dense_xyz=points.xyz)
            if floor is not None:
                diag.notes.append(f"up from {floor.source}"
                                  + (f", camera {floor.height_m:.2f} m above floor" if floor.height_m else ""))
        rng = np.random.default_rng(0)
        score = rng.choice(len(down), min(fc.score_points, len(down)), replace=False)
        fit = rng.choice(len(down), min(fc.fit_points, len(down)), replace=False)
        check = rng.choice(len(points), min(fc.check_points, len(points)), replace=False)
        K = reference_camera(frame.depth_intrinsics)
        return Scan(points, down, class_index, clusters, floor, score_xyz=down.xyz[score], fit_xyz=down.xyz[fit],
                    fit_lab=rgb_to_lab(down.rgb[fit]), fit_cls=class_index[fit] if labelled.any() else None,
                    fit_rgb=window_colours(frame, down.xyz[fit], COLOUR_WINDOW),
                    check_xyz=points.xyz[check],
                    zbuf=ViewCheck.zbuffer(down.xyz, K), K=K,
                    center_camera=_centroid(points.xyz), search=frame.search_region,
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
                                hyp.R_table, hyp.t, rot=hyp.rot, tau_m=mc.score_tau_m)
            hyp = hyp.take(self._screened(hyp, first, wider=FIRST_LOOK_WIDER))
        screen = score_poses(self.field, screen_xyz, hyp.R_table, hyp.t, rot=hyp.rot, tau_m=mc.score_tau_m)
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
        each for a first look. In one room, best first; in a building, in index order (equal scores there taken in
        index order: `match.best_overall_and_by_group`)."""
        count = wider * self.config.match.screen_keep
        if len(self.maps) == 1:
            return np.argsort(-screen)[:count]
        return best_overall_and_by_group(screen, self._seed_regions(hyp), count=count,
                                         per_group=wider * self.config.regions.screen_per_region)

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
            source = self._coarse_source(scan)
            candidates = self._align(hyp, source, scan)
            if prior is not None:
                # A client's pose prior is one more hypothesis, checked like the others (never trusted blindly).
                candidates += self._align(Hypotheses.of_pose(prior), source, scan, origin="prior")
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
                        candidates += self._apart_from(self._align(found, source, scan, origin=f"fallback:{name}"),
                                                       [g.T_map_camera for g in candidates])
                        best = max([best] + [c.score for c in candidates])
                        if best >= enough:
                            break
        # Stable: among equal scores the graph's order (its ranking) stands.
        candidates = sorted(candidates, key=lambda c: -c.score)
        if scan.view is not None:
            candidates = self._one_per_place(scan, candidates)
        return candidates

    def _one_per_place(self, scan: Scan, candidates: list[Candidate]) -> list[Candidate]:
        """A building's candidates (best first) with one per place: hypotheses of one room pulled onto the field
        often meet at one pose (within the distinct-pose radius of each other). Each place keeps its best, unless a
        later one there agrees with the frame's depth on the rays both show a surface on by SAME_PLACE_DEPTH_MARGIN
        more (`FieldView.shared`): then that one stands in its place, as the refine stage puts such a refinement
        first (`_deepest_at_the_winners_place_first`). A real frame sees what no mapping frame saw, and the view
        agreement ranks a pose turned toward the mapped part first: the right leaf of a real RedKitchen frame in a
        3-room building (5 mm from the kitchen alone's answer) was dropped here for one 26 cm off."""
        poses = np.array([c.T_map_camera for c in candidates]).reshape(-1, 4, 4)
        alike = ~self._distinct_pairs(poses, poses)
        depth = [None] * len(candidates)  # made for the candidates that share a place, when asked

        def depth_of(k: int) -> float:
            if depth[k] is None:
                depth[k] = scan.view.shared(candidates[k].rendered)[0] if candidates[k].rendered is not None else 0.0
            return depth[k]

        kept: list[int] = []
        for k in range(len(candidates)):
            here = [j for j, i in enumerate(kept) if alike[k, i]]
            if not here:
                kept.append(k)
            elif len(here) == 1 and depth_of(k) > depth_of(kept[here[0]]) + SAME_PLACE_DEPTH_MARGIN:
                kept[here[0]] = k
        return [candidates[k] for k in kept]

    def _coarse_source(self, scan: Scan) -> small_gicp.PointCloud:
        """The frame's points of the coarse GICP: at most COARSE_POINTS (a coarser grid for a frame that spans a
        large room): each candidate's coarse GICP costs a KD-tree query of each per iteration."""
        coarse = voxel_budget(scan.down, self.config.refine.coarse_voxel_m, COARSE_POINTS)
        return small_gicp.preprocess_points(coarse.xyz, self.config.refine.coarse_voxel_m,
                                            num_neighbors=GICP_NEIGHBORS)[0]

    def _view_bar(self, candidates: list[Candidate]) -> float:
        """The view agreement a building's best candidate needs for the fallbacks not to join
        (RegionConfig.min_view_agreement; min_one_object_view_agreement when it rests on at most one object)."""
        best = max(candidates, key=lambda c: c.score, default=None)
        if best is None or int(np.sum(best.assignment >= 0)) > 1:
            return self.config.regions.min_view_agreement
        return self._one_object_view_bar()

    def _one_object_view_bar(self) -> float:
        """The view agreement a building's answer needs when little points at its room: what the graph's best needs
        when it rests on one object (`_view_bar`), and the answer of a label-free search kept to the graph's guessed
        rooms (`FallbackStage._label_free`)."""
        rg = self.config.regions
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
        # what it stands for; right label-free answers in the buildings slide 0.41-0.56 cm (MatchConfig). Beyond
        # the limit, a pose that would be `ok` is no longer held back on the covariance's word: the probe decides,
        # and its confidence falls with the spread (`stages.answer_status`). Right label-free answers at 0.60-0.63
        # cm in three buildings had been `uncertain` (confidence 0.81-0.89), and no wrong one became `ok`.
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
        min_depth_agreement = (mc.min_depth_agreement if choice.view_agreement is None
                               else self.config.regions.min_depth_agreement)
        if choice.passed_over:
            min_depth_agreement = max(min_depth_agreement, mc.min_depth_agreement_passed_over)
        # In a building the margin is between view agreements, and grows where they are noisier (`_view_margin`).
        ambiguity_margin = (mc.ambiguity_margin if choice.view_agreement is None
                            else self._view_margin(choice.view_agreement))
        status = answer_status(choice.fitness, choice.margin, choice.has_rival, choice.see_through, trust,
                               min_fitness=rc.min_fitness, ambiguity_margin=ambiguity_margin,
                               max_see_through=mc.max_see_through, min_ok_confidence=mc.min_ok_confidence,
                               pose_std=slide, max_pose_std=mc.max_pose_std_m,
                               depth_agreement=choice.depth_agreement, min_depth_agreement=min_depth_agreement)
        # The slide probe (`_slides`) holds a graph answer too when its matched objects are a small part of the
        # frame: slivers of a door and a whiteboard under a view over a low wall into a neighbour's curtain were
        # answered `ok` 38 cm and 11 degrees off in a composed building.
        # Nor do objects pin the camera's height when the frame shows no floor: a partly seen door or wall's
        # centroid lies above or below its node's, and a view of walls alone lets the refinement slide up and down
        # (150 renders at a robot's height, 0.3-0.8 m: seven close views of the door and the wall beside it answered
        # `ok` 5-24 cm too high or too low, confidence 0.82-0.95).
        matched = sum(len(scan.clusters[i].index) for i, a in enumerate(winner.assignment) if a >= 0)
        floor_seen = scan.floor is not None and scan.floor.height_m is not None
        pinned = by_objects and floor_seen and matched >= mc.objects_pin_share * len(scan.down)
        slides = status == Status.OK and not pinned and self._slides(scan, T, choice.center_camera,
                                                                        choice.depth_agreement)
        if slides:
            # As unpinned as the covariance's limit twice over: uncertain, its confidence halved. (Only an answer
            # that would be `ok`: an ambiguous one lists its rivals, and claims none of them either.)
            trust, status = trust_for(max(slide, 2.0 * mc.max_pose_std_m)), Status.UNCERTAIN
        # The shape alone may fit another place: a close view of a door in a corner fits every corner of the room.
        # The colours there are the other place's (`_chroma_rules_out`). A pose the frame's objects pin is where its
        # labels say (under a camera's colour faults the gate held back right graph answers, and no wrong one).
        if choice.chroma is not None:
            diag.notes.append(f"colour: the frame's chroma correlates {choice.chroma:.2f} with the map's at the answer")
        recoloured = status == Status.OK and not pinned and self._chroma_rules_out(choice.chroma)
        if recoloured:
            trust, status = 0.5 * trust, Status.UNCERTAIN
        behind = status == Status.OK and self._seen_from_behind(scan, T, choice.center_camera)
        if behind:
            trust, status = 0.5 * trust, Status.UNCERTAIN
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
                                 "it fits as well" if slides else "")
                              + ("; the frame's colours are not the map's there" if recoloured else "")
                              + ("; a sensor there would see most of the map's surfaces from behind" if behind else ""))
            # Listed once: the candidates at the refined pose (the winner's coarse pose, a few millimetres off) are
            # not listed beside it.
            best = replace(winner.hypothesis, T_map_camera=T)
            others = self._apart_from(hypotheses, [T])[:top_k - 1]
            if choice.has_rival and choice.margin < ambiguity_margin:
                # A close rival is as much the frame's place as the answer: listed, as an ambiguous answer lists
                # every one, beyond top_k. (A label-free view of a 16-room building with moved furniture, the pose
                # too loose to be `ambiguous`, listed five search leaves and left out three copies of its view that
                # showed it better, the true room's 4 cm from the truth.)
                listed = {id(h) for h in others}
                others += [h for h in self._apart_from(self._rivals(candidates, choice) + scan.unverified, [T])
                           if id(h) not in listed]
            return LocalizationResult(Status.UNCERTAIN, None, confidence=trust, hypotheses=[best] + others,
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

    def _seen_from_behind(self, scan: Scan, T_map_camera: np.ndarray, center_camera: np.ndarray) -> bool:
        """Whether a sensor at the pose would see more than MAX_SEEN_FROM_BEHIND of the frame's check points on the
        map's surfaces from behind (`RefineMap.seen_from_behind`; a one-room map only, where the scan's normals face
        the side it was scanned from). A flat face fits from both sides: a close view of scene0470's door, rendered
        as a phone's 256 x 192 depth camera sees it and without labels, was answered `ok` 1.1 m off and turned 180°,
        from outside the room (confidence 0.94); there 99.7 % of its points lie on surfaces seen from behind. At the
        true poses of the scene0470 renders, Replica office0's and the real RedKitchen frames: at most 12 %."""
        share = self.maps_at(T_map_camera, center_camera).refine_map.seen_from_behind(
            transform_points(T_map_camera, scan.check_xyz), T_map_camera[:3, 3], inlier_m=self.config.refine.inlier_m)
        return share is not None and share > MAX_SEEN_FROM_BEHIND

    def _chroma_rules_out(self, chroma: float | None) -> bool:
        """Whether the frame's colours at a pose fail to follow the map's: their chroma correlates with the map's less
        than MatchConfig.min_chroma_correlation (`chroma`, `_chroma_at`'s; None: not measured, nothing concluded)."""
        return chroma is not None and chroma < self.config.match.min_chroma_correlation

    def _chroma_doubtful(self, chroma: float | None) -> bool:
        """Whether the frame's colours at a pose follow the map's too weakly to leave the label-free search's next
        leaves unlooked at (MatchConfig.second_look_chroma, and below min_chroma_correlation in any case)."""
        mc = self.config.match
        return chroma is not None and chroma < max(mc.second_look_chroma, mc.min_chroma_correlation)

    def _chroma_at(self, scan: Scan, T_map_camera: np.ndarray, center_camera: np.ndarray) -> float | None:
        """`RefineMap.chroma_correlation` of the frame's fit sample placed by a pose, within the refinement's inlier
        distance, on the map of the pose's region."""
        return self.maps_at(T_map_camera, center_camera).refine_map.chroma_correlation(
            transform_points(T_map_camera, scan.fit_xyz), scan.fit_rgb, inlier_m=self.config.refine.inlier_m,
            min_std=self.config.match.chroma_min_std, frame_in_colour=scan.in_colour)

    def _second_look(self, scan: Scan, candidates: list[Candidate], choice: Choice, method: str,
                     diag: Diagnostics) -> tuple[list[Candidate], Choice]:
        """The refined answer's colours follow the map's weakly or not at all (`_chroma_doubtful`): the shape may fit
        another place. The label-free search's reserve leaves at which the frame's colours do follow the map's
        (`_leaves_in_the_frames_colours`) join the candidates, and the refine stage runs again over them all (the
        doubted answer among them: it may still win, and `_result` then claims it unless `_chroma_rules_out`). A
        close view of a door in a corner of scene0470, at a robot's height, fit a white corner 2.1 m away best (leaf
        score 0.94); the true corner's leaf ranked 17th, and polished it fit better (0.97), its chroma correlating
        0.97. Two views of bare walls at a robot's height, answered `ok` 1.2 m / 91° and 2.8 m / 174° off at chroma
        0.46 and 0.28, had their true poses among the next leaves (then 0.95 and 0.92)."""
        leaves = self._leaves_in_the_frames_colours(scan)
        if leaves is None:
            return candidates, choice
        source = self._coarse_source(scan)
        more, kept = self._new_places(self._align(leaves, source, scan, origin="fallback:bbs"), candidates,
                                      choice.outcome.T_map_camera)
        if not more:
            return candidates, choice
        diag.notes.append(f"the answer's colours follow the map's weakly there (chroma {choice.chroma:.2f}): {len(more)} "
                          "more leaves of the label-free search, where they follow them, refined too")
        candidates = sorted(kept + more, key=lambda c: -c.score)
        return candidates, self._refine(scan, candidates, method, diag)

    def _new_places(self, leaves: list[Candidate], candidates: list[Candidate],
                    T_answer: np.ndarray) -> tuple[list[Candidate], list[Candidate]]:
        """(the aligned leaves of the second look that bring a place the candidates do not, the candidates they do not
        replace). A leaf at the answer's refined pose brings nothing; one distinct from every candidate is new; one
        not distinct from some is new when it scores higher than each of them (a closer start), which it replaces, so
        that the two do not take two of the refine stage's contenders. A rival whose coarse pose the frame sees
        through is never refined (`refine_stage.HOPELESS_SEE_THROUGH`): at a robot's height, a view of two chairs
        before a wall had its true place among the candidates 22 cm off, seen through and passed by, and the leaf 5 cm
        off that the second look found was dropped as the same place; the answer went 1.4 m and 85° off (`ok`,
        confidence 0.93)."""
        leaves = self._apart_from(leaves, [T_answer])
        if not leaves or not candidates:
            return leaves, candidates
        scores = np.array([k.score for k in candidates])
        same = ~self._distinct_pairs(np.array([c.T_map_camera for c in leaves]),
                                     np.array([k.T_map_camera for k in candidates]))
        new = np.array([not s.any() or c.score > scores[s].max() for c, s in zip(leaves, same)])
        replaced = same[new].any(axis=0)
        return ([c for c, n in zip(leaves, new) if n],
                [k for k, r in zip(candidates, replaced) if not r])

    def _weak_after_a_cut_search(self, scan: Scan, choice: Choice) -> bool:
        """In a building: the label-free search searched the graph's candidate rooms only, or stopped at its node cap
        with few nodes a room, and the answer, which lies on the map (RefineConfig.min_fitness), shows the frame
        along its rays less than `Scan.deeper_below` (RegionConfig.deeper_view_agreement after a cut search, whose
        comment gives the figures behind it): the search may have passed the frame's pose by. On the 100-room
        benchmark the right answers showed the frame 0.62 or more; the three unique views without labels
        that the search missed, 0.40-0.58 at the poses it found, and the one with labels that the graph's rooms did
        not hold, 0.49. In a 30-room building with moved furniture a labelled view of two chairs over a low wall,
        whose graph's best (two chairs matched) showed it 0.34, was answered `ok` at 0.62 in one of the graph's
        four rooms, 8 m off: the true room, which the graph had not named, shows it 0.76. An answer off the map is
        looked at again too when the refine stage left the copies of its view to the deeper search
        (`Scan.copies_wait`): they were the other way to a better one."""
        return (choice.view_agreement is not None and choice.view_agreement < scan.deeper_below
                and (choice.fitness >= self.config.refine.min_fitness or scan.copies_wait))

    def _deeper_look(self, scan: Scan, candidates: list[Candidate], choice: Choice, method: str,
                     diag: Diagnostics) -> tuple[list[Candidate], Choice]:
        """The label-free search run again (`_weak_after_a_cut_search`) over the whole building, or the client's
        search region, with DEEPER_SEARCH_NODES times the nodes (and, where the rooms face their own ways, a second
        such search over each room's own yaws, `FallbackStage._yaws`): its leaves not among the candidates join them,
        and the refine stage runs again over them all (the weak answer among them: it may still win)."""
        scan.deeper_below = 0.0
        # The rooms the cut search left unverified were tied with its weak best; the deeper search ranks the rooms
        # again, and those it leaves unverified are tied with its own best.
        scan.unverified = [h for h in scan.unverified if h.source != BBS_UNVERIFIED]
        # Over the whole building (or the client's search region): the graph's candidate rooms were searched already.
        searches = [self._label_free(scan, diag.notes, [], deeper=True)]
        if self.rooms_face_their_own_ways():
            searches.append(self._label_free(scan, diag.notes, [], deeper=True, own_yaws=True))
        found = _leaves_of(searches)
        if found is None:
            return candidates, choice
        found = self._within_search(found, scan)
        # A leaf joins unless a candidate stands at its pose (within the refinement's reach): one at its place but
        # a few decimetres off is what the cut search found there, and `_one_per_place` keeps the better.
        aligned = self._align(found, self._coarse_source(scan), scan, origin="fallback:bbs")
        known = np.array([k.T_map_camera for k in candidates]).reshape(-1, 4, 4)
        apart = distinct_pairs(np.array([c.T_map_camera for c in aligned]).reshape(-1, 4, 4), known,
                               min_translation_m=NEAR_REACH_M, min_rotation_deg=NEAR_REACH_DEG).all(axis=1)
        more = [c for c, keep in zip(aligned, apart) if keep]
        if not more:
            return candidates, choice
        diag.notes.append(f"the answer showed the frame {choice.view_agreement:.2f} along its rays after a cut "
                          f"search: {len(more)} leaves of a search of the building {DEEPER_SEARCH_NODES} times as "
                          "deep refined too")
        candidates = self._one_per_place(scan, sorted(candidates + more, key=lambda c: -c.score))
        return candidates, self._refine(scan, candidates, method, diag)

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
        reach = ((self.config.label_free.voxel_m, LEAF_ALIGN_LAST_REACH_M) if origin == "fallback:bbs"
                 else FIELD_ALIGN_REACH_M)
        R, t = align_on_field(self.field, scan.score_xyz, hyp.R, hyp.t, up=None if scan.floor is None else self.up,
                              iterations=FIELD_ALIGN_ITERATIONS, reach_m=reach)
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

    def _apart_from(self, items: list, others: list[np.ndarray]) -> list:
        """The items (each with its `T_map_camera`: candidates, hypotheses, refined entries), in order, whose pose is
        distinct from every one of `others` ((4, 4) each)."""
        keep = self._distinct_from_all([x.T_map_camera for x in items], others)
        return [x for x, k in zip(items, keep) if k]


def _leaves_of(searches: list[Hypotheses | None]) -> Hypotheses | None:
    """The label-free searches' leaves (`FallbackStage._label_free`) in one set, their scores kept; None when none
    found any."""
    parts = [h for h in searches if h is not None and len(h)]
    if not parts:
        return None
    out = Hypotheses.concat(parts)
    out.geometric = np.concatenate([h.geometric for h in parts])
    return out


def _centroid(xyz: np.ndarray) -> np.ndarray:
    """(3,) the mean of the points xyz (n, 3): the column sums in one pass over the rows, as numpy's mean over axis 0
    sums them (the same value), which took 0.9 ms of a frame's 55 k points."""
    return np.einsum("ij->j", xyz) / len(xyz)


def _region_sample(site: Site, region: Region, count: int) -> np.ndarray:
    """(m, 3) points of `region`'s own, count <= m < 2 count (all of them when it has fewer): the enhanced map's
    rows of it, evenly strided; map frame."""
    start, stop = region.map_range
    step = max(1, (stop - start) // count)
    xyz = np.asarray(site.map.points[start:stop:step], dtype=np.float64)
    site.release("map", slice(start, stop))
    return xyz


def _surface_sample(site: Site, maps: RegionMaps) -> PointSet:
    """The map points the site-wide up direction and floor height are measured on: all of a one-room site; in a
    building its largest region (its rooms share the floor), so that loading a building does not read all of it.
    (A building's wall directions are its kinds of region's: `Localizer._building_wall_directions`.)"""
    if len(maps) == 1:
        return site.cloud("both")
    largest = max(maps.regions, key=lambda r: r.points)
    return region_cloud(site, largest, "both")
