"""Frame -> coloured, labelled points in the colour-camera frame (paper eq. 1–2).

Depth pixels are back-projected with the depth intrinsics, moved into the colour camera with `T_color_depth`
and projected into the colour image to read colour and label there (colour and depth may differ in size and
viewpoint, e.g. ScanNet's 1296×968 colour camera 2.5 cm beside its 640×480 depth camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..errors import InvalidFrame
from ..frame import Frame

# A point budget's voxel grows by this factor until the points fit (`voxel_budget`).
VOXEL_GROWTH = 1.15
# A point's voxel in the refinement grows with its depth noise (`noise_octaves`) at most 2^MAX_NOISE_OCTAVE times: a
# point that much noisier than the reference already weighs a 256th of a quiet one.
MAX_NOISE_OCTAVE = 4
# A frame whose points, so thinned, are fewer than this share of those the plain grid keeps (at most the budget) has
# every octave lowered by one until they are not: a frame seen only from afar keeps enough points for a fit, weighed
# among themselves.
NOISE_MIN_SHARE = 0.25


@dataclass
class FramePoints:
    """Points of one frame, colour-camera frame (OpenCV axes), metres.

    xyz : (n, 3) float64.
    rgb : (n, 3) float64 in [0, 1].
    labels : (n,) int64 label ids of the frame's label set, -1 where the frame has no labels.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    labels: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    def subset(self, index: np.ndarray) -> "FramePoints":
        return FramePoints(self.xyz[index], self.rgb[index], self.labels[index])


def stride_for(frame: Frame, pixel_stride: int, reference_pixels: int) -> int:
    """The depth-pixel stride that takes of `frame` about as many pixels as `pixel_stride` takes of a depth image of
    `reference_pixels`: `pixel_stride` for one that size or smaller, larger for a larger one. What the stages after
    the points cost grows with the points: on a frame of surfaces the 3 cm voxels bound them, but a depth image of
    noise fills its frustum, and one of 3840 x 2880 noise took 3.3 s at stride 2 (the up direction alone 1.9 s). A
    larger image of surfaces sampled so keeps as many points per square metre within a few metres as a 640 x 480
    one does at stride 2, and so the same 3 cm voxels."""
    pixels = frame.depth.shape[0] * frame.depth.shape[1]
    # The nearest stride, not the next one up: an 848 x 480 or 640 x 576 sensor keeps stride 2 (at 3 it kept half
    # the points of a 640 x 480 frame); at most (2.5 / 2)² = 1.56 times a reference image's points.
    return max(pixel_stride, int(round(pixel_stride * np.sqrt(pixels / reference_pixels))))


def sampled_points(frame: Frame, pixel_stride: int, *, reference_pixels: int, min_depth_m: float,
                   max_depth_m: float, min_points: int) -> FramePoints:
    """`frame_to_points` at the stride `stride_for` gives (a search's and a tracked frame's alike); a frame with fewer
    than `min_points` valid points is refused, the count named as of the pixels sampled (a client counting its
    valid pixels would otherwise not recognise it)."""
    stride = stride_for(frame, pixel_stride, reference_pixels)
    points = frame_to_points(frame, pixel_stride=stride, min_depth_m=min_depth_m, max_depth_m=max_depth_m)
    if len(points) < min_points:
        raise InvalidFrame(f"only {len(points)} valid depth points in range {min_depth_m}–{max_depth_m} m "
                           f"(one depth pixel in {stride} along each row and column sampled)")
    return points


def frame_to_points(frame: Frame, *, pixel_stride: int = 2, min_depth_m: float = 0.1,
                    max_depth_m: float = 6.0) -> FramePoints:
    """Back-project every `pixel_stride`-th depth pixel and read colour and label in the colour image.

    Points whose projection falls outside the colour image are dropped: they have neither colour nor label.
    """
    K = frame.depth_intrinsics
    z = frame.depth[::pixel_stride, ::pixel_stride].astype(np.float64) / frame.depth_scale
    ok = (z > min_depth_m) & (z < max_depth_m)
    v, u = np.nonzero(ok)
    v *= pixel_stride
    u *= pixel_stride
    z = z[ok]
    xyz_depth = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1)
    if _registered(frame):
        # Depth already registered to colour (renders, 7-Scenes, most phone APIs): every point projects onto its
        # own pixel, so the reprojection would give back u, v and keep every point.
        xyz, ui, vi = xyz_depth, u, v
    else:
        xyz, ui, vi = _project_to_color(frame, xyz_depth)
    rgb = _take_pixels(frame.color, vi, ui).astype(np.float64) / 255.0
    if frame.labels is not None:
        labels = _take_pixels(frame.labels, vi, ui).astype(np.int64)
    else:
        labels = np.full(len(xyz), -1, dtype=np.int64)
    return FramePoints(xyz, rgb, labels)


