"""Maps from recorded RGB-D frames with poses: TSDF fusion (Open3D tensor VoxelBlockGrid) and label voting.

Open3D 0.20's legacy ScalableTSDFVolume returned no points on this stack (DESIGN §9); the tensor VoxelBlockGrid
works. Labels are not fused in the grid: the extracted surface points are projected into every n-th labelled frame,
and each point takes the majority of the labels it sees where its depth agrees with the frame's (occlusion check).

    fuse_frames(frames, indices, *, config, progress) -> FusedCloud (points, colors, normals, labels | None)
    fuse_site(frames, indices, *, site_id, config, build_config, progress, cad_root, auto_cad) -> Site (via
        site_from_labelled_points; with auto_cad, CAD models aligned to the voted-label instances)
    map_accuracy(map_points, frames, indices) -> distances of held-out frames' depth to the map
    pose_offset(map_points, map_normals, frames, indices) -> how far the held-out frames' recorded poses disagree
        with the map (their own fused surface registered onto it)
    pose_offset_by_window(map_points, map_normals, frames, indices, window) -> the same along a sequence, a window
        of frames at a time: which frames' recorded poses a localizer right against the map cannot match
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from ..camera import CameraIntrinsics
from ..config import AutoCadConfig, FrameConfig, FuseConfig, SiteBuildConfig
from ..errors import ConfigError
from ..frame import Frame
from ..geometry import invert_T, rotation_angle_deg, transform_points
from ..io.bundle_files import sha256_bytes, sha256_file
from ..io.frames import RecordedFrames
from ..localize.gravity import estimate_up_from_normals, map_up_axis
from ..localize.points import frame_to_points, voxel_downsample

Progress = Callable[[int, int], None]


@dataclass
class FusedCloud:
    """points (N, 3) float32 metres, map frame; colors (N, 3) uint8 RGB; normals (N, 3) float32 unit;
    labels (N,) int64 label ids in `label_set` (0 = none seen) or None when the frames carry no labels."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    labels: np.ndarray | None
    label_set: str


def _K_tensor(intr: CameraIntrinsics) -> o3c.Tensor:
    return o3c.Tensor(intr.K, dtype=o3c.float64)


def color_in_depth_camera(frame: Frame) -> np.ndarray:
    """(H, W, 3) uint8 colour sampled at each depth pixel (nearest colour pixel; black where no depth or outside).

    Needed when the colour camera differs from the depth camera: the grid integrates one registered image pair.
    """
    di, ci = frame.depth_intrinsics, frame.color_intrinsics
    z = frame.depth.astype(np.float64) / frame.depth_scale
    v, u = np.nonzero(z > 0)
    zz = z[v, u]
    p = np.stack([(u - di.cx) / di.fx * zz, (v - di.cy) / di.fy * zz, zz], axis=1)
    q = transform_points(frame.T_color_depth, p)
    out = np.zeros((di.height, di.width, 3), dtype=np.uint8)
    front = q[:, 2] > 1e-6
    uc = np.rint(q[front, 0] / q[front, 2] * ci.fx + ci.cx).astype(np.int64)
    vc = np.rint(q[front, 1] / q[front, 2] * ci.fy + ci.cy).astype(np.int64)
    inside = (uc >= 0) & (uc < ci.width) & (vc >= 0) & (vc < ci.height)
    out[v[front][inside], u[front][inside]] = frame.color[vc[inside], uc[inside]]
    return out


