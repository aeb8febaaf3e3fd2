"""Gravity and floor: the camera's up direction and height from a visible floor, and the map's floor height.

A known up direction leaves 4 degrees of freedom (yaw + translation); a visible floor also fixes the camera's
height above it, leaving 3 (x, y, yaw).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

# Label ids meaning "floor" per label set; NYU40 floor = 2 (ScanNet, the renderer), ScanNet-20 floor = 2 too.
FLOOR_LABELS: dict[str, tuple[int, ...]] = {"nyu40": (2,), "scannet20": (2,), "scannet": (2,)}
# The flatness test of the up estimate: neighbours and the largest smallest-to-middle eigenvalue ratio. A depth
# sensor's noise at 2–3 m (a centimetre and more) makes a patch of 12 points on the frame's 3 cm grid look
# curved, and a floor seen that far then gave too few flat normals for any up. With 24 neighbours (twice the
# area) and a ratio of 0.08: up found on all 500 real 7-Scenes RedKitchen frames (4 had none before) and never
# more than 4° off (16 were more than 10° off); on the 200 scene0470 renders (seed 7), on all (4 had none), at
# most 7° off (two were 17° and 54° off).
UP_NEIGHBORS = 24
UP_MAX_FLATNESS = 0.08
# Points sampled for the flat neighbourhoods of `estimate_up_from_normals`, and again when those were too few.
UP_SAMPLE = 1000
UP_RETRY_SAMPLE = 4000


@dataclass
class Floor:
    """Up direction and floor in the colour-camera frame.

    up_camera : (3,) float64 unit vector opposite to gravity, camera frame.
    height_m : camera centre's height above the floor, metres; None when only the direction is known.
    source : "floor" (plane fitted on floor-labelled points) | "client" (gravity given with the frame) |
        "surfaces" (the frame's flat surfaces, `estimate_up_from_normals`).
    inliers : number of floor points supporting the plane (0 for client gravity).
    """

    up_camera: np.ndarray
    height_m: float | None
    source: str
    inliers: int = 0
    floor_guess_m: float | None = None  # height above the lowest horizontal plane seen (maybe a table top)
    normals: np.ndarray | None = None  # (m, 3) unit normals of the flat patches the up came from (source "surfaces")


def fit_plane(points: np.ndarray, *, threshold_m: float = 0.02, iterations: int = 60,
              rng: np.random.Generator | None = None) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC plane n·x = c on (n, 3) points, refined by least squares on the inliers.

    Returns (unit normal (3,), c, inlier mask) or None when there are too few points.
    Written by hand: Open3D's segment_plane needs a tensor/legacy cloud round trip that costs more than this.
    """
    n = len(points)
    if n < 20:
        return None
    rng = rng or np.random.default_rng(0)
    sample = rng.integers(0, n, size=(iterations, 3))
    a, b, c = points[sample[:, 0]], points[sample[:, 1]], points[sample[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-9
    if not np.any(good):
        return None
    normals = normals[good] / norm[good, None]
    offsets = np.einsum("ij,ij->i", normals, a[good])
    probe = points if n <= 3000 else points[rng.choice(n, 3000, replace=False)]
    support = (np.abs(probe @ normals.T - offsets) < threshold_m).sum(axis=0)
    best = int(np.argmax(support))
    inl = np.abs(points @ normals[best] - offsets[best]) < threshold_m
    if inl.sum() < 3:
        return None
    centre = points[inl].mean(axis=0)
    _, _, Vt = np.linalg.svd(points[inl] - centre, full_matrices=False)
    normal = Vt[2]
    return normal, float(normal @ centre), np.abs(points @ normal - normal @ centre) < threshold_m


def estimate_floor(xyz: np.ndarray, labels: np.ndarray, label_set: str, *,
                   gravity_camera: np.ndarray | None = None, min_floor_points: int = 150,
                   max_tilt_from_client_deg: float = 20.0, use_surfaces: bool = True,
                   dense_xyz: np.ndarray | None = None) -> Floor | None:
    """Up direction (and camera height) of a frame.

    xyz : (n, 3) float colour-camera frame; labels : (n,) int label ids (-1 = none).
    gravity_camera : (3,) "down" from the client, if any. A floor plane that disagrees with it by more than
    `max_tilt_from_client_deg` is ignored (it is not the floor). With neither floor nor client gravity, the
    up direction comes from the frame's flat surfaces when `use_surfaces` (no height then), from `dense_xyz` (the
    frame's points before xyz was gridded, if given) when xyz's say nothing (`estimate_up_from_normals`).
    """
    floor_ids = FLOOR_LABELS.get(label_set.lower(), ())
    mask = np.isin(labels, floor_ids) if floor_ids else np.zeros(len(xyz), bool)
    if mask.sum() >= min_floor_points:
        fit = fit_plane(xyz[mask])
        if fit is not None:
            normal, c, inl = fit
            # The camera (origin) is above the floor: orient the normal towards it.
            if c > 0:
                normal, c = -normal, -c
            height = -c
            agrees = True
            if gravity_camera is not None:
                agrees = float(normal @ -gravity_camera) > np.cos(np.radians(max_tilt_from_client_deg))
            if agrees and int(inl.sum()) >= min_floor_points // 2 and height > 0.05:
                return Floor(normal, float(height), "floor", int(inl.sum()))
    if gravity_camera is not None:
        up = -np.asarray(gravity_camera, float)
        return Floor(up / np.linalg.norm(up), None, "client")
    if use_surfaces:
        return estimate_up_from_normals(xyz, dense_xyz=dense_xyz)
    return None


def map_floor_height(points: np.ndarray, normals: np.ndarray | None, up: np.ndarray, *, bin_m: float = 0.02) -> float:
    """Height of the map's floor along `up` (metres, map frame).

    points, normals : (n, 3) float map frame. The floor is the most populated height bin, among points whose
    normal is vertical, in the lower third of the map's height range.
    """
    h = points @ up
    keep = np.ones(len(h), bool)
    if normals is not None and len(normals) == len(points):
        keep = np.abs(normals @ up) > 0.9
    lo, hi = np.percentile(h, 0.5), np.percentile(h, 99.5)
    keep &= h < lo + (hi - lo) / 3
    if keep.sum() < 10:
        return float(lo)
    hk = h[keep]
    edges = np.arange(hk.min(), hk.max() + 2 * bin_m, bin_m)
    counts, edges = np.histogram(hk, bins=edges)
    i = int(np.argmax(counts))
    inbin = hk[(hk >= edges[i]) & (hk <= edges[i + 1])]
    return float(np.median(inbin))


def planar_normals(xyz: np.ndarray, *, k: int = 12, max_points: int = 3000, max_flatness: float = 0.05,
                   rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(points (m, 3), unit normals (m, 3)) of up to `max_points` sampled points whose k-neighbourhood is flat.

    Flat: smallest / middle covariance eigenvalue below `max_flatness`.
    """
    from scipy.spatial import cKDTree

    rng = rng or np.random.default_rng(0)
    if len(xyz) < k + 1:
        return np.zeros((0, 3)), np.zeros((0, 3))
    sample = xyz if len(xyz) <= max_points else xyz[rng.choice(len(xyz), max_points, replace=False)]
    _, nn = cKDTree(xyz).query(sample, k=k)
    w, U = np.linalg.eigh(_scatter(np.ascontiguousarray(xyz, dtype=np.float64), nn))
    flat = w[:, 0] < max_flatness * np.maximum(w[:, 1], 1e-12)
    return sample[flat], U[flat, :, 0]


def estimate_up_from_normals(xyz: np.ndarray, *, max_roll_deg: float = 25.0, pitch_range_deg: tuple[float, float] = (-30.0, 90.0),
                             step_deg: float = 2.0, tolerance_deg: float = 6.0, min_horizontal: int = 20,
                             min_vertical: int = 150, second_wall_ratio: float = 0.1,
                             dense_xyz: np.ndarray | None = None) -> Floor | None:
    """Up direction from the frame's flat surfaces when no floor is labelled.

    Indoors, flat surfaces are horizontal (floor, table tops, seats) or vertical (walls, doors). A camera held by
    a person has a small roll: the up direction is searched over pitch and a bounded roll, scoring normals that
    are parallel to it (horizontal surfaces, weighted double) or perpendicular (vertical ones); then refined as
    the mean of the parallel normals. Walls alone leave the up direction on a circle: then the smallest roll on
    it is taken.

    The flat neighbourhoods come from a sample of UP_SAMPLE points, and from UP_RETRY_SAMPLE when those were too
    few to say: in a cluttered view (shelves, a plant, a scan's rough furniture in front of its walls) a sixth of
    the sample lies on flat surfaces, and 155 of 1000 left three views of the 10-room benchmark with no up at all
    (and a building with no answer), where 4000 found the walls they show.

    Last, when given, from `dense_xyz`, the frame's points before xyz was gridded: a view 4-5 m deep (depth noise
    σ 3-4 cm there) spreads each far surface over several of the grid's 3 cm voxels in depth, one point kept in each,
    and a neighbourhood of those points is flat nowhere (4 views of the far walls across a 16-room building, 22-174
    flat of 4000); the frame's own points, denser along the surface than the noise is deep, are (up 1-7° off).
    """
    kw = dict(max_roll_deg=max_roll_deg, pitch_range_deg=pitch_range_deg, step_deg=step_deg, tolerance_deg=tolerance_deg,
              min_horizontal=min_horizontal, min_vertical=min_vertical, second_wall_ratio=second_wall_ratio)

    def up_of(points: np.ndarray, sample: int) -> Floor | None:
        return _up_from_normals(*planar_normals(points, k=UP_NEIGHBORS, max_points=sample,
                                                max_flatness=UP_MAX_FLATNESS), **kw)

    floor = up_of(xyz, UP_SAMPLE)
    if floor is None and len(xyz) > UP_SAMPLE:
        floor = up_of(xyz, UP_RETRY_SAMPLE)
    if floor is None and dense_xyz is not None and len(dense_xyz) > len(xyz):
        floor = up_of(dense_xyz, UP_RETRY_SAMPLE)
    return floor


def _up_from_normals(points: np.ndarray, normals: np.ndarray, *, max_roll_deg: float, pitch_range_deg: tuple[float, float],
                     step_deg: float, tolerance_deg: float, min_horizontal: int, min_vertical: int,
                     second_wall_ratio: float) -> Floor | None:
    """`estimate_up_from_normals` from the frame's flat points and their normals ((m, 3) each, camera frame)."""
    if len(normals) < min_horizontal:
        return None
    pitch = np.radians(np.arange(pitch_range_deg[0], pitch_range_deg[1] + 1e-9, step_deg))
    roll = np.radians(np.arange(-max_roll_deg, max_roll_deg + 1e-9, step_deg))
    P, Rr = np.meshgrid(pitch, roll, indexing="ij")
    P, Rr = P.ravel(), Rr.ravel()
    # Up of a camera with OpenCV axes (y down), pitched down by P and rolled by Rr.
    up0 = np.stack([np.zeros_like(P), -np.cos(P), -np.sin(P)], axis=1)
    cu, su = np.cos(Rr), np.sin(Rr)
    up = np.stack([cu * up0[:, 0] - su * up0[:, 1], su * up0[:, 0] + cu * up0[:, 1], up0[:, 2]], axis=1)
    cos_tol, sin_tol = np.cos(np.radians(tolerance_deg)), np.sin(np.radians(tolerance_deg))
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    n_par, n_perp = _alignment_counts(normals, np.ascontiguousarray(up), cos_tol, sin_tol)
    # Ties (walls only) go to the smallest roll.
    score = 2.0 * n_par + n_perp - 0.01 * np.abs(np.degrees(Rr))
    best = int(np.argmax(score))
    u = up[best]
    if n_par[best] < min_horizontal:
        # Too little horizontal surface to count: a few stray normals (an edge, a ragged scan border) must not
        # pick a tilted up over the upright one. Walls alone leave up on a circle; take the smallest roll on it.
        on_circle = np.flatnonzero(n_perp >= 0.9 * n_perp.max())
        best = int(on_circle[np.lexsort((-n_perp[on_circle], np.abs(Rr[on_circle])))[0]])
        u = up[best]
        if n_perp[best] < min_vertical:
            return None
        # Two walls that are not parallel fix up exactly (their normals' common perpendicular): then trust them
        # over the roll prior; one wall leaves the circle, and the prior stands.
        walls = normals[_abs_dots(normals, u) < sin_tol]
        w, V = np.linalg.eigh(walls.T @ walls / len(walls))
        if w[1] > second_wall_ratio * w[2]:
            u = V[:, 0] * np.sign(V[:, 0] @ u)
        return Floor(u, None, "surfaces", int(n_perp[best]), normals=normals)
    par = _abs_dots(normals, u) > cos_tol
    n = normals[par]
    n = n * np.sign(n @ u)[:, None]
    u = n.mean(axis=0)
    u /= np.linalg.norm(u)
    # The lowest horizontal plane with some support: the floor when it is in view, else whatever is lowest.
    below = -(points[par] @ u)
    guess = None
    if len(below):
        counts, edges = np.histogram(below, bins=np.arange(below.min(), below.max() + 0.04, 0.02))
        ok = np.flatnonzero(counts >= max(5, 0.1 * len(below)))
        if len(ok):
            k = ok[-1]
            guess = float(np.median(below[(below >= edges[k]) & (below <= edges[k + 1])]))
    return Floor(u, None, "surfaces", int(n_par[best]), floor_guess_m=guess, normals=normals)


@njit(cache=True, nogil=True)
def _scatter(xyz, nn):
    """(m, 3, 3) the scatter matrix of each neighbourhood (xyz (n, 3) at the indices nn (m, k)) about its mean,
    summed as numpy's mean and einsum over the gathered (m, k, 3) neighbourhoods sum it (the same values): those
    passes took 2.7 ms a frame's 1000 neighbourhoods, a tenth of that here."""
    m, k = nn.shape
    out = np.zeros((m, 3, 3))
    centred = np.empty((k, 3))
    mean = np.empty(3)
    for s in range(m):
        mean[:] = 0.0
        for q in range(k):
            for a in range(3):
                mean[a] += xyz[nn[s, q], a]
        mean /= k
        for q in range(k):
            for a in range(3):
                centred[q, a] = xyz[nn[s, q], a] - mean[a]
        for i in range(3):
            for j in range(3):
                total = 0.0
                for q in range(k):
                    total += centred[q, i] * centred[q, j]
                out[s, i, j] = total
    return out


@njit(cache=True, nogil=True, inline="always")
def _abs_dot(normals, i, ux, uy, uz):
    return abs(normals[i, 0] * ux + normals[i, 1] * uy + normals[i, 2] * uz)


@njit(cache=True, nogil=True)
def _abs_dots(normals, u):
    """(m,) |n · u| of each normal (m, 3) with one direction u (3,)."""
    out = np.empty(len(normals))
    for i in range(len(normals)):
        out[i] = _abs_dot(normals, i, u[0], u[1], u[2])
    return out


@njit(cache=True, nogil=True)
def _alignment_counts(normals, up, cos_tol, sin_tol):
    """(parallel, perpendicular), (c,) int64 each: for each candidate direction of up (c, 3), how many of the
    normals (m, 3) lie within the tolerance of parallel to it (|n · u| > cos_tol) and of perpendicular
    (|n · u| < sin_tol). One pass, no (m, c) temporaries: as numpy products and masks, the 1586 candidates of a
    frame's 1000 normals took 4-6 ms (of the 13-15 a label-free frame's up direction cost)."""
    par = np.zeros(len(up), dtype=np.int64)
    perp = np.zeros(len(up), dtype=np.int64)
    for j in range(len(up)):
        ux, uy, uz = up[j, 0], up[j, 1], up[j, 2]
        for i in range(len(normals)):
            d = _abs_dot(normals, i, ux, uy, uz)
            if d > cos_tol:
                par[j] += 1
            elif d < sin_tol:
                perp[j] += 1
    return par, perp


def warm() -> None:
    """Compile (or load from numba's cache) the loops (`Localizer.warm`)."""
    n = np.zeros((1, 3))
    _alignment_counts(n, np.eye(3), 0.9, 0.1)
    _abs_dots(n, np.zeros(3))
    _scatter(n, np.zeros((1, 1), dtype=np.int64))


# `map_up_axis` with the normals' points: +z, scoring at least FLOOR_KEEP_RATIO of the best axis, is kept when its
# surfaces lie at one end of the map and the best's at both (the share of an axis's surfaces in the END_BAND of the
# map's extent at one end, less that at the other, over both: at least ONE_SIDED, at most TWO_SIDED).
FLOOR_KEEP_RATIO = 0.5
ONE_SIDED = 0.7
TWO_SIDED = 0.3
END_BAND = 0.1


def _one_sided(points: np.ndarray, along: np.ndarray, axis: np.ndarray) -> float:
    """|a − b| / (a + b) (0 when both are 0): a and b count the points marked `along` (their normal parallel to
    `axis`) in the END_BAND share of the extent of all `points` along `axis` at its low and at its high end. A floor
    under an open top reads 1; two facing walls, 0."""
    h = points @ axis
    lo, hi = np.percentile(h, 0.5), np.percentile(h, 99.5)
    band = END_BAND * (hi - lo)
    a = int(np.count_nonzero(along & (h <= lo + band)))
    b = int(np.count_nonzero(along & (h >= hi - band)))
    return abs(a - b) / (a + b) if a + b else 0.0


def map_up_axis(normals: np.ndarray, *, points: np.ndarray | None = None, prior: np.ndarray | None = None,
                tolerance_deg: float = 5.0, sample: int = 20000, candidates: int = 400, snap_deg: float = 3.0,
                z_keep_ratio: float = 0.8, prior_cone_deg: float = 45.0, seed: int = 0) -> np.ndarray:
    """The map's up direction (3,) from its surface normals, for sites that do not state it.

    Indoors, the most common normal direction with the most perpendicular ones (walls) is vertical: every
    candidate (a sampled normal) is scored by normals parallel to it plus half those perpendicular; the best is
    refined as the mean of its parallel normals. Sign: floors and table tops face up and outnumber ceilings.
    A box-shaped room scores its three axes alike, so +z (the convention of ScanNet, of the demo site and of
    most building scans) is kept unless another direction scores clearly better.

    points : (n, 3) the normals' points, when at hand: then +z is also kept when it scores at least
    FLOOR_KEEP_RATIO of the best, its surfaces lie at one end of the map (a floor, nothing under it: `_one_sided`
    at least ONE_SIDED) and the best's at both (facing walls: at most TWO_SIDED). A corridor's long walls outnumber
    its floor, and the up of a scan of one came out as the corridor's cross axis: every frame was searched on its
    side.

    prior : (3,) a rough up of the map's own (the mean up of the cameras that recorded it, `fuse.fused_up`):
    then the best candidate within prior_cone_deg of it wins and faces its way, with no +z preference. A map
    fused in the frame of its first camera (KinectFusion, SUN3D) has no reason to be z-up, and one fused from a
    few views of a lounge scored its floor (y) under 1.25x a z axis that every floor and wall normal lay
    perpendicular to: +z was kept and every frame was placed on its side.
    """
    rng = np.random.default_rng(seed)
    n = np.asarray(normals, dtype=np.float64)
    keep = np.linalg.norm(n, axis=1) > 0.5
    n = n[keep]
    xyz = None if points is None else np.asarray(points, dtype=np.float64)[keep]
    if len(n) > sample:
        pick = rng.choice(len(n), sample, replace=False)
        n, xyz = n[pick], None if xyz is None else xyz[pick]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cand = n[rng.choice(len(n), min(candidates, len(n)), replace=False)]
    if prior is None:
        cand = np.vstack([[0.0, 0.0, 1.0], cand])
    else:
        prior = np.asarray(prior, dtype=np.float64) / np.linalg.norm(prior)
        cand = np.vstack([prior, cand * np.sign(cand @ prior)[:, None]])
    dots = np.abs(n @ cand.T)
    par = dots > np.cos(np.radians(tolerance_deg))
    perp = dots < np.sin(np.radians(tolerance_deg))
    score = par.sum(axis=0) + 0.5 * perp.sum(axis=0)
    if prior is not None:
        score = np.where(cand @ prior >= np.cos(np.radians(prior_cone_deg)), score, -1.0)
    best = int(np.argmax(score))
    if prior is None and score[0] >= z_keep_ratio * score[best]:
        return np.array([0.0, 0.0, 1.0])
    if (prior is None and xyz is not None and score[0] >= FLOOR_KEEP_RATIO * score[best]
            and _one_sided(xyz, par[:, 0], cand[0]) >= ONE_SIDED
            and _one_sided(xyz, par[:, best], cand[best]) <= TWO_SIDED):
        return np.array([0.0, 0.0, 1.0])
    p = n[par[:, best]]
    if not len(p):  # the prior itself with no surface along it (a map of walls alone): the prior stands
        return cand[best]
    p = p * np.sign(p @ cand[best])[:, None]
    u = p.mean(axis=0)
    u /= np.linalg.norm(u)
    if prior is not None:
        u = u * np.sign(u @ prior)
    elif np.sum(n[par[:, best]] @ u > 0) < np.sum(n[par[:, best]] @ u < 0):
        # Sign: most of the horizontal surfaces face up.
        u = -u
    # Scans are mostly built gravity-aligned (ScanNet: z up); a floor that is not quite flat should not tilt
    # the map by a degree or two, so an axis within snap_deg wins.
    k = int(np.argmax(np.abs(u)))
    if abs(u[k]) > np.cos(np.radians(snap_deg)):
        u = np.sign(u[k]) * np.eye(3)[k]
    return u