def window_colours(frame: Frame, xyz_camera: np.ndarray, half: int) -> np.ndarray:
    """(n, 3) float64 in [0, 1]: the mean colour of the (2·half + 1)² colour pixels about each point's own
    (xyz_camera (n, 3), colour-camera frame, points of `frame_to_points`), clipped to the image: one pixel's colour
    carries the sensor's noise, which a neighbourhood averages out."""
    C = frame.color_intrinsics
    z = np.maximum(xyz_camera[:, 2], 1e-6)
    u = np.clip(np.rint(C.fx * xyz_camera[:, 0] / z + C.cx).astype(np.intp), 0, C.width - 1)
    v = np.clip(np.rint(C.fy * xyz_camera[:, 1] / z + C.cy).astype(np.intp), 0, C.height - 1)
    steps = np.arange(-half, half + 1)
    uu = np.clip(u[:, None, None] + steps[None, None, :], 0, C.width - 1)
    vv = np.clip(v[:, None, None] + steps[None, :, None], 0, C.height - 1)
    vv, uu = np.broadcast_arrays(vv, uu)  # (n, 2·half + 1, 2·half + 1) each
    window = _take_pixels(frame.color, vv.ravel(), uu.ravel()).reshape(len(u), -1, 3)
    return window.mean(axis=1) / 255.0