def fuse_frames(
    frames: RecordedFrames,
    indices: Sequence[int] | None = None,
    *,
    config: FuseConfig = FuseConfig(),
    progress: Progress | None = None,
) -> FusedCloud:
    """TSDF-fuse the frames `indices` (default all) at their poses; frames without a pose are skipped.

    Raises ConfigError when no frame has a pose or the fused surface is empty.
    """
    indices = list(frames.indices if indices is None else indices)
    posed = [(i, frames.pose(i)) for i in indices]
    posed = [(i, T) for i, T in posed if T is not None]
    if not posed:
        raise ConfigError("none of the selected frames has a pose: fusion needs T_map_camera per frame")
    use_labels = frames.has_labels()
    total = len(posed) + (len(posed[::config.label_frame_stride]) if use_labels else 0)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=config.voxel_size_m,
        block_resolution=config.block_resolution,
        block_count=config.block_count,
        device=o3c.Device("CPU:0"),
    )
    K_depth = _K_tensor(frames.depth_intrinsics)
    registered = np.allclose(frames.T_color_depth, np.eye(4)) and frames.depth_intrinsics == frames.color_intrinsics
    for k, (i, T_map_camera) in enumerate(posed):
        frame, _ = frames.load(i)
        # Poses are the colour camera's; the grid integrates in the depth camera.
        T_map_depth = T_map_camera @ frames.T_color_depth
        extrinsic = o3c.Tensor(invert_T(T_map_depth), dtype=o3c.float64)  # map -> depth camera
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(frame.depth)))
        color_np = frame.color if registered else color_in_depth_camera(frame)
        color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color_np)))
        blocks = vbg.compute_unique_block_coordinates(
            depth, K_depth, extrinsic, frames.depth_scale, config.depth_max_m, config.sdf_trunc_voxels
        )
        vbg.integrate(blocks, depth, color, K_depth, extrinsic, frames.depth_scale, config.depth_max_m,
                      config.sdf_trunc_voxels)
        if progress is not None:
            progress(k + 1, total)
    # A surface needs more than weight_threshold frames' worth of integration (Open3D's test is strict); no
    # surface of fewer frames than that (one frame of a new room) would pass, so it is kept under their number.
    pcd = vbg.extract_point_cloud(min(config.weight_threshold, len(posed) - 0.5))
    if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
        raise ConfigError("TSDF fusion produced no surface points (check poses, depth scale and depth_max_m)")
    points = pcd.point.positions.numpy().astype(np.float32)
    colors = np.clip(np.rint(pcd.point.colors.numpy() * 255.0), 0, 255).astype(np.uint8)
    if "normals" in pcd.point:
        normals = pcd.point.normals.numpy().astype(np.float32)
    else:
        legacy = pcd.to_legacy()
        legacy.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * config.voxel_size_m, max_nn=30))
        normals = np.asarray(legacy.normals, dtype=np.float32)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # The grid's blocks come out in the order its threads inserted them, a different order each run; the site
    # build keeps the first point met per voxel, so that order made every fused site a little different (a test's
    # relocalization at the edge of `ok` flipped about one run in four). Sorted by position, a fusion is repeatable.
    order = np.lexsort(points.T)
    points, colors, normals = points[order], colors[order], normals[order]
    labels = None
    if use_labels:
        def _vote_progress(done: int, _n: int) -> None:
            if progress is not None:
                progress(len(posed) + done, total)

        labels = vote_labels(frames, posed[::config.label_frame_stride], points, config, _vote_progress)
    return FusedCloud(points, colors, normals, labels, frames.label_set)


def vote_labels(
    frames: RecordedFrames,
    posed: Sequence[tuple[int, np.ndarray]],
    points: np.ndarray,
    config: FuseConfig = FuseConfig(),
    progress: Progress | None = None,
) -> np.ndarray:
    """(N,) int64 majority label per map point over the labelled frames `posed` ((index, T_map_camera) pairs).

    A frame votes for a point when the point projects inside its depth image with a depth within
    `label_depth_tolerance_m` of the measured one (so occluded points get no vote); the vote is the label at the
    point's projection into the colour camera. Points no frame sees get 0.
    """
    n = len(points)
    di, ci = frames.depth_intrinsics, frames.color_intrinsics
    keys: list[np.ndarray] = []
    for k, (i, T_map_camera) in enumerate(posed):
        frame, _ = frames.load(i)
        if frame.labels is None:
            continue
        T_depth_map = invert_T(T_map_camera @ frames.T_color_depth)
        p = transform_points(T_depth_map, points)
        z = p[:, 2]
        front = np.flatnonzero(z > 1e-3)
        u = np.rint(p[front, 0] / z[front] * di.fx + di.cx).astype(np.int64)
        v = np.rint(p[front, 1] / z[front] * di.fy + di.cy).astype(np.int64)
        inside = (u >= 0) & (u < di.width) & (v >= 0) & (v < di.height)
        front, u, v = front[inside], u[inside], v[inside]
        measured = frame.depth[v, u].astype(np.float64) / frame.depth_scale
        seen = (measured > 0) & (np.abs(measured - z[front]) < config.label_depth_tolerance_m)
        idx = front[seen]
        q = transform_points(frames.T_color_depth, p[idx])
        uc = np.rint(q[:, 0] / q[:, 2] * ci.fx + ci.cx).astype(np.int64)
        vc = np.rint(q[:, 1] / q[:, 2] * ci.fy + ci.cy).astype(np.int64)
        ok = (uc >= 0) & (uc < ci.width) & (vc >= 0) & (vc < ci.height)
        lab = frame.labels[vc[ok], uc[ok]].astype(np.int64)
        keys.append(idx[ok].astype(np.int64) * 65536 + lab)
        if progress is not None:
            progress(k + 1, len(posed))
    labels = np.zeros(n, dtype=np.int64)
    if not keys:
        return labels
    uniq, counts = np.unique(np.concatenate(keys), return_counts=True)
    pt, lab = uniq // 65536, uniq % 65536
    # Majority per point: sort by (point, count) and take each point's last entry.
    order = np.lexsort((counts, pt))
    pt, lab = pt[order], lab[order]
    last = np.r_[pt[1:] != pt[:-1], True]
    labels[pt[last]] = lab[last]
    return labels


