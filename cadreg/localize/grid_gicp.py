"""GICP against a map whose points and KD-tree are already built: a building's region map (`RefineMap` with
`stored_target`), the stored grid of its room and halo with the KD-tree its fitness reads.

Written by hand, and why: small_gicp takes no covariances computed elsewhere and no KD-tree it did not build, so
each refinement in a building built a small_gicp target around the frame (a voxel grid, a KD-tree and a covariance
for each of some 30 k map points: 46 of the 255 ms a 100-room frame took), to run two or three GICP iterations from
a start the field alignment had put within a centimetre or two. Here the map's covariances are made only for the
map points a refinement pairs with, on first use, and kept with the map for the frames that come back to it (and
a region's frames always refine here, whatever it served before, so that a frame's answer does not depend on the
frames before it: `RefineMap.refine`).

The cost and its parts are small_gicp's (Segal et al. 2009; small_gicp's `GICPFactor`): residual r = q - T p for
the nearest map point q within the correspondence distance, cost ½ Σ rᵀ (C_q + R C_p Rᵀ)⁻¹ r, covariances from
the GICP_NEIGHBORS nearest points with eigenvalues (1e-3, 1, 1) (a plane), the pose perturbed on the right
(T ← T · exp(δ), δ = (ω, v) in the camera frame), so that the Hessian, and the pose covariance made from it, means
what small_gicp's does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .point_tree import PointTree

# A plane's covariance: unit spread along it, this across it (small_gicp's regularization):
# U diag(PLANE_EPS, 1, 1) Uᵀ = I - (1 - PLANE_EPS) n nᵀ for the unit normal n.
PLANE_EPS = 1e-3
# small_gicp's Levenberg-Marquardt optimizer: the first damping, its factor, and the damped steps tried an iteration.
LM_INIT_DAMPING = 1e-3
LM_FACTOR = 10.0
LM_TRIALS = 10


def plane_normals(xyz: np.ndarray, tree: PointTree, index: np.ndarray, k: int) -> np.ndarray:
    """(m, 3) unit normals of the points xyz[index]: the least axis of each one's k nearest points in `tree`
    (a KD-tree over xyz)."""
    if len(index) == 0:
        return np.zeros((0, 3))
    k = min(k, len(xyz))
    _, nn = tree.query(xyz[index], k=k)
    out = np.empty((len(index), 3))
    _normals(xyz, np.asarray(nn, dtype=np.int64).reshape(len(index), k), out)
    return out


def plane_covariance(normals: np.ndarray) -> np.ndarray:
    """(m, 3) unit normals -> (m, 3, 3) plane covariances I - (1 - PLANE_EPS) n nᵀ."""
    return np.eye(3) - (1.0 - PLANE_EPS) * normals[:, :, None] * normals[:, None, :]


class MapNormals:
    """The GICP normals of a map's points (xyz (n, 3), map frame, with its KD-tree), each made on first use."""

    def __init__(self, xyz: np.ndarray, tree: PointTree, k: int) -> None:
        self.xyz, self.tree, self.k = xyz, tree, k
        self.normals = np.zeros((len(xyz), 3))
        self._known = np.zeros(len(xyz), dtype=bool)

    def ensure(self, index: np.ndarray) -> None:
        """Make the normals of the points xyz[index] that are not made yet."""
        new = np.unique(index[~self._known[index]])
        if len(new):
            self.normals[new] = plane_normals(self.xyz, self.tree, new, self.k)
            self._known[new] = True

    @property
    def known(self) -> int:
        """How many points' normals have been made."""
        return int(self._known.sum())


@dataclass
class GicpResult:
    """T_target_source : (4, 4). H : (6, 6) Gauss-Newton Hessian over (rx, ry, rz, tx, ty, tz) at the last
    linearization (perturbation on the right); error : Σ rᵀ M r there; inliers : its correspondences."""

    T_target_source: np.ndarray
    H: np.ndarray
    error: float
    inliers: int
    iterations: int
    converged: bool


