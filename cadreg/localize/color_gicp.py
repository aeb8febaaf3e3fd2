"""Colour-supported GICP after Korn, Holzkothen & Pauli (2014), written by hand.

No library offers it: small_gicp has GICP without colour, Open3D's coloured ICP (Park et al. 2017) is a
point-to-plane + photometric-gradient method, not GICP. Korn et al. search correspondences in a joint space of
position and L*a*b* colour (here a 6-D KD-tree on [x, y, z, λ·L/100, λ·a/100, λ·b/100]) and minimise the GICP
plane-to-plane cost Σ rᵀ (C_q + R C_p Rᵀ)⁻¹ r with per-point covariances (Segal et al. 2009). Multi-scale,
coarse to fine; each scale stops when the update is below ε.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .grid_gicp import plane_covariance, plane_normals
from .points import voxel_indices


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """(n, 3) sRGB in [0, 1] -> (n, 3) CIE L*a*b* (D65), L in [0, 100]."""
    return linear_to_lab(srgb_to_linear(rgb))


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """(n, 3) sRGB in [0, 1] -> (n, 3) linear light (the sRGB transfer curve undone)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)


def linear_to_lab(lin: np.ndarray) -> np.ndarray:
    """(n, 3) linear-light RGB (sRGB primaries) -> (n, 3) CIE L*a*b* (D65), L in [0, 100]."""
    M = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]])
    xyz = np.asarray(lin, dtype=np.float64) @ M.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 216 / 24389, np.cbrt(xyz), (24389 / 27 * xyz + 16) / 116)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)


def plane_covariances(xyz: np.ndarray, tree: cKDTree | None = None, k: int = 10) -> np.ndarray:
    """(n, 3) points -> (n, 3, 3) GICP covariances: the k-neighbourhood's axes with eigenvalues (1, 1, PLANE_EPS)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    return plane_covariance(plane_normals(xyz, tree or cKDTree(xyz), np.arange(len(xyz)), k))


@dataclass
class GicpCloud:
    """One scale of a cloud: xyz (n, 3) float64, lab (n, 3) float64, cov (n, 3, 3) float64, its own frame."""

    xyz: np.ndarray
    lab: np.ndarray
    cov: np.ndarray
    voxel_m: float


def prepare_cloud(xyz: np.ndarray, rgb: np.ndarray, voxel_m: float, k: int = 10) -> GicpCloud:
    """Down-sample to one point per voxel and compute Lab colours and plane covariances."""
    keep = voxel_indices(xyz, voxel_m)
    p = np.asarray(xyz, dtype=np.float64)[keep]
    return GicpCloud(p, rgb_to_lab(rgb[keep]), plane_covariances(p, k=k), voxel_m)


class ColorGicpTarget:
    """A map scale with its 6-D (position + weighted colour) KD-tree, built once per site."""

    def __init__(self, cloud: GicpCloud, color_weight_m: float) -> None:
        self.cloud = cloud
        self.color_weight_m = float(color_weight_m)
        self.tree = cKDTree(np.hstack([cloud.xyz, cloud.lab * (color_weight_m / 100.0)]))


@dataclass
class GicpOutcome:
    T_target_source: np.ndarray
    H: np.ndarray  # (6, 6) Gauss-Newton Hessian over (rx, ry, rz, tx, ty, tz), left perturbation in the target frame
    error: float  # Σ rᵀ M r over the final correspondences
    inliers: int
    iterations: int
    converged: bool


def _skew_batch(p: np.ndarray) -> np.ndarray:
    S = np.zeros((len(p), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -p[:, 2], p[:, 1]
    S[:, 1, 0], S[:, 1, 2] = p[:, 2], -p[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -p[:, 1], p[:, 0]
    return S


def align_scale(target: ColorGicpTarget, source: GicpCloud, T_init: np.ndarray, *, max_correspondence_m: float,
                epsilon: float = 1e-3, max_iterations: int = 30) -> GicpOutcome:
    """Gauss-Newton colour GICP at one scale. T_init, result: (4, 4) T_target_source."""
    T = np.array(T_init, dtype=np.float64)
    src_feat_col = source.lab * (target.color_weight_m / 100.0)
    H = np.zeros((6, 6))
    error, inliers, it, converged = 0.0, 0, 0, False
    for it in range(1, max_iterations + 1):
        R, t = T[:3, :3], T[:3, 3]
        p = source.xyz @ R.T + t
        # Joint-space search; the bound also caps the colour term, then the spatial distance is checked alone.
        d, nn = target.tree.query(np.hstack([p, src_feat_col]), k=1, distance_upper_bound=2.0 * max_correspondence_m)
        ok = np.isfinite(d)
        nn = np.where(ok, nn, 0)
        q = target.cloud.xyz[nn]
        r = q - p
        ok &= np.einsum("ni,ni->n", r, r) < max_correspondence_m ** 2
        inliers = int(ok.sum())
        if inliers < 6:
            break
        r, pm = r[ok], p[ok]
        C = target.cloud.cov[nn[ok]] + R @ source.cov[ok] @ R.T
        M = np.linalg.inv(C)
        J = np.concatenate([_skew_batch(pm), -np.broadcast_to(np.eye(3), (len(pm), 3, 3))], axis=2)  # (m, 3, 6)
        MJ = M @ J
        H = np.einsum("mki,mkj->ij", J, MJ)
        g = np.einsum("mki,mk->i", MJ, r)
        error = float(np.einsum("mi,mij,mj->", r, M, r))
        try:
            xi = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        dT = np.eye(4)
        dT[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
        dT[:3, 3] = xi[3:]
        T = dT @ T
        if np.linalg.norm(xi) < epsilon:
            converged = True
            break
    return GicpOutcome(T, H, error, inliers, it, converged)


def color_gicp(targets: list[ColorGicpTarget], sources: list[GicpCloud], T_init: np.ndarray, *,
               correspondence_factor: float = 3.0, epsilon: float = 1e-3, max_iterations: int = 30) -> GicpOutcome:
    """Coarse-to-fine over paired scales (targets[i] with sources[i]); max correspondence = factor × voxel."""
    T = np.asarray(T_init, dtype=np.float64)
    out: GicpOutcome | None = None
    iterations = 0
    for tgt, src in zip(targets, sources):
        out = align_scale(tgt, src, T, max_correspondence_m=correspondence_factor * max(src.voxel_m, tgt.cloud.voxel_m),
                          epsilon=epsilon, max_iterations=max_iterations)
        iterations += out.iterations
        T = out.T_target_source
    assert out is not None
    out.iterations = iterations
    return out
