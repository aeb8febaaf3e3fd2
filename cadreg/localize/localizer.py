"""The localizer: one RGB-D frame -> T_map_camera in a site's map, with no initial guess.

Stages (DESIGN §1): frame -> points, class-wise clustering -> scan graph, up direction from a floor or the client,
coarse graph matching scored by Sim and a distance-field check, a coarse GICP that pulls the best distinct
hypotheses in before they are re-ranked, a fallback when the graph has too little to say, and fine refinement.
Everything site-dependent is built once in `from_site` and reused for every frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import small_gicp

from ..config import LocalizeConfig
from ..errors import InvalidFrame
from ..frame import Frame
from ..geometry import rotation_angle_deg, rotation_between, transform_points
from ..result import Diagnostics, Hypothesis, LocalizationResult, Match, Refinement, ScanObject, Status
from .cluster import ScanCluster, cluster_objects
from .fallback import FpfhRansac, floor_grid_search
from .gravity import Floor, estimate_floor, map_floor_height, map_up_axis
from .match import Hypotheses, MapGraph, distinct_best, gravity_hypotheses, kabsch_hypotheses, score_graph
from .points import FramePoints, frame_to_points, voxel_downsample
from .refine import REFINE_METHODS, RefineMap
from .score import DistanceField, score_poses


def _site_map(site, which: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """(xyz, rgb in [0, 1], normals, class index) of the raw scan, the enhanced map or both, map frame."""
    raw = (getattr(site, "raw_points", None), getattr(site, "raw_colors", None), getattr(site, "raw_normals", None),
           getattr(site, "raw_class_index", None))
    enh = (site.points, site.colors, getattr(site, "normals", None), getattr(site, "class_index", None))
    if which == "raw" and raw[0] is not None and len(raw[0]):
        parts = [raw]
    elif which == "both" and raw[0] is not None and len(raw[0]):
        parts = [raw, enh]
    else:
        parts = [enh]
    xyz = np.concatenate([np.asarray(p[0], dtype=np.float64) for p in parts])
    rgb = np.concatenate([np.asarray(p[1], dtype=np.float64) / 255.0 for p in parts])
    normals = None
    if all(p[2] is not None and len(p[2]) == len(p[0]) for p in parts):
        normals = np.concatenate([np.asarray(p[2], dtype=np.float64) for p in parts])
    cls = np.concatenate([np.full(len(p[0]), -1, np.int64) if p[3] is None else np.asarray(p[3], np.int64) for p in parts])
    return xyz, rgb, normals, cls


class Localizer:
    """Localize frames in one site. Build with `from_site`; `localize` is read-only and may be called repeatedly."""

    def __init__(self, site, config: LocalizeConfig, *, up: np.ndarray, floor_height_m: float, graph: MapGraph,
                 field: DistanceField, refine_map: RefineMap) -> None:
        self.site = site
        self.config = config
        self.up = up
        self.floor_height_m = floor_height_m
        self.graph = graph
        self.field = field
        self.refine_map = refine_map
        self._fpfh: FpfhRansac | None = None

    @classmethod
    def from_site(cls, site, config: LocalizeConfig = LocalizeConfig()) -> "Localizer":
        """Build every per-site search structure (distance field, small_gicp map, KD-trees) once."""
        xyz, rgb, _, map_cls = _site_map(site, config.refine.map_points)
        all_xyz, _, all_normals, _ = _site_map(site, "both")
        if getattr(site, "up", None) is not None:
            up = np.asarray(site.up, dtype=float)
        elif all_normals is not None:
            # Derived from the map's surfaces (+z for ScanNet and the demo; not for KinectFusion maps).
            up = map_up_axis(all_normals)
        else:
            up = np.array([0.0, 0.0, 1.0])
        up = up / np.linalg.norm(up)
        rc = config.refine
        return cls(
            site, config, up=up,
            floor_height_m=map_floor_height(all_xyz, all_normals, up),
            graph=MapGraph.from_site(site, up),
            field=DistanceField(all_xyz),
            refine_map=RefineMap(xyz, rgb, map_cls, fine_voxel_m=rc.fine_voxel_m, coarse_voxel_m=rc.coarse_voxel_m,
                                 color_scales_m=rc.color_scales_m, color_weight_m=rc.color_weight_m),
        )

    # ------------------------------------------------------------------------------------------------------------
    def warm(self) -> "Localizer":
        """Build now what is otherwise built on first use (the map's FPFH features for the fallback, about a second
        a site), so that a long-running server does not make its first fallback request pay for it."""
        if self.config.fallback.enabled:
            self.fpfh()
        return self

    def fpfh(self) -> FpfhRansac:
        """The FPFH + RANSAC registrar of this site (map features computed on first use)."""
        if self._fpfh is None:
            self._fpfh = FpfhRansac(self.refine_map.xyz, voxel_m=self.config.fallback.voxel_size_m)
        return self._fpfh

    def localize(self, frame: Frame, *, top_k: int | None = None, method: str | None = None,
                 progress: Callable[[int, int], None] | None = None) -> LocalizationResult:
        """Register one frame.

        top_k : hypotheses to report (default MatchConfig.top_k). method : refinement method, one of
        `REFINE_METHODS` (default RefineConfig.method). Raises InvalidFrame for frames that cannot be registered.
        """
        if not isinstance(frame, Frame):
            raise InvalidFrame(f"expected a Frame, got {type(frame).__name__}")
        frame.validate()
        method = method or self.config.refine.method
        if method not in REFINE_METHODS:
            raise ValueError(f"unknown refinement method {method!r}; choose one of {REFINE_METHODS}")
        top_k = self.config.match.top_k if top_k is None else int(top_k)
        cfg = self.config
        diag = Diagnostics(site_id=str(getattr(self.site, "site_id", "")), bundle_version=str(getattr(self.site, "version", "")))
        stage_ms = diag.stage_ms
        clock = [time.perf_counter()]

        def lap(name: str) -> None:
            now = time.perf_counter()
            stage_ms[name] = stage_ms.get(name, 0.0) + (now - clock[0]) * 1000.0
            clock[0] = now

        def step(i: int) -> None:
            if progress is not None:
                progress(i, 6)

        # 1. points ---------------------------------------------------------------------------------------------
        fc = cfg.frame
        pts = frame_to_points(frame, pixel_stride=fc.pixel_stride, min_depth_m=fc.min_depth_m, max_depth_m=fc.max_depth_m)
        if len(pts) < 100:
            raise InvalidFrame(f"only {len(pts)} valid depth points in range {fc.min_depth_m}–{fc.max_depth_m} m")
        ds = voxel_downsample(pts, fc.voxel_size_m)
        diag.frame_points = len(pts)
        lap("points"); step(1)

        # 2. scan graph ------------------------------------------------------------------------------------------
        cls_index = np.full(len(ds), -1, dtype=np.int64)
        has_label = ds.labels >= 0
        if has_label.any():
            try:
                cls_index[has_label] = np.asarray(self.site.classes_for_labels(frame.label_set, ds.labels[has_label]),
                                                  dtype=np.int64)
            except KeyError:
                diag.notes.append(f"site has no label map {frame.label_set!r}: labels ignored")
        clusters = cluster_objects(ds.xyz, cls_index, tolerance_m=cfg.cluster.tolerance_m, min_points=cfg.cluster.min_points)
        names = list(self.site.classes)
        diag.scan_objects = [ScanObject(names[c.cls], c.centroid.tolist(), len(c.index)) for c in clusters]
        lap("cluster"); step(2)

        # 3. up direction and floor ------------------------------------------------------------------------------
        floor = estimate_floor(ds.xyz, ds.labels, frame.label_set, gravity_camera=frame.gravity_camera)
        if floor is not None:
            diag.notes.append(f"up from {floor.source}" + (f", camera {floor.height_m:.2f} m above floor" if floor.height_m else ""))
        lap("gravity"); step(3)

        # 4. coarse matching ---------------------------------------------------------------------------------------
        rng = np.random.default_rng(0)
        score_pts = ds.xyz[rng.choice(len(ds), min(fc.score_points, len(ds)), replace=False)]
        hyp = self._graph_hypotheses(clusters, floor, ds.xyz)
        mc = cfg.match
        if len(hyp):
            cent = np.array([c.centroid for c in clusters])
            ccls = np.array([c.cls for c in clusters])
            # Two passes: a quick geometric screen of every hypothesis, then Sim and a finer check of the best.
            screen = score_poses(self.field, score_pts[: max(20, len(score_pts) // 3)], hyp.R, hyp.t, tau_m=mc.score_tau_m)
            hyp = hyp.take(np.argsort(-screen)[: mc.screen_keep])
            score_graph(hyp, cent, ccls, self.graph, match_radius_m=mc.match_radius_m, edge_max_m=mc.edge_max_m,
                        alpha=mc.alpha, beta=mc.beta)
            hyp.geometric = score_poses(self.field, score_pts, hyp.R, hyp.t, tau_m=mc.score_tau_m)
            rank = hyp.geometric * (1.0 - mc.sim_weight + mc.sim_weight * hyp.sim)
            keep = distinct_best(hyp.R, hyp.t, np.argsort(-rank), count=mc.candidates,
                                 min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg)
            hyp = hyp.take(np.array(keep, dtype=np.int64))
        lap("match"); step(4)

        # 5. coarse GICP on the candidates, fallback when the graph's best is weak -------------------------------
        rc = cfg.refine
        src_coarse, _ = small_gicp.preprocess_points(ds.xyz, rc.coarse_voxel_m, num_neighbors=10)
        pick = rng.choice(len(ds), min(800, len(ds)), replace=False)
        fit_pts = (ds.xyz[pick], ds.rgb[pick], cls_index[pick])
        verified = self._verify(hyp, src_coarse, fit_pts)
        if frame.T_map_camera_prior is not None:
            # A client's pose prior is one more hypothesis, checked like the others (never trusted blindly).
            P = frame.T_map_camera_prior
            verified += self._verify(Hypotheses(P[None, :3, :3].copy(), P[None, :3, 3].copy(), np.array([[-1, -1]])),
                                     src_coarse, fit_pts, source="prior")
        best_fit = max((v[1] for v in verified), default=0.0)
        lap("verify")
        if cfg.fallback.enabled and best_fit < cfg.fallback.min_graph_fitness:
            # Cheapest first: the floor-constrained grid search, then FPFH + RANSAC if that is still weak.
            for name in ("floor-grid", "fpfh-ransac"):
                fb = self._fallback(name, ds, floor, score_pts, diag.notes)
                if fb is None:
                    continue
                found = self._verify(fb, src_coarse, fit_pts, source=f"fallback:{name}")
                verified += found
                best_fit = max([best_fit] + [v[1] for v in found])
                if best_fit >= cfg.fallback.min_graph_fitness:
                    break
            lap("fallback")
        step(5)

        if not verified:
            status = Status.NO_OBJECTS if not clusters else Status.NO_MATCH
            diag.notes.append("no hypothesis: " + ("no objects in view" if not clusters else "no map node matches the scan objects"))
            return LocalizationResult(status, diagnostics=diag, frame_id=frame.frame_id)

        verified.sort(key=lambda v: -v[1])
        best = verified[0]
        runner_up = next((v for v in verified[1:] if self._distinct(v[0], best[0])), None)

        # 6. fine refinement: of the best, and of its close rivals when the coarse stage is ambiguous ---------
        contenders = [best] + [v for v in verified[1:mc.refine_contenders]
                               if best[1] - v[1] < mc.ambiguity_margin and self._distinct(v[0], best[0])]
        # Region of interest (paper §2.5, radius γ about the frame's centre under the hypothesis). The map's search
        # structures are built once per site rather than cropped per frame; leaving out the frame points farther
        # than γ from their centroid has the same effect, since correspondences are sought only a few centimetres
        # from each frame point.
        centre_camera = pts.xyz.mean(axis=0)
        in_roi = np.flatnonzero(np.linalg.norm(pts.xyz - centre_camera, axis=1) <= rc.roi_radius_m)
        roi_pts = pts.subset(in_roi) if len(in_roi) >= 100 else pts
        refined = []
        for v in contenders:
            out = self.refine_map.refine(roi_pts, v[0], method=method, epsilon=rc.epsilon, source_voxel_m=rc.source_voxel_m,
                                         max_correspondence_m=rc.max_correspondence_m, max_iterations=rc.max_iterations)
            score = self._score(out.T_map_camera, fit_pts)
            refined.append((score, out, v))
        if len(refined) > 1:
            refined.sort(key=lambda r: -r[0])
            diag.notes.append(f"refined {len(refined)} close hypotheses, scores " +
                              ", ".join(f"{r[0]:.3f}" for r in refined))
            best = refined[0][2]
            rival = refined[1]
            runner_up = (rival[1].T_map_camera, rival[0]) if self._distinct(rival[1].T_map_camera, refined[0][1].T_map_camera) else None
            best = (best[0], refined[0][0], best[2], best[3])
        out = refined[0][1]
        T = out.T_map_camera
        diag.method = "cadreg" if best[2].source == "graph" else best[2].source
        fine_pts = pts.xyz[rng.choice(len(pts), min(2000, len(pts)), replace=False)]
        fitness, rmse = self.refine_map.fitness(transform_points(T, fine_pts), inlier_m=rc.inlier_m)
        diag.refinement = Refinement(method=out.method, iterations=out.iterations, fitness=fitness, inlier_rmse_m=rmse,
                                     converged=out.converged)
        centre = transform_points(T, centre_camera[None])[0]
        diag.roi = {"center": centre.tolist(), "radius_m": rc.roi_radius_m,
                    "points": self.refine_map.roi_count(centre, rc.roi_radius_m), "frame_points": len(roi_pts)}
        if best[2].source == "graph":
            diag.matches = [Match(i, self.graph.ids[a], names[clusters[i].cls]) for i, a in enumerate(best[3]) if a >= 0]
        lap("refine"); step(6)

        hyps = [v[2] for v in verified[:top_k]]
        margin = best[1] - (runner_up[1] if runner_up else 0.0)
        ambiguous = runner_up is not None and margin < cfg.match.ambiguity_margin
        if fitness < rc.min_fitness:
            diag.notes.append(f"fitness {fitness:.2f} below {rc.min_fitness}")
            return LocalizationResult(Status.LOW_OVERLAP, None, confidence=float(fitness) * 0.5, hypotheses=hyps,
                                      diagnostics=diag, frame_id=frame.frame_id)
        # Confidence: how much of the frame lies on the map, how tightly, and how clearly the best beat the rest.
        confidence = fitness * np.exp(-(rmse / rc.inlier_m) ** 2) * min(1.0, 0.5 + margin / 0.2)
        status = Status.AMBIGUOUS if ambiguous else Status.OK
        return LocalizationResult(status, T, confidence=float(np.clip(confidence, 0.0, 1.0)), covariance=out.covariance,
                                  hypotheses=hyps, diagnostics=diag, frame_id=frame.frame_id)

    # ------------------------------------------------------------------------------------------------------------
    def _graph_hypotheses(self, clusters: list[ScanCluster], floor: Floor | None, xyz: np.ndarray) -> Hypotheses:
        if not clusters or len(self.graph.ids) == 0:
            return Hypotheses.empty()
        cent = np.array([c.centroid for c in clusters])
        ccls = np.array([c.cls for c in clusters])
        mc = self.config.match
        if floor is not None:
            R_level = rotation_between(floor.up_camera, self.up)
            cam_up = None if floor.height_m is None else self.floor_height_m + floor.height_m
            # Few objects: little to go on, so search single-object offsets densely as well.
            offset = mc.offset_step_m if len(clusters) <= mc.dense_below_objects else 0.0
            up_cam = R_level.T @ self.up
            tops = np.array([np.percentile(xyz[c.index] @ up_cam, 98) for c in clusters])
            return gravity_hypotheses(cent, ccls, self.graph, R_level=R_level, up=self.up, camera_height_m=cam_up,
                                      yaw_step_deg=mc.yaw_step_deg, pair_tolerance_m=mc.pair_tolerance_m,
                                      offset_step_m=offset, max_offset_m=mc.max_offset_m, scan_top=tops)
        if len(clusters) >= 3:
            return kabsch_hypotheses(cent, ccls, self.graph, pair_tolerance_m=mc.pair_tolerance_m)
        return Hypotheses.empty()

    def _fallback(self, name: str, ds: FramePoints, floor: Floor | None, score_pts: np.ndarray,
                  notes: list[str]) -> Hypotheses | None:
        """Hypotheses of one fallback method, or None when it cannot run (floor-grid needs up and a height) or
        found nothing the frame's up direction allows."""
        fb = self.config.fallback
        height = None if floor is None else (floor.height_m if floor.height_m is not None else floor.floor_guess_m)
        if name == "floor-grid":
            if floor is None or height is None:
                return None
            R_level = rotation_between(floor.up_camera, self.up)
            hyp = floor_grid_search(self.field, score_pts @ R_level.T, self.up, self.floor_height_m + height,
                                    step_m=fb.grid_step_m, yaw_step_deg=fb.yaw_step_deg, R_level=R_level)
            mc = self.config.match
            keep = distinct_best(hyp.R, hyp.t, np.arange(len(hyp)), count=mc.candidates,
                                 min_translation_m=mc.distinct_translation_m, min_rotation_deg=mc.distinct_rotation_deg)
            return hyp.take(np.array(keep, dtype=np.int64))
        T, _ = self.fpfh().register(ds.xyz)
        if floor is not None:
            # FPFH + RANSAC knows nothing of gravity: on a bare wall it happily returns the camera upside down.
            tilt = np.degrees(np.arccos(np.clip((T[:3, :3] @ floor.up_camera) @ self.up, -1.0, 1.0)))
            if tilt > fb.max_up_disagreement_deg:
                notes.append(f"fallback fpfh-ransac refused: its pose tilts up by {tilt:.0f}° from the {floor.source}'s")
                return None
        hyp = Hypotheses(T[None, :3, :3].copy(), T[None, :3, 3].copy(), np.array([[-1, -1]]))
        hyp.geometric = score_poses(self.field, score_pts, hyp.R, hyp.t, tau_m=self.config.match.score_tau_m)
        return hyp

    def _verify(self, hyp: Hypotheses, src_coarse, fit_pts: tuple, *, source: str = "graph") -> list:
        """[(T, score, Hypothesis, assignment)] after a coarse GICP from each hypothesis.

        fit_pts : (xyz camera frame, rgb, class index) of a sample of frame points. The score is the geometric
        fitness weighted by how well labels and colours agree with the map's there: geometry alone cannot tell
        a wall from the opposite wall or a chair seen from above turned by 90°.
        """
        out = []
        for i in range(len(hyp)):
            T = self.refine_map.coarse_align(src_coarse, hyp.T(i))
            fit = self._score(T, fit_pts)
            has = lambda a: len(a) == len(hyp)  # noqa: E731
            h = Hypothesis(T, float(hyp.sim[i]) if has(hyp.sim) else 0.0, float(hyp.s_v[i]) if has(hyp.s_v) else 0.0,
                           float(hyp.s_e[i]) if has(hyp.s_e) else 0.0, float(fit),
                           matches=[], source=source)
            assign = hyp.assignment[i] if has(hyp.assignment) else np.zeros(0, dtype=np.int64)
            h.matches = [(int(k), self.graph.ids[a]) for k, a in enumerate(assign) if a >= 0]
            out.append((T, float(fit), h, assign))
        return out

    def _score(self, T: np.ndarray, fit_pts: tuple) -> float:
        """Geometric fitness weighted by label and colour agreement of sampled frame points placed by T."""
        xyz, rgb, cls = fit_pts
        mc = self.config.match
        geo, sem, col = self.refine_map.agreement(transform_points(T, xyz), rgb, cls, inlier_m=self.config.refine.inlier_m)
        return geo * (1.0 - mc.semantic_weight + mc.semantic_weight * sem) * (1.0 - mc.color_weight + mc.color_weight * col)

    def _distinct(self, Ta: np.ndarray, Tb: np.ndarray) -> bool:
        mc = self.config.match
        return bool(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) > mc.distinct_translation_m
                    or rotation_angle_deg(Ta[:3, :3].T @ Tb[:3, :3]) > mc.distinct_rotation_deg)