def se3_exp(delta: np.ndarray) -> np.ndarray:
    """(6,) (ω, v) -> (4, 4) exp of the twist (rotation first, as small_gicp's `se3_exp`)."""
    w, v = delta[:3], delta[3:]
    theta = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-10:
        R, V = np.eye(3) + W, np.eye(3) + 0.5 * W
    else:
        a, b = np.sin(theta) / theta, (1.0 - np.cos(theta)) / theta ** 2
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + (theta - np.sin(theta)) / theta ** 3 * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def gicp(target: MapNormals, source_xyz: np.ndarray, source_normals: np.ndarray, T_init: np.ndarray, *,
         max_correspondence_m: float, max_iterations: int, epsilon: float) -> GicpResult:
    """GICP of source points (source frame, (n, 3), plane normals (n, 3)) onto the target map from T_init ((4, 4)
    T_target_source), as small_gicp's Levenberg-Marquardt optimizer runs it: each iteration pairs every source
    point with its nearest map point within the correspondence distance, then tries damped steps (the damping ten
    times larger after each that does not lower the error of those pairs, ten times smaller after one that does),
    and stops when a step's rotation (rad) and translation (m) are both below epsilon, or no step lowers the error."""
    T = np.array(T_init, dtype=np.float64)
    H, b, M = np.zeros((6, 6)), np.zeros(6), np.zeros((len(source_xyz), 3, 3))
    error, inliers, converged, it, damping = 0.0, 0, False, 0, LM_INIT_DAMPING
    while it < max_iterations and not converged:
        it += 1
        R = np.ascontiguousarray(T[:3, :3])
        _, nn = target.tree.query(source_xyz @ R.T + T[:3, 3], k=1, distance_upper_bound=max_correspondence_m)
        found = nn < len(target.xyz)  # a point with no map point within the distance reads the tree's size
        target.ensure(nn[found])
        error, inliers = _linearize(source_xyz, source_normals, target.xyz, target.normals, nn, found, R,
                                    np.ascontiguousarray(T[:3, 3]), PLANE_EPS, H, b, M)
        if inliers < 6:
            break
        for _ in range(LM_TRIALS):
            delta = np.linalg.solve(H + damping * np.eye(6), -b)
            moved = T @ se3_exp(delta)
            if _pair_error(source_xyz, target.xyz, nn, found, M, np.ascontiguousarray(moved[:3, :3]),
                           np.ascontiguousarray(moved[:3, 3])) < error:
                T, damping = moved, damping / LM_FACTOR
                converged = bool(np.linalg.norm(delta[:3]) < epsilon and np.linalg.norm(delta[3:]) < epsilon)
                break
            damping *= LM_FACTOR
        else:
            break
    return GicpResult(T, H.copy(), error, inliers, it, converged)


def warm() -> None:
    """Compile (or load from numba's cache) the loops below (`field_kernels.warm`)."""
    tree, _ = PointTree.sorted(np.random.default_rng(0).random((12, 3)))
    xyz = tree.xyz
    normals = plane_normals(xyz, tree, np.arange(12), 10)
    nn, found, M = np.arange(12), np.ones(12, dtype=bool), np.zeros((12, 3, 3))
    _linearize(xyz, normals, xyz, normals, nn, found, np.eye(3), np.zeros(3), PLANE_EPS, np.zeros((6, 6)),
               np.zeros(6), M)
    _pair_error(xyz, xyz, nn, found, M, np.eye(3), np.zeros(3))


# Compiled, and why: a refinement's few iterations each linearize a thousand pairs, and numpy's batched 3 x 3
# products and inverses cost more than the neighbour search (2.7 ms an iteration where these take a tenth).
@njit(cache=True, nogil=True)
def _normals(xyz, nn, out):
    k = nn.shape[1]
    C = np.empty((3, 3))
    for i in range(nn.shape[0]):
        mx = my = mz = 0.0
        for j in range(k):
            mx += xyz[nn[i, j], 0]
            my += xyz[nn[i, j], 1]
            mz += xyz[nn[i, j], 2]
        mx, my, mz = mx / k, my / k, mz / k
        sxx = sxy = sxz = syy = syz = szz = 0.0
        for j in range(k):
            dx, dy, dz = xyz[nn[i, j], 0] - mx, xyz[nn[i, j], 1] - my, xyz[nn[i, j], 2] - mz
            sxx += dx * dx
            sxy += dx * dy
            sxz += dx * dz
            syy += dy * dy
            syz += dy * dz
            szz += dz * dz
        C[0, 0], C[0, 1], C[0, 2] = sxx, sxy, sxz
        C[1, 0], C[1, 1], C[1, 2] = sxy, syy, syz
        C[2, 0], C[2, 1], C[2, 2] = sxz, syz, szz
        _least_axis(C, out[i])


