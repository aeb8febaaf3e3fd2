"""Kinect-like depth noise for rendered depth images.

Model (Nguyen, Izadi, Lovell 2012 for the axial part; the dropout terms mimic structured-light sensors):
axial σ(z) = a + b·(z − z0)², losses on depth discontinuities (the projected pattern breaks there), at grazing
incidence (no pattern returns), at random, outside the sensor's range; then quantised to the depth unit.
"""

from __future__ import annotations

import numpy as np

from ..camera import axial_noise_sigma_m
from ..config import NoiseConfig


def depth_range_m(noise: NoiseConfig | None) -> float | None:
    """The range a frame rendered with `noise` says its camera has (`Frame.depth_range_m`): the model's cut-off;
    None without noise (a noiseless render measures every surface, however far)."""
    return None if noise is None else noise.max_depth_m


def axial_sigma_m(z_m: np.ndarray, config: NoiseConfig = NoiseConfig()) -> np.ndarray:
    """σ of the depth noise (metres) at depth z_m (metres), elementwise."""
    return axial_noise_sigma_m(z_m, config.axial_a_m, config.axial_b_per_m, config.axial_z0_m)


def depth_edges(depth_m: np.ndarray, jump_m: float) -> np.ndarray:
    """(H, W) bool: pixels next to a 4-neighbour more than `jump_m` away in depth, or next to no depth.

    depth_m : (H, W) float metres, 0 or non-finite = invalid.
    """
    d = np.where(np.isfinite(depth_m), depth_m, 0.0)
    valid = d > 0
    edge = np.zeros(d.shape, dtype=bool)
    for axis in (0, 1):
        a = np.take(d, np.arange(d.shape[axis] - 1), axis=axis)
        b = np.take(d, np.arange(1, d.shape[axis]), axis=axis)
        va = np.take(valid, np.arange(d.shape[axis] - 1), axis=axis)
        vb = np.take(valid, np.arange(1, d.shape[axis]), axis=axis)
        jump = (np.abs(a - b) > jump_m) | (va != vb)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis] = slice(0, d.shape[axis] - 1)
        hi[axis] = slice(1, d.shape[axis])
        edge[tuple(lo)] |= jump
        edge[tuple(hi)] |= jump
    return edge & valid


def apply_depth_noise(
    depth_m: np.ndarray,
    cos_incidence: np.ndarray,
    rng: np.random.Generator,
    config: NoiseConfig = NoiseConfig(),
) -> np.ndarray:
    """Noisy depth in metres.

    depth_m : (H, W) float metres (z along the optical axis), 0 or non-finite = no surface.
    cos_incidence : (H, W) float, |cos| of the angle between the viewing ray and the surface normal.
    Returns (H, W) float64 metres, 0 = invalid (dropped or out of range); not yet quantised.
    """
    z = np.where(np.isfinite(depth_m), depth_m, 0.0).astype(np.float64)
    valid = z > 0
    drop = np.zeros(z.shape, dtype=bool)
    edges = depth_edges(z, config.edge_jump_m)
    drop |= edges & (rng.random(z.shape) < config.edge_dropout_p)
    angle = np.degrees(np.arccos(np.clip(np.abs(cos_incidence), 0.0, 1.0)))
    span = max(config.grazing_full_deg - config.grazing_start_deg, 1e-6)
    p_graze = np.clip((angle - config.grazing_start_deg) / span, 0.0, 1.0)
    drop |= rng.random(z.shape) < p_graze
    drop |= rng.random(z.shape) < config.random_dropout_p
    noisy = z + rng.standard_normal(z.shape) * axial_sigma_m(z, config)
    keep = valid & ~drop & (noisy >= config.min_depth_m) & (noisy <= config.max_depth_m)
    return np.where(keep, noisy, 0.0)


def apply_color_noise(color: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """(h, w, 3) uint8 colour with Gaussian noise of `sigma` 8-bit levels, clipped."""
    if sigma <= 0:
        return color
    noisy = color.astype(np.float32) + rng.standard_normal(color.shape, dtype=np.float32) * np.float32(sigma)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