def frames_sha256(frames: RecordedFrames, indices: Sequence[int]) -> str:
    """The sha256 of the frames a site is fused from (DESIGN §3: a bundle names its inputs with their sha256), over
    the sorted "file:sha256" lines of their files, named relative to the folder: the same frames copied elsewhere
    give the same digest."""
    lines = sorted(f"{os.path.relpath(p, frames.root)}:{sha256_file(p)}" for p in frames.source_files(list(indices)))
    return sha256_bytes("\n".join(lines).encode())


def fuse_site(
    frames: RecordedFrames,
    indices: Sequence[int] | None = None,
    *,
    site_id: str,
    config: FuseConfig = FuseConfig(),
    build_config: SiteBuildConfig = SiteBuildConfig(),
    progress: Progress | None = None,
    cad_root=None,
    auto_cad: AutoCadConfig | None = None,
) -> "Site":  # noqa: F821  (imported lazily: the bundle pulls in the whole site build)
    """A site from TSDF-fused frames: objects from clustering of voted labels, none when the frames have no labels
    (such a site localizes with the geometric fallback). With `auto_cad` and a CAD library at `cad_root`, the
    library's models are aligned to the labelled instances (cadreg/site/autocad.py); that needs labelled frames."""
    from .build import site_from_labelled_points

    indices = list(frames.indices if indices is None else indices)

    # One 0..100 scale: fusion (and label votes) take the first 85 steps, the site build the rest.
    def _fuse_progress(done: int, total: int) -> None:
        if progress is not None:
            progress(round(85 * done / max(total, 1)), 100)

    cloud = fuse_frames(frames, indices, config=config, progress=_fuse_progress)

    def _build_progress(done: int, total: int) -> None:
        if progress is not None:
            progress(85 + round(15 * done / max(total, 1)), 100)

    inputs = {
        "frames": {
            "path": str(frames.root), "layout": frames.layout, "indices": [int(indices[0]), int(indices[-1]) + 1],
            "count": len(indices), "sha256": frames_sha256(frames, indices),
        },
        "fusion": config.model_dump(),
    }
    site = site_from_labelled_points(
        cloud.points, cloud.colors, cloud.normals, cloud.labels, label_set=cloud.label_set if cloud.labels is not None
        else "nyu40", site_id=site_id, inputs=inputs, config=build_config, progress=_build_progress,
        cad_root=cad_root, auto_cad=auto_cad,
    )
    # The map's frame is the recording's (often its first camera's), with no axis up: the site states its up.
    site.manifest["up"] = [float(x) for x in fused_up(frames, indices, cloud.normals)]
    return site