@njit(cache=True, nogil=True)
def _least_axis(C, out):
    """out <- the unit eigenvector of the symmetric 3 x 3 C with the least eigenvalue: the eigenvalue in closed
    form (the trigonometric solution of the characteristic cubic), the vector as the largest cross product of two
    rows of C - λ I. Where those vanish there is no single least axis: `_any_least_axis`. A fraction of LAPACK
    eigh's cost, and no eigh to compile (a second of a cold cache's first start)."""
    q = (C[0, 0] + C[1, 1] + C[2, 2]) / 3.0
    p1 = C[0, 1] ** 2 + C[0, 2] ** 2 + C[1, 2] ** 2
    p2 = (C[0, 0] - q) ** 2 + (C[1, 1] - q) ** 2 + (C[2, 2] - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    least = q
    if p > 1e-12 * abs(q):
        b00, b11, b22 = (C[0, 0] - q) / p, (C[1, 1] - q) / p, (C[2, 2] - q) / p
        b01, b02, b12 = C[0, 1] / p, C[0, 2] / p, C[1, 2] / p
        r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
        least = q + 2.0 * p * np.cos(np.arccos(min(1.0, max(-1.0, r))) / 3.0 + 2.0 * np.pi / 3.0)
        a00, a11, a22 = C[0, 0] - least, C[1, 1] - least, C[2, 2] - least
        a01, a02, a12 = C[0, 1], C[0, 2], C[1, 2]
        # the rows (a00, a01, a02), (a01, a11, a12), (a02, a12, a22): their three cross products
        wx, wy, wz = a01 * a12 - a02 * a11, a02 * a01 - a00 * a12, a00 * a11 - a01 * a01
        size = wx * wx + wy * wy + wz * wz
        ux, uy, uz = a01 * a22 - a02 * a12, a02 * a02 - a00 * a22, a00 * a12 - a01 * a02
        n = ux * ux + uy * uy + uz * uz
        if n > size:
            wx, wy, wz, size = ux, uy, uz, n
        ux, uy, uz = a11 * a22 - a12 * a12, a12 * a02 - a01 * a22, a01 * a12 - a11 * a02
        n = ux * ux + uy * uy + uz * uz
        if n > size:
            wx, wy, wz, size = ux, uy, uz, n
        if size > 1e-12 * p2 * p2:
            size = np.sqrt(size)
            out[0], out[1], out[2] = wx / size, wy / size, wz / size
            return
    _any_least_axis(C, least, out)


@njit(cache=True, nogil=True)
def _any_least_axis(C, least, out):
    """out <- a unit vector of the least eigenvalue's eigenspace of the symmetric 3 x 3 C where that is a plane or
    all of space (points on a line, or all alike: no surface normal to find, any will do). The rows of C - least I
    then lie along one direction a: the unit vector across a, a × the axis a is least along; where they all vanish
    (C is least I), the first axis, as LAPACK's eigh returns."""
    ax = ay = az = 0.0  # the row of C - least I farthest from naught
    size = 0.0
    for i in range(3):
        rx, ry, rz = C[i, 0] - least * (i == 0), C[i, 1] - least * (i == 1), C[i, 2] - least * (i == 2)
        n = rx * rx + ry * ry + rz * rz
        if n > size:
            ax, ay, az, size = rx, ry, rz, n
    k = 0  # the axis a is least along: a × it is well away from naught
    if abs(ay) < abs(ax):
        k = 1
    if abs(az) < min(abs(ax), abs(ay)):
        k = 2
    out[0] = out[1] = out[2] = 0.0
    out[k] = 1.0
    if size == 0.0:  # (a is naught: the first axis)
        return
    wx, wy, wz = ay * out[2] - az * out[1], az * out[0] - ax * out[2], ax * out[1] - ay * out[0]
    size = math.sqrt(wx * wx + wy * wy + wz * wz)
    out[0], out[1], out[2] = wx / size, wy / size, wz / size


@njit(cache=True, nogil=True)
def _linearize(src, src_normals, tgt, tgt_normals, nn, found, R, t, eps, H, b, Ms):
    """H, b <- Σ Jᵀ M J, Σ Jᵀ M r over the found pairs (J = ∂r/∂δ = [R [p]x, -R],
    M = (C_q + R C_p Rᵀ)⁻¹, r = q - (R p + t)), Ms[i] <- M of pair i; returns (Σ rᵀ M r, pairs)."""
    H[:] = 0.0
    b[:] = 0.0
    error, count = 0.0, 0
    J = np.empty((3, 6))
    C = np.empty((3, 3))
    M = np.empty((3, 3))
    ns = np.empty(3)
    r = np.empty(3)
    MJ = np.empty((3, 6))
    Mr = np.empty(3)
    for i in range(len(src)):
        if not found[i]:
            continue
        count += 1
        j = nn[i]
        for a in range(3):
            # the source's normal in the map frame (R C_p Rᵀ = I - (1 - eps) (R n)(R n)ᵀ), and r = q - (R p + t)
            ns[a] = R[a, 0] * src_normals[i, 0] + R[a, 1] * src_normals[i, 1] + R[a, 2] * src_normals[i, 2]
            r[a] = tgt[j, a] - (R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a])
        for a in range(3):
            for c in range(3):
                C[a, c] = (2.0 if a == c else 0.0) - (1.0 - eps) * (tgt_normals[j, a] * tgt_normals[j, c]
                                                                    + ns[a] * ns[c])
        # the inverse of a symmetric 3 x 3 by its cofactors
        M[0, 0] = C[1, 1] * C[2, 2] - C[1, 2] * C[2, 1]
        M[0, 1] = C[0, 2] * C[2, 1] - C[0, 1] * C[2, 2]
        M[0, 2] = C[0, 1] * C[1, 2] - C[0, 2] * C[1, 1]
        M[1, 1] = C[0, 0] * C[2, 2] - C[0, 2] * C[2, 0]
        M[1, 2] = C[0, 2] * C[1, 0] - C[0, 0] * C[1, 2]
        M[2, 2] = C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0]
        M[1, 0], M[2, 0], M[2, 1] = M[0, 1], M[0, 2], M[1, 2]
        det = C[0, 0] * M[0, 0] + C[0, 1] * M[1, 0] + C[0, 2] * M[2, 0]
        for a in range(3):  # (as loops: an array expression costs numba seconds to compile, a cold cache's start)
            for c in range(3):
                M[a, c] /= det
                Ms[i, a, c] = M[a, c]
        # J = [R [p]x, -R]: column k of R [p]x is R (p x e_k)
        x, y, z = src[i, 0], src[i, 1], src[i, 2]
        for a in range(3):
            J[a, 0] = R[a, 1] * z - R[a, 2] * y
            J[a, 1] = R[a, 2] * x - R[a, 0] * z
            J[a, 2] = R[a, 0] * y - R[a, 1] * x
            J[a, 3], J[a, 4], J[a, 5] = -R[a, 0], -R[a, 1], -R[a, 2]
        for a in range(3):
            Mr[a] = M[a, 0] * r[0] + M[a, 1] * r[1] + M[a, 2] * r[2]
            for v in range(6):
                MJ[a, v] = M[a, 0] * J[0, v] + M[a, 1] * J[1, v] + M[a, 2] * J[2, v]
        for u in range(6):
            for v in range(u, 6):
                H[u, v] += J[0, u] * MJ[0, v] + J[1, u] * MJ[1, v] + J[2, u] * MJ[2, v]
            b[u] += J[0, u] * Mr[0] + J[1, u] * Mr[1] + J[2, u] * Mr[2]
        error += r[0] * Mr[0] + r[1] * Mr[1] + r[2] * Mr[2]
    for u in range(6):
        for v in range(u):
            H[u, v] = H[v, u]
    return error, count


@njit(cache=True, nogil=True)
def _pair_error(src, tgt, nn, found, Ms, R, t):
    """Σ rᵀ M r of the pairs `_linearize` made, their M kept, under another pose (R, t)."""
    error = 0.0
    r = np.empty(3)
    for i in range(len(src)):
        if not found[i]:
            continue
        for a in range(3):
            r[a] = tgt[nn[i], a] - (R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a])
        for a in range(3):
            error += r[a] * (Ms[i, a, 0] * r[0] + Ms[i, a, 1] * r[1] + Ms[i, a, 2] * r[2])
    return error
