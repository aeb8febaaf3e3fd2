"""Fine refinement (paper §2.5): frame points against the map around the coarse hypothesis.

The whole T_init is kept (the paper keeps only its translation). Three methods share one interface:
`color_gicp` (hand-written colour-supported GICP, `color_gicp.py`), `small_gicp` (GICP, the map preprocessed once)
and `open3d_colored_icp` (Open3D's coloured ICP, for comparison). All search structures are built once per site.
In a building, `small_gicp` runs the same GICP written over the region map's fitness grid (`grid_gicp.py`, reported
as `grid_gicp`) until a region has served enough refinements to pay for small_gicp's whole target (a small_gicp
target per region and frame cost more than the rest of the refinement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp

from ..config import REFINE_METHODS
from ..errors import InvalidArgument
from ..geometry import transform_points
from .color_gicp import ColorGicpTarget, color_gicp, linear_to_lab, prepare_cloud, rgb_to_lab, srgb_to_linear
from .grid_gicp import MapNormals, gicp, plane_normals
from .point_tree import PointTree, tree_order
from .points import FramePoints, voxel_indices

# A correlation of fewer colour pairs than this says little (a pose that leaves most of the frame off the map is
# judged by its fitness, not by its colours).
MIN_COLOR_PAIRS = 50

# Neighbours of each point's covariance in GICP: small_gicp's default, for the map's side and the frame's alike.
GICP_NEIGHBORS = 10
# The map's grid for fitness and agreement (`RefineMap.fit_xyz`): one map point per voxel of this size.
FITNESS_VOXEL_M = 0.02
# Fewer frame points than this inside the ROI cannot carry a GICP: refine with the whole frame instead.
MIN_ROI_POINTS = 100
# GICP's passes: correspondences this many times RefineConfig.max_correspondence_m (pulling in a start some
# centimetres off), then that distance (keeping stray points out of the final estimate). The wide pass pairs each
# frame point with the map's Gaussian of the voxel it falls in (VGICP, RefineConfig.wide_voxel_m), not with its
# nearest map point: a hash look-up instead of a KD-tree walk, a tenth of GICP's cost an iteration on 7-Scenes, where
# a wrong contender's start spends its whole budget (18 ms a refinement, most of a slow frame). The narrow pass,
# GICP, gives the pose as before. On every set (7-Scenes both ways, scene0470, Replica, 3DMatch) no answer got
# worse: RedKitchen p99 129 -> 85 and 120 -> 93 ms, two wrong `ok` answers right (`README.md`, fourteenth session).
WIDE_PASS = 2.5
# small_gicp's KD-tree finds the nearest map point of a frame point far from every map point (a part of the frame
# the map never saw, a hypothesis metres off) by visiting most of the tree: a 3DMatch frame's 1438 refinement
# points, 60 % of them over 0.5 m from a one-frame map, took 230 ms a pass instead of 6. A point farther than the
# wide pass's reach plus this from the map at the start pairs with nothing in either pass unless the pose moves
# that far, and is left out (the result is the same: same iterations, same inliers).
REACH_MARGIN_M = 0.25


def chroma_spread(rgb: np.ndarray) -> float:
    """How widely colours ((n, 3) sRGB in [0, 1]) spread in chroma: the root of the variances of their CIE a* and b*
    summed (0 for a grey picture; a colour camera's view of a grey room 2 or more, of a furnished one 10-20)."""
    return float(np.sqrt(np.sum(np.var(rgb_to_lab(rgb)[:, 1:], axis=0)))) if len(rgb) else 0.0


def chroma_correlation(frame_rgb: np.ndarray, map_rgb: np.ndarray, min_std: float, *,
                       frame_in_colour: bool = False) -> float | None:
    """The correlation of a frame's chroma with the map's at the same points ((n, 3) sRGB in [0, 1] each): the
    frame's white balance matched to the map's first (a gain per channel, in linear light, least squares), then of
    the CIE (a*, b*) vectors about their means, Σ (f − f̄)·(m − m̄) / √(Σ |f − f̄|² · Σ |m − m̄|²); None when the
    map's chroma spreads less than `min_std` (the root of the two axes' variances) there, or the frame's does and
    the frame has no colour elsewhere either (`frame_in_colour` False: a camera without colour, a grey view).
    A correlation, not a colour distance: exposure and the camera's tone curve scale and bend the chroma axes, and
    the map's colours were fused from other frames (or another sensor). A white balance off by a gain per channel
    tints each surface by as much as it is bright, and the shading of a grey room then reads as chroma the map does
    not have: matched first (renders of scene0470 with each channel's gain off by up to 25 %, tone curve, blur,
    noise and colour 6 px off the depth: right poses below 0.25, 16 % -> 3 %). One correlation of both axes, not one
    an axis: an axis along which one side barely varies weighs as little as it varies.
    A frame in colour that is grey where the map is coloured has its spread taken as `min_std` (the correlation is
    then that of the map's chroma with the frame's noise, near 0): the colours do not follow the map's. Frames of
    other rooms placed in a one-room map by their shape alone were answered `ok` there (confidence 0.71-0.90, a
    render of Replica office0 in the 7-Scenes kitchen 3.3 m off): at their poses the frame's chroma spread 0.6-2.8,
    the map's 5-15; at right poses the two spread alike (both 1.4-2.9 on Replica office0's grey walls).
    Not handled: balanced to the map, a grey frame takes on the gains' tint in proportion to each point's brightness,
    and against a map whose coloured surfaces are brighter than its grey ones that tint correlates with them (0.9
    in a made-up case). Judging greyness by the frame's colours as the camera saw them instead cost a right answer
    under a camera's colour faults (its chroma spread 2.8 as seen, 18.5 balanced) and gained a wrong `ok` among
    frames of another room."""
    f_lin, m_lin = srgb_to_linear(frame_rgb), srgb_to_linear(map_rgb)
    gain = np.sum(f_lin * m_lin, axis=0) / np.maximum(np.sum(m_lin * m_lin, axis=0), 1e-12)
    f = linear_to_lab(f_lin / np.maximum(gain, 1e-6))[:, 1:]
    m = linear_to_lab(m_lin)[:, 1:]
    f, m = f - f.mean(axis=0), m - m.mean(axis=0)
    f_var, m_var, least = float(np.sum(f * f)), float(np.sum(m * m)), len(f) * min_std ** 2
    if m_var < least or (f_var < least and not frame_in_colour):
        return None
    denominator = np.sqrt(max(f_var, least) * m_var)
    return float(np.sum(f * m) / denominator) if denominator > 0.0 else None


def crop_to_roi(points: FramePoints, radius_m: float,
                center_camera: np.ndarray | None = None) -> tuple[FramePoints, np.ndarray]:
    """The frame points within `radius_m` of `center_camera` (default: their centroid; the whole frame when fewer
    than MIN_ROI_POINTS are), and that centre (colour-camera frame): the region of interest of paper §2.5 as seen
    from the frame."""
    if center_camera is None:
        center_camera = points.xyz.mean(axis=0)
    in_roi = np.flatnonzero(np.linalg.norm(points.xyz - center_camera, axis=1) <= radius_m)
    return (points.subset(in_roi) if len(in_roi) >= MIN_ROI_POINTS else points), center_camera


@dataclass
class RefineOutcome:
    """T_map_camera : (4, 4); covariance : (6, 6) over (rx, ry, rz, tx, ty, tz), rad² / m², or None."""

    T_map_camera: np.ndarray
    covariance: np.ndarray | None
    iterations: int
    converged: bool
    method: str


def covariance_from_hessian(H: np.ndarray, error: float, inliers: int, *,
                            residuals_per_inlier: int = 3) -> np.ndarray | None:
    """Pose covariance ≈ σ²·H⁻¹ with σ² the residual per degree of freedom (Gauss-Newton at the optimum).

    residuals_per_inlier : 3 for GICP (a 3-D residual per pair), 1 for point-to-plane ICP."""
    if inliers <= 6 or not np.all(np.isfinite(H)):
        return None
    try:
        cov = np.linalg.inv(H) * (error / max(inliers * residuals_per_inlier - 6, 1))
    except np.linalg.LinAlgError:
        return None
    return 0.5 * (cov + cov.T)


class RefineMap:
    """The map as the refinement sees it (map frame, metres).

    xyz : (n, 3) float; rgb : (n, 3) float in [0, 1], or uint8 in 0-255 (a stored region grid's: converted only
    where read, `rgb_at`: a building's refinements read the colours of a few hundred of its 150-200 k points, and
    converting them all took 1-2 ms of each region map). gridded : the points are one per fitness_voxel_m voxel
    already.
    tree_ordered : gridded points in the order of their KD-tree (`point_tree.tree_order`: a building's stored
    region grid), so that the tree is read, not built. stored_target : a building's region map; its GICP pairs the
    frame with the fitness grid through the fitness KD-tree (`grid_gicp.py`), whatever the map served before.
    """

    def __init__(self, xyz: np.ndarray, rgb: np.ndarray, class_index: np.ndarray | None = None, *, fine_voxel_m: float = 0.025, coarse_voxel_m: float = 0.08,
                 color_scales_m: tuple[float, ...] = (0.08, 0.04, 0.02), color_weight_m: float = 0.05,
                 fitness_voxel_m: float = FITNESS_VOXEL_M, stored_target: bool = False, gridded: bool = False,
                 tree_ordered: bool = False, normals: np.ndarray | None = None) -> None:
        self.xyz = np.asarray(xyz, dtype=np.float64)
        rgb = np.asarray(rgb)
        self._rgb_bytes = rgb if rgb.dtype == np.uint8 else None
        self._rgb = None if self._rgb_bytes is not None else np.asarray(rgb, dtype=np.float64)
        self.fine_voxel_m = fine_voxel_m
        self.coarse_voxel_m = coarse_voxel_m
        self.color_scales_m = tuple(color_scales_m)
        self.color_weight_m = color_weight_m
        # The fine target costs most of a map's build and only the refinement of the best poses uses it: built on
        # first use (`fine_target`), so that verifying a hypothesis in another room of a building stays cheap.
        self._sg_fine: tuple[small_gicp.PointCloud, small_gicp.KdTree] | None = None
        # The wide pass's voxels of the fine target, by voxel size (`wide_voxels`).
        self._sg_wide: dict[float, small_gicp.GaussianVoxelMap] = {}
        # The coarse target likewise: a building's candidates are aligned on its distance field, not here.
        self._sg_coarse: tuple[small_gicp.PointCloud, small_gicp.KdTree] | None = None
        # The fitness grid, in the order of its KD-tree (`point_tree.py`): one map point per fitness voxel, where the
        # points are not that already (a building's region grid is, and is not copied: a building makes a region map
        # for each room it refines in), put in tree order unless they come in it (a stored region grid does).
        if gridded and tree_ordered:
            keep = slice(None)
        else:
            keep = np.arange(len(self.xyz)) if gridded else voxel_indices(self.xyz, fitness_voxel_m)
            keep = keep[tree_order(self.xyz[keep])]
        self.fit_xyz = self.xyz[keep]
        self._fit_keep = keep
        self._fit_lab: np.ndarray | None = None  # CIE Lab of fit_xyz, made on first use (`fit_lab`)
        self.fit_cls = (np.full(len(self.fit_xyz), -1, dtype=np.int64) if class_index is None
                        else np.asarray(class_index, dtype=np.int64)[keep])
        self.has_classes = bool(np.any(self.fit_cls >= 0))  # a map fused without labels has none (`agreement`)
        # The scan's own surface normals of fit_xyz, facing the side it was scanned from, or None (`seen_from_behind`)
        self.fit_normals = None if normals is None else np.asarray(normals, dtype=np.float64)[keep]
        # The nearest neighbours of `fitness`, `agreement` and the grid GICP, bounded by a distance: for points off
        # the map (a wrong hypothesis, a frame looking past the map's edge) small_gicp's unbounded search took 30 ms
        # for 1000 points where a bounded one takes 0.8.
        self.fit_tree = PointTree(self.fit_xyz)
        # A building's region map often serves a few refinements before its cache drops it: its GICP normals are
        # made for the points those pair with, not for the whole map (`grid_gicp.py`).
        self.stored_target = stored_target
        self.normals = MapNormals(self.fit_xyz, self.fit_tree, GICP_NEIGHBORS) if stored_target else None
        self._color_targets: list[ColorGicpTarget] | None = None
        self._o3d_targets: list | None = None

    # -- structures built on first use of a method ---------------------------------------------------------------
    @property
    def rgb(self) -> np.ndarray:
        """(n, 3) float64 colours in [0, 1] of xyz."""
        if self._rgb is None:
            self._rgb = self._rgb_bytes / 255.0
        return self._rgb

    def rgb_at(self, index: np.ndarray) -> np.ndarray:
        """(m, 3) float64 colours in [0, 1] of xyz[index]: the same values as `rgb[index]`."""
        if self._rgb is None:
            return self._rgb_bytes[index] / 255.0
        return self._rgb[index]

    @property
    def fit_lab(self) -> np.ndarray:
        """(m, 3) CIE Lab colours of fit_xyz: only the agreement score reads them (a building's candidates are
        scored along the frame's rays instead), and the conversion took 15-35 ms of a 100-room building's region map
        (70-120 ms before its GICP targets)."""
        if self._fit_lab is None:
            self._fit_lab = rgb_to_lab(self.rgb_at(self._fit_keep))
        return self._fit_lab

    def fine_target(self) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
        """small_gicp's map at fine_voxel_m and its KD-tree."""
        if self._sg_fine is None:
            self._sg_fine = small_gicp.preprocess_points(self.xyz, self.fine_voxel_m, num_neighbors=GICP_NEIGHBORS)
        return self._sg_fine

    def wide_voxels(self, leaf_m: float) -> small_gicp.GaussianVoxelMap:
        """small_gicp's map as Gaussians of `leaf_m` voxels (its fine target's points and covariances), for the wide
        pass's VGICP; one per voxel size, made on first use."""
        leaf_m = float(leaf_m)
        if leaf_m not in self._sg_wide:
            voxels = small_gicp.GaussianVoxelMap(leaf_m)
            voxels.insert(self.fine_target()[0])
            self._sg_wide[leaf_m] = voxels
        return self._sg_wide[leaf_m]

    def coarse_target(self) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
        """small_gicp's map at coarse_voxel_m and its KD-tree."""
        if self._sg_coarse is None:
            self._sg_coarse = small_gicp.preprocess_points(self.xyz, self.coarse_voxel_m, num_neighbors=GICP_NEIGHBORS)
        return self._sg_coarse

    def color_targets(self) -> list[ColorGicpTarget]:
        if self._color_targets is None:
            self._color_targets = [ColorGicpTarget(prepare_cloud(self.xyz, self.rgb, v), self.color_weight_m)
                                   for v in self.color_scales_m]
        return self._color_targets

    def o3d_targets(self) -> list:
        if self._o3d_targets is None:
            import open3d as o3d

            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.xyz))
            pcd.colors = o3d.utility.Vector3dVector(self.rgb)
            self._o3d_targets = []
            for v in self.color_scales_m:
                down = pcd.voxel_down_sample(v)
                down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
                self._o3d_targets.append(down)
        return self._o3d_targets

    # -- queries ----------------------------------------------------------------------------------------------
    def roi_count(self, center: np.ndarray, radius_m: float) -> int:
        """Map points (at the fitness resolution) within `radius_m` of `center`. The count alone: the list of a
        3 m ball's indices cost twenty times the count (1.6 ms of a tracked frame's 20)."""
        return self.fit_tree.count_within(center, radius_m)

    def fitness(self, xyz_map: np.ndarray, *, inlier_m: float = 0.05) -> tuple[float, float]:
        """(fraction of points within inlier_m of the map, RMSE of those, metres); xyz_map (n, 3) map frame."""
        if len(xyz_map) == 0:
            return 0.0, 0.0
        d, _ = self.fit_tree.query(xyz_map, k=1, distance_upper_bound=inlier_m)
        ok = np.isfinite(d)
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0
        return float(ok.mean()), rmse

    def seen_from_behind(self, xyz_map: np.ndarray, camera_xyz: np.ndarray, *, inlier_m: float = 0.05,
                         min_cos: float = 0.2) -> float | None:
        """Share of the points within inlier_m of the map (xyz_map (n, 3), map frame) whose nearest map point's normal
        faces away from the camera at camera_xyz ((3,), map frame) by more than min_cos: surfaces a sensor there sees
        from behind. None without the map's normals (a composed building's: see `regions.build_index`) or with no
        point on the map."""
        if self.fit_normals is None or len(xyz_map) == 0:
            return None
        d, i = self.fit_tree.query(xyz_map, k=1, distance_upper_bound=inlier_m)
        on = np.isfinite(d)
        if not on.any():
            return None
        rays = xyz_map[on] - np.asarray(camera_xyz, dtype=np.float64)
        facing = np.einsum("ij,ij->i", self.fit_normals[i[on]], rays) / np.maximum(np.linalg.norm(rays, axis=1), 1e-9)
        return float(np.mean(facing > min_cos))

    def agreement(self, xyz_map: np.ndarray, lab: np.ndarray, cls: np.ndarray | None, *, inlier_m: float = 0.05,
                  color_scale: float = 25.0) -> tuple[float, float, float]:
        """(geometric fitness, semantic agreement, colour agreement) of frame points placed in the map.

        xyz_map (n, 3) map frame; lab (n, 3) CIE Lab colours (`rgb_to_lab`: converted once per frame, not per
        hypothesis); cls (n,) class index, -1 none (a labelled point of no class the site knows: a wall), or None
        for a frame without labels.
        Semantic: among inliers where the frame or the map has an object class, the fraction whose classes agree
        (1 when there is none, and when either side has no labels at all: a frame without labels, or a map fused
        without them, says nothing of classes, and counting its points as "no class" put every pose that lays the
        frame on objects below every pose that lays it on walls; on the 1-room benchmark without labels the right
        pose ranked third at half the score of wrong ones in 6 of its 10 failures). Colour: mean
        exp(-(ΔE / color_scale)²) over inliers (CIE76 ΔE).
        """
        if len(xyz_map) == 0:
            return 0.0, 0.0, 0.0
        d, nn = self.fit_tree.query(xyz_map, k=1, distance_upper_bound=inlier_m)
        ok = np.isfinite(d)
        if not ok.any():
            return 0.0, 0.0, 0.0
        nn = nn[ok]
        sem = 1.0
        if cls is not None and self.has_classes:
            fc, mc = cls[ok], self.fit_cls[nn]
            either = (fc >= 0) | (mc >= 0)
            sem = float((fc[either] == mc[either]).mean()) if either.sum() >= 10 else 1.0
        dE = np.linalg.norm(lab[ok] - self.fit_lab[nn], axis=1)
        col = float(np.exp(-(dE / color_scale) ** 2).mean())
        return float(ok.mean()), sem, col

    def chroma_correlation(self, xyz_map: np.ndarray, rgb: np.ndarray, *, inlier_m: float, min_std: float,
                           frame_in_colour: bool = False) -> float | None:
        """The correlation of the chroma of the frame's inliers with their map points' (`chroma_correlation`, with
        `min_std` and `frame_in_colour`); None when that is, or fewer than MIN_COLOR_PAIRS points are inliers.
        xyz_map (n, 3) frame points placed in the map; rgb (n, 3) their colours, sRGB in [0, 1] (`Scan.fit_rgb`)."""
        d, nn = self.fit_tree.query(xyz_map, k=1, distance_upper_bound=inlier_m)
        ok = np.isfinite(d)
        if ok.sum() < MIN_COLOR_PAIRS:
            return None
        nn = nn[ok]
        return chroma_correlation(rgb[ok], self.rgb_at(nn if isinstance(self._fit_keep, slice) else self._fit_keep[nn]),
                                  min_std, frame_in_colour=frame_in_colour)

    def coarse_align(self, source: small_gicp.PointCloud, init_T_map_camera: np.ndarray, *,
                     max_correspondence_m: float = 0.3, max_iterations: int = 20) -> np.ndarray:
        """A cheap GICP at the coarse scale to pull a hypothesis in before it is ranked: (4, 4) T_map_camera.

        source : frame points (colour-camera frame) preprocessed at the coarse voxel size."""
        target, tree = self.coarse_target()
        res = small_gicp.align(target, source, tree, init_T_target_source=init_T_map_camera,
                               registration_type="GICP", max_correspondence_distance=max_correspondence_m,
                               num_threads=1, max_iterations=max_iterations)
        return np.asarray(res.T_target_source)

    def refine(self, points: FramePoints, init_T_map_camera: np.ndarray, *, method: str = "small_gicp",
               epsilon: float = 1e-3, source_voxel_m: float = 0.04, max_correspondence_m: float = 0.1,
               max_iterations: int = 30, grid_max_iterations: int | None = None,
               wide_voxel_m: float = 0.1) -> RefineOutcome:
        """Refine T_map_camera from `init_T_map_camera` with the frame's points (colour-camera frame).
        max_iterations : per pass; grid_max_iterations : per pass of the GICP on a building's region map (default:
        max_iterations). wide_voxel_m : small_gicp's wide pass's voxel (`WIDE_PASS`)."""
        T_init = np.asarray(init_T_map_camera, dtype=np.float64)
        if method == "small_gicp" and self.stored_target:
            # Always on the grid, whatever the map served before: the region used to switch to small_gicp's whole
            # target once its refinements had paid for building it (or a tracked stream had built it), and the two
            # differ below a millimetre, enough to move a borderline answer's status with the frames a worker had
            # seen (10 rooms: 6 of 120 frames' confidences moved, one `ok` <-> `ambiguous`; grid only: none, the
            # same medians). A tracked stream keeps its target (`tracking.py`).
            return self._refine_on_grid(points, T_init, epsilon=epsilon, source_voxel_m=source_voxel_m,
                                        max_correspondence_m=max_correspondence_m,
                                        max_iterations=grid_max_iterations or max_iterations)
        if method == "small_gicp":
            near = self._near_map(points.xyz, T_init, WIDE_PASS * max_correspondence_m + REACH_MARGIN_M)
            if len(near) <= GICP_NEIGHBORS:  # nothing of the frame lies near the map there: no GICP can run
                return RefineOutcome(T_init, None, 0, False, method)
            src, _ = small_gicp.preprocess_points(near, source_voxel_m, num_neighbors=GICP_NEIGHBORS)
            each_pass = dict(num_threads=1, max_iterations=max_iterations, translation_epsilon=epsilon,
                             rotation_epsilon=epsilon)
            wide = small_gicp.align(self.wide_voxels(wide_voxel_m), src, init_T_target_source=T_init,
                                    max_correspondence_distance=WIDE_PASS * max_correspondence_m, **each_pass)
            target, tree = self.fine_target()
            res = small_gicp.align(target, src, tree, init_T_target_source=np.asarray(wide.T_target_source),
                                   registration_type="GICP", max_correspondence_distance=max_correspondence_m, **each_pass)
            cov = covariance_from_hessian(np.asarray(res.H), 2.0 * float(res.error), int(res.num_inliers))
            return RefineOutcome(np.asarray(res.T_target_source), cov, int(res.iterations), bool(res.converged), method)
        if method == "color_gicp":
            sources = [prepare_cloud(points.xyz, points.rgb, max(v, source_voxel_m)) for v in self.color_scales_m]
            out = color_gicp(self.color_targets(), sources, T_init, epsilon=epsilon, max_iterations=max_iterations)
            cov = covariance_from_hessian(out.H, out.error, out.inliers)
            return RefineOutcome(out.T_target_source, cov, out.iterations, out.converged, method)
        if method == "open3d_colored_icp":
            import open3d as o3d

            reg = o3d.pipelines.registration
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.xyz))
            pcd.colors = o3d.utility.Vector3dVector(points.rgb)
            T = np.asarray(T_init, dtype=np.float64)
            iterations, converged = 0, True
            for k, (v, target) in enumerate(zip(self.color_scales_m, self.o3d_targets())):
                down = pcd.voxel_down_sample(v)
                down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
                # The first scale must reach as far as the start may be off; later ones only polish.
                corr = max(max_correspondence_m, 2 * v) if k == 0 else 2 * v
                res = reg.registration_colored_icp(
                    down, target, corr, T, reg.TransformationEstimationForColoredICP(),
                    reg.ICPConvergenceCriteria(relative_fitness=epsilon, relative_rmse=epsilon, max_iteration=max_iterations))
                T = np.asarray(res.transformation)
                iterations += max_iterations
            return RefineOutcome(T, None, iterations, converged, method)
        raise InvalidArgument(f"unknown refinement method {method!r}; choose one of {REFINE_METHODS}")

    def _near_map(self, xyz_camera: np.ndarray, T_map_camera: np.ndarray, reach_m: float) -> np.ndarray:
        """The points of xyz_camera ((n, 3), camera frame) within reach_m of the map at T_map_camera."""
        d, _ = self.fit_tree.query(transform_points(T_map_camera, xyz_camera), k=1, distance_upper_bound=reach_m)
        return xyz_camera[np.isfinite(d)]

    def _refine_on_grid(self, points: FramePoints, T_init: np.ndarray, *, epsilon: float, source_voxel_m: float,
                        max_correspondence_m: float, max_iterations: int) -> RefineOutcome:
        """GICP (`grid_gicp.gicp`) of the frame's points, on small_gicp's voxel grid (means of source_voxel_m
        voxels) with their own plane covariances, onto the fitness grid: the same two passes and the same
        covariance of the pose as the small_gicp path."""
        # The tree's points are row-major (small_gicp hands its points over column-major, and the compiled loops
        # are compiled and warmed, `compile_loops`, for row-major arrays: any other layout compiles again on a
        # worker's first frame), in tree order (the GICP's sums are the same in any order, up to rounding).
        sampled = np.asarray(small_gicp.voxelgrid_sampling(points.xyz, source_voxel_m).points())[:, :3]
        src_tree, _ = PointTree.sorted(sampled)
        src = src_tree.xyz
        src_normals = plane_normals(src, src_tree, np.arange(len(src)), GICP_NEIGHBORS)
        T = T_init
        for corr in (WIDE_PASS * max_correspondence_m, max_correspondence_m):
            res = gicp(self.normals, src, src_normals, T, max_correspondence_m=corr, max_iterations=max_iterations,
                       epsilon=epsilon)
            T = res.T_target_source
        cov = covariance_from_hessian(res.H, res.error, res.inliers)
        return RefineOutcome(T, cov, res.iterations, res.converged, "grid_gicp")