def fused_up(frames: RecordedFrames, indices: Sequence[int], normals: np.ndarray, *, frames_used: int = 30,
             agree_deg: float = 10.0) -> np.ndarray:
    """(3,) the up of a map fused from `frames` at their poses (map frame).

    Each of up to `frames_used` frames spread over `indices` finds its own up from its flat surfaces, as a query
    frame first does (`estimate_up_from_normals` on the 3 cm grid; not the query's retry on its own points, whose
    far floors keep the depth's steps, below), put into the map by its pose; the mean of the
    largest group within agree_deg of one another is the map's up. The fused surface's own normals are no match
    for that: fused from few views of a structured-light sensor, far floors keep the depth's steps, whose normals
    face the camera (a map fused from one frame of a lounge came out 16 degrees off). Frames that find no up leave
    it to those normals, with the cameras' mean up as the prior (`map_up_axis`)."""
    posed = [(i, T) for i in indices if (T := frames.pose(i)) is not None]
    if not posed:
        raise ConfigError("none of the selected frames has a pose: fusion needs T_map_camera per frame")
    fc = FrameConfig()
    ups = []
    for i, T_map_camera in posed[::max(1, len(posed) // frames_used)]:
        frame, _ = frames.load(i)
        points = frame_to_points(frame, pixel_stride=fc.pixel_stride, min_depth_m=fc.min_depth_m,
                                 max_depth_m=fc.max_depth_m)
        floor = estimate_up_from_normals(voxel_downsample(points, fc.voxel_size_m).xyz)
        if floor is not None:
            ups.append(T_map_camera[:3, :3] @ floor.up_camera)
    if ups:
        ups = np.array(ups)
        agree = (ups @ ups.T) > np.cos(np.radians(agree_deg))
        group = ups[agree[int(np.argmax(agree.sum(axis=1)))]]
        up = group.mean(axis=0)
        return up / np.linalg.norm(up)
    prior = np.mean([-T[:3, 1] for _, T in posed], axis=0)
    if np.linalg.norm(prior) < 1e-6:
        raise ConfigError("the recorded cameras' up directions cancel out: cannot tell the map's up")
    return map_up_axis(normals, prior=prior)


def frame_points_in_map(frames: RecordedFrames, i: int) -> np.ndarray:
    """Valid depth of frame i back-projected (paper eq. 1–2) and put into the map at its recorded pose.

    Returns (n, 3) float64 metres, map frame. Raises ConfigError when the frame has no pose.
    """
    frame, T_map_camera = frames.load(i)
    if T_map_camera is None:
        raise ConfigError(f"frame {i} of {frames.root} has no pose")
    K = frame.depth_intrinsics
    z = frame.depth.astype(np.float64) / frame.depth_scale
    v, u = np.nonzero(z > 0)
    p = np.stack([(u - K.cx) / K.fx * z[v, u], (v - K.cy) / K.fy * z[v, u], z[v, u]], axis=1)
    return transform_points(T_map_camera @ frames.T_color_depth, p)


def map_accuracy(map_points: np.ndarray, frames: RecordedFrames, indices: Sequence[int], *,
                 overlap_m: float = 0.1) -> dict[str, float]:
    """How well a map explains frames it was not built from.

    Both directions: every valid depth point of the frames, placed at their recorded poses, to the nearest map
    point (`median_m`, `p90_m`: accuracy and completeness together), and every map point to the nearest frame
    point (`map_to_frames_median_m`). Held-out frames also see what the map never saw; `overlap_median_m` is the
    median over frame points within `overlap_m` of the map, the accuracy where both saw the same surface.
    map_points : (n, 3) float, map frame.
    """
    from scipy.spatial import cKDTree

    map_points = np.asarray(map_points, dtype=np.float64)
    clouds = [frame_points_in_map(frames, i) for i in indices]
    d = np.concatenate([cKDTree(map_points).query(c, workers=-1)[0] for c in clouds])
    # Every 7th frame point is plenty for the reverse direction (frames are far denser than the map).
    held = np.concatenate([c[::7] for c in clouds])
    d_back = cKDTree(held).query(map_points, workers=-1)[0]
    near = d[d < overlap_m]
    return {"frames": len(indices), "points": int(len(d)), "median_m": float(np.median(d)),
            "p90_m": float(np.percentile(d, 90)), "map_to_frames_median_m": float(np.median(d_back)),
            "overlap_fraction": float(len(near) / max(len(d), 1)),
            "overlap_median_m": float(np.median(near)) if len(near) else float("nan")}


def pose_offset(map_points: np.ndarray, map_normals: np.ndarray, frames: RecordedFrames, indices: Sequence[int], *,
                config: FuseConfig = FuseConfig(), voxel_m: float = 0.02,
                correspondences_m: tuple[float, ...] = (0.08, 0.04, 0.02)) -> dict[str, float]:
    """How far the recorded poses of held-out frames disagree with a map: the frames are fused at their poses and
    their surface is registered onto the map by point-to-plane ICP from where they put it (wide then narrow
    correspondences). A localizer that is right against the map is off from such frames' recorded poses by this
    much: a dataset's poses (7-Scenes' come from KinectFusion) drift between parts of a sequence.

    map_points, map_normals : (n, 3) float, map frame. Returns `camera_offset_m` (median over the frames of how
    far the correction moves their camera centres), `max_camera_offset_m`, `rotation_deg` (of the correction),
    and the ICP's `fitness` and `rmse_m`. Raises ConfigError when the frames fuse to nothing.
    """
    target = _map_cloud(map_points, map_normals)
    return _offset_onto(target, frames, list(indices), config=config, voxel_m=voxel_m,
                        correspondences_m=correspondences_m)


def pose_offset_by_window(map_points: np.ndarray, map_normals: np.ndarray, frames: RecordedFrames,
                          indices: Sequence[int], window: int, *, config: FuseConfig = FuseConfig(),
                          voxel_m: float = 0.02, min_fitness: float = 0.5,
                          offset_limit_m: float = 0.05, corrected: dict[int, np.ndarray] | None = None
                          ) -> dict[str, object]:
    """`pose_offset` of each run of `window` consecutive frames of `indices`: where along a sequence its recorded
    poses drift from the map. A window whose surface lies less than `min_fitness` on the map (it looks past the
    map) says little and is counted apart.

    Returns `windows` (each with `first`, `last` and pose_offset's keys; only `frames` and a `fitness` of 0 for
    one that fuses to nothing), `frames_checked` (frames of windows that reach min_fitness) and
    `frames_over_limit` (those of them whose camera the correction moves by more than `offset_limit_m`: frames a
    localizer right against the map places more than that far from their record).

    corrected : when given, filled with the pose each frame of a window that reaches min_fitness has where the map
    puts it (the window's correction applied to its recorded pose): a ground truth against the map itself, for
    `cadreg bench --truth`.
    """
    if window < 1:
        raise ConfigError(f"window must be at least 1 frame, got {window}")
    indices = list(indices)
    target = _map_cloud(map_points, map_normals)
    windows, checked, over = [], 0, 0
    for start in range(0, len(indices), window):
        part = indices[start:start + window]
        try:
            offset = _offset_onto(target, frames, part, config=config, voxel_m=voxel_m, per_frame=True)
        except ConfigError:
            # Frames that see no surface twice (too few, or too far apart) fuse to nothing: nothing to check.
            windows.append({"first": part[0], "last": part[-1], "frames": len(part), "fitness": 0.0})
            continue
        moved, on_map = offset.pop("per_frame_m"), offset.pop("corrected")
        windows.append({"first": part[0], "last": part[-1], **offset})
        if offset["fitness"] >= min_fitness:
            checked += len(moved)
            over += int(np.sum(np.asarray(moved) > offset_limit_m))
            if corrected is not None:
                corrected.update(on_map)
    return {"window": window, "min_fitness": min_fitness, "offset_limit_m": offset_limit_m,
            "frames_checked": checked, "frames_over_limit": over, "windows": windows}


def _map_cloud(map_points: np.ndarray, map_normals: np.ndarray) -> o3d.geometry.PointCloud:
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(map_points, dtype=np.float64)))
    target.normals = o3d.utility.Vector3dVector(np.asarray(map_normals, dtype=np.float64))
    return target