def _take_pixels(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """image (H, W) or (H, W, channels) at the pixels (rows, cols), (n,) each: (n,) or (n, channels). One `take`
    along the flattened rows: indexing by row and column arrays copies each colour pixel on its own, and a frame's
    55 k took 0.8 ms of the 1.1 a frame's points cost to colour (0.2 this way)."""
    height, width = image.shape[:2]
    return np.take(image.reshape(height * width, *image.shape[2:]), rows * width + cols, axis=0)


def _registered(frame: Frame) -> bool:
    return frame.color_intrinsics == frame.depth_intrinsics and bool(np.array_equal(frame.T_color_depth, np.eye(4)))


def _project_to_color(frame: Frame, xyz_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth-camera points -> (points in the colour camera, column, row of their colour pixel), keeping those that
    fall inside the colour image."""
    T = frame.T_color_depth
    xyz = xyz_depth @ T[:3, :3].T + T[:3, 3]
    C = frame.color_intrinsics
    zc = xyz[:, 2]
    front = zc > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        uc = np.rint(C.fx * xyz[:, 0] / zc + C.cx)
        vc = np.rint(C.fy * xyz[:, 1] / zc + C.cy)
    inside = front & (uc >= 0) & (uc < C.width) & (vc >= 0) & (vc < C.height)
    return xyz[inside], uc[inside].astype(np.intp), vc[inside].astype(np.intp)


def voxel_indices(xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices of one point per occupied voxel (the first one met), sorted.

    xyz : (n, 3) float. Keeping a real point (not the voxel mean) keeps its label and colour exact.
    """
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.intp)
    # Axis by axis into contiguous rows: reductions over the columns of an (n, 3) array are strided, and this runs
    # several times a frame.
    keys = np.empty((3, len(xyz)), dtype=np.int64)
    for axis in range(3):
        keys[axis] = np.floor(xyz[:, axis] / voxel_size_m)
    lo = keys.min(axis=1)
    dims = keys.max(axis=1) - lo + 1
    keys -= lo[:, None]
    return first_of_each((keys[0] * dims[1] + keys[1]) * dims[2] + keys[2])


@njit(cache=True, nogil=True)
def first_of_each(keys):
    """(m,) int64 ascending: the index of the first of each distinct value of keys (n,) int64.

    What np.unique(return_index=True) gives, by one pass over a hash set (open addressing, Fibonacci hashing)
    instead of a stable sort: the sort was most of the 2.3 ms a frame's 55 k points took to grid, and a frame
    grids its points several times. Written here: numpy has no hash set."""
    n = len(keys)
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    mask = np.int64((1 << bits) - 1)
    shift = np.uint64(64 - bits)
    table = np.empty(1 << bits, dtype=np.int64)
    used = np.zeros(1 << bits, dtype=np.bool_)
    out = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        key = keys[i]
        slot = np.int64((np.uint64(key) * np.uint64(11400714819323198485)) >> shift)
        while used[slot] and table[slot] != key:
            slot = (slot + 1) & mask
        if not used[slot]:
            used[slot] = True
            table[slot] = key
            out[count] = i
            count += 1
    return out[:count]


def warm() -> None:
    """Compile (or load from numba's cache) the hash set (`Localizer.warm`)."""
    first_of_each(np.zeros(1, dtype=np.int64))


def voxel_downsample(points: FramePoints, voxel_size_m: float) -> FramePoints:
    return points.subset(voxel_indices(points.xyz, voxel_size_m))


def voxel_budget(points: FramePoints, voxel_m: float, budget: int, *,
                 octaves: np.ndarray | None = None) -> FramePoints:
    """`points` on a voxel grid of voxel_m or, when that leaves more than `budget`, of the coarser voxel that does
    not (a grid, not a random sample: thin structure such as a door frame keeps its points). A frame's points lie
    on surfaces, so their count falls about with the voxel's square: one guess, then growth by VOXEL_GROWTH.
    octaves : (n,) int, each point's voxel that many times doubled (`noise_octaves`), or None; lowered by one
    at a time while they leave fewer than NOISE_MIN_SHARE of what the plain grid (or the budget) would keep."""
    grid = lambda v: points.subset(octave_voxel_indices(points.xyz, v, octaves))  # noqa: E731
    sparse = grid(voxel_m)
    if octaves is not None and np.any(octaves) and len(sparse) < NOISE_MIN_SHARE * budget:
        least = NOISE_MIN_SHARE * min(budget, len(voxel_indices(points.xyz, voxel_m)))
        while np.any(octaves) and len(sparse) < least:
            octaves = np.maximum(octaves - 1, 0)
            sparse = grid(voxel_m)
    if len(sparse) > budget:
        voxel_m *= np.sqrt(len(sparse) / budget)
        sparse = grid(voxel_m)
        while len(sparse) > budget:
            voxel_m *= VOXEL_GROWTH
            sparse = grid(voxel_m)
    return sparse


def noise_octaves(sigma_m: np.ndarray, reference_m: float) -> np.ndarray:
    """(n,) int in [0, MAX_NOISE_OCTAVE]: for each frame point's depth noise σ (sigma_m (n,), metres),
    ⌈log2(σ / reference_m)⌉. A point kept one per voxel 2^k times larger weighs about 4^-k as much as its neighbours
    in a refinement that weighs every pair alike (points of a surface are as many as it has voxels): its weight
    falls with its variance, as a least-squares fit of noisy measurements wants, which GICP's covariances (its
    points' local shapes, not their noise) do not give (`RefineStage._noise_weighed`)."""
    sigma = np.asarray(sigma_m, dtype=np.float64)
    if reference_m <= 0:
        return np.zeros(len(sigma), dtype=np.int64)
    return np.clip(np.ceil(np.log2(np.maximum(sigma / reference_m, 1.0))), 0, MAX_NOISE_OCTAVE).astype(np.int64)


def octave_voxel_indices(xyz: np.ndarray, voxel_m: float, octaves: np.ndarray | None) -> np.ndarray:
    """`voxel_indices` with each point's voxel voxel_m · 2^octaves[i] (all voxel_m when octaves is None), sorted:
    one grid per octave."""
    if octaves is None or not np.any(octaves):
        return voxel_indices(xyz, voxel_m)
    parts = [idx[voxel_indices(xyz[idx], voxel_m * 2.0 ** k)]
             for k in np.unique(octaves) for idx in [np.flatnonzero(octaves == k)]]
    return np.sort(np.concatenate(parts))
