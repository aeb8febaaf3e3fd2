"""Geometric global registration for frames the graph cannot place (no labels, too few objects, no match).

`floor_grid_search`: with the up direction and the camera height known from a visible floor, only (x, y, yaw)
remain; they are searched exhaustively on a grid over the map's footprint, scored on the distance field.
`FpfhRansac`: Open3D FPFH features + RANSAC + point-to-plane ICP on the whole map with no initial guess (the
baseline, and the last resort when there is no up direction).
`KissMatcher`: the KISS-Matcher global registration (pip `kiss-matcher`, the optional extra `cadreg[kiss]`) + the
same point-to-plane ICP: the bench's peer.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidArgument
from .match import Hypotheses, yaw_rotations
from .points import VOXEL_GROWTH
from .score import DistanceField


def floor_grid_search(field: DistanceField, points_level: np.ndarray, up: np.ndarray, camera_up_m: float, *,
                      step_m: float = 0.2, yaw_step_deg: float = 10.0, keep: int = 200,
                      min_clearance_m: float = 0.15, tau_m: float = 0.15, R_level: np.ndarray | None = None) -> Hypotheses:
    """3-DoF search over camera positions (x, y at the floor-given height) and yaws.

    points_level : (m, 3) frame points rotated so that the camera's up is `up` (R_level @ p_camera).
    camera_up_m : camera centre's coordinate along `up`, map frame. Positions closer than `min_clearance_m` to
    the map are skipped (a camera is not inside a wall). Returns the `keep` best hypotheses (R includes R_level).
    """
    lo = field.origin
    hi = field.origin + field.dims * field.voxel_m
    # Two horizontal axes orthogonal to up.
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 1e-3:
        e1 = np.cross(up, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    a = corners @ e1
    b = corners @ e2
    ga, gb = np.meshgrid(np.arange(a.min(), a.max(), step_m), np.arange(b.min(), b.max(), step_m), indexing="ij")
    pos = ga.reshape(-1, 1) * e1 + gb.reshape(-1, 1) * e2 + camera_up_m * up
    pos = pos[field.lookup(pos) >= min_clearance_m]
    # Positions outside the map's grid read the truncation distance: drop those far outside the footprint.
    ijk = np.floor((pos - field.origin) / field.voxel_m)
    pos = pos[np.all((ijk >= 0) & (ijk < field.dims), axis=1)]
    if len(pos) == 0:
        return Hypotheses.empty()
    yaws = np.radians(np.arange(0.0, 360.0, yaw_step_deg))
    Ryaw = yaw_rotations(up, yaws)
    rotated = np.einsum("yij,mj->ymi", Ryaw, points_level)  # (y, m, 3)
    scores = np.empty((len(yaws), len(pos)))
    for k in range(len(yaws)):
        d = field.lookup(rotated[k][None, :, :] + pos[:, None, :])
        scores[k] = np.clip(1.0 - (d / tau_m) ** 2, 0.0, 1.0).mean(axis=1)
    flat = np.argsort(scores.ravel())[::-1][:keep]
    yi, pi = np.unravel_index(flat, scores.shape)
    R = Ryaw[yi]
    if R_level is not None:
        R = R @ R_level
    hyp = Hypotheses(R, pos[pi], np.stack([np.full(len(pi), -1), np.full(len(pi), -1)], axis=1))
    hyp.geometric = scores[yi, pi]
    return hyp


class FpfhRansac:
    """Open3D FPFH + RANSAC + ICP against the whole map; the map's features are computed once."""

    def __init__(self, map_xyz: np.ndarray, *, voxel_m: float = 0.05, seed: int = 0) -> None:
        import open3d as o3d

        self.voxel_m = voxel_m
        self.seed = seed
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(map_xyz, dtype=np.float64)))
        self.target = pcd.voxel_down_sample(voxel_m)
        self.target_fpfh = self._features(self.target)

    def _features(self, pcd):
        import open3d as o3d

        v = self.voxel_m
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        return o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=100))

    def register(self, xyz_camera: np.ndarray, *, max_iterations: int = 100000, confidence: float = 0.999,
                 max_points: int | None = None) -> tuple[np.ndarray, float]:
        """(T_map_camera (4, 4), ICP fitness) for frame points (m, 3) in the camera frame. max_points: the frame is
        described and matched on voxels of voxel_m, or of the coarser voxel that leaves at most this many (the
        features, RANSAC and the ICP cost grow with them): real frames have 2-11 k at 5 cm (RedKitchen, 3DMatch), a
        depth image of noise (a hostile client's) filled 60 k over its whole frustum and took 5.4 s (180 k, 21 s at
        1280 x 960). A coarser grid, not a random subset: a subset of 2 k of a 3DMatch frame's 11 k voxels left each
        point two neighbours for its normal, and frames found at 1 cm went 1.8-6.8 m off. None: no bound."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        o3d.utility.random.seed(self.seed)
        v = self.voxel_m
        frame = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz_camera, dtype=np.float64)))
        src, voxel = frame.voxel_down_sample(v), v
        while max_points is not None and len(src.points) > max_points:
            voxel *= VOXEL_GROWTH
            src = frame.voxel_down_sample(voxel)
        fpfh = self._features(src)
        # Open3D warns on stderr when the mutual filter leaves few correspondences (a frame unlike the map): a
        # service's console is no place for it, and the answer's fitness says as much.
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            res = reg.registration_ransac_based_on_feature_matching(
                src, self.target, fpfh, self.target_fpfh, True, 1.5 * v,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
                reg.RANSACConvergenceCriteria(max_iterations, confidence))
        return self.polish(src, np.asarray(res.transformation))

    def polish(self, src, T_map_camera: np.ndarray) -> tuple[np.ndarray, float]:
        """Point-to-plane ICP of a down-sampled Open3D cloud from a coarse pose: (T_map_camera, ICP fitness). The
        one refinement of both baselines, so that they differ only in their coarse stage."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        icp = reg.registration_icp(src, self.target, 0.4 * self.voxel_m * 2, T_map_camera,
                                   reg.TransformationEstimationPointToPlane())
        return np.asarray(icp.transformation), float(icp.fitness)


KISS_HINT = 'the kiss-matcher method needs the optional extra: pip install "cadreg[kiss]" (or pip install kiss-matcher)'


class KissMatcher:
    """KISS-Matcher (Lim et al. 2025: faster-PFH, graph-theoretic outlier pruning, GNC-TLS) + the ICP of
    `FpfhRansac.polish`, against the whole map with no initial guess. The map is down-sampled once; KISS-Matcher's
    Python API takes both clouds on each call, so it describes the map again every frame (its own cost, kept)."""

    def __init__(self, fpfh: FpfhRansac) -> None:
        try:
            import kiss_matcher
        except ImportError as exc:
            raise InvalidArgument(KISS_HINT) from exc
        self._km = kiss_matcher
        self.fpfh = fpfh
        self.target_xyz = np.asarray(fpfh.target.points, dtype=np.float32)

    def register(self, xyz_camera: np.ndarray) -> tuple[np.ndarray, float]:
        """(T_map_camera (4, 4), ICP fitness) for frame points (m, 3) in the camera frame."""
        import open3d as o3d

        v = self.fpfh.voxel_m
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz_camera, dtype=np.float64))).voxel_down_sample(v)
        src.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        matcher = self._km.KISSMatcher(self._km.KISSMatcherConfig(v))
        sol = matcher.estimate(np.asarray(src.points, dtype=np.float32), self.target_xyz)
        T = np.eye(4)
        if sol.valid:
            T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64)
            T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).ravel()
        return self.fpfh.polish(src, T)