def _offset_onto(target: o3d.geometry.PointCloud, frames: RecordedFrames, indices: list[int], *, config: FuseConfig,
                 voxel_m: float, correspondences_m: tuple[float, ...] = (0.08, 0.04, 0.02),
                 per_frame: bool = False) -> dict:
    """The frames fused at their recorded poses, registered onto `target` from there: how far that moves them."""
    cloud = fuse_frames(frames, indices, config=config)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points.astype(np.float64)))
    source = source.voxel_down_sample(voxel_m)
    reg = o3d.pipelines.registration
    T = np.eye(4)
    for corr in correspondences_m:
        res = reg.registration_icp(source, target, corr, T, reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=50))
        T = np.asarray(res.transformation)
    poses = [frames.pose(i) for i in indices]  # each a file read
    centres = np.array([T_map_camera[:3, 3] for T_map_camera in poses if T_map_camera is not None])
    moved = np.linalg.norm(transform_points(T, centres) - centres, axis=1)
    out = {"frames": len(centres), "camera_offset_m": float(np.median(moved)),
           "max_camera_offset_m": float(moved.max()), "rotation_deg": rotation_angle_deg(T[:3, :3]),
           "fitness": float(res.fitness), "rmse_m": float(res.inlier_rmse)}
    if per_frame:
        # How far each camera moves, and its pose where the map puts it (the correction applied to its record).
        out["per_frame_m"] = moved.tolist()
        out["corrected"] = {i: T @ P for i, P in zip(indices, poses) if P is not None}
    return out
