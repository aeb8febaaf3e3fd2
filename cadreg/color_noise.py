"""A real camera's colour faults in a frame's colour image, for the benchmark (`cadreg bench --color-noise`).

Rendered frames carry the map's own colours, exactly; a client's colour comes from a camera, whose exposure, white
balance and tone curve differ from those the map was fused with, whose colour is registered to its depth within a
few pixels, and whose pixels are noisy. The colour gate (`MatchConfig.min_chroma_correlation`) must hold back
answers of another place, not right ones under those faults. Each fault, drawn per frame:

- gamma: the tone curve, each channel raised to a power drawn from `gamma`;
- exposure: every channel scaled by a factor drawn from `exposure`;
- white balance: each channel scaled by its own factor within 1 ± `white_balance`;
- offset: each channel shifted by up to ± `offset` (black level);
- blur: a Gaussian blur of up to `blur_px` pixels (σ, drawn per axis);
- shift: the colour image misregistered against depth by up to `shift_px` pixels each way;
- noise: Gaussian noise of σ `noise` on every pixel and channel.

Values are in [0, 1] of full scale. Written here: a benchmark's model of a camera, in the order the camera makes the
faults (optics, then exposure and white balance, then the tone curve and noise of the pipeline); the blur is scipy's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from .errors import InvalidArgument


@dataclass(frozen=True)
class ColorNoise:
    """How a camera's colour differs from the map's (see the module's docstring for each fault)."""

    gamma: tuple[float, float] = (1.0, 1.0)
    exposure: tuple[float, float] = (1.0, 1.0)
    white_balance: float = 0.0
    offset: float = 0.0
    blur_px: float = 0.0
    shift_px: int = 0
    noise: float = 0.0

    def __post_init__(self) -> None:
        for name in ("gamma", "exposure"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi:
                raise InvalidArgument(f"colour noise {name} must be a range 0 < lo <= hi, got {(lo, hi)}")
        if not 0.0 <= self.white_balance < 1.0:
            raise InvalidArgument(f"colour noise white_balance must lie in [0, 1), got {self.white_balance}")
        for name in ("offset", "blur_px", "shift_px", "noise"):
            if getattr(self, name) < 0:
                raise InvalidArgument(f"colour noise {name} must be >= 0, got {getattr(self, name)}")

    def as_dict(self) -> dict:
        return asdict(self)


# `cadreg bench --color-noise NAME`: camera is every fault at once, each about as far as a consumer RGB-D camera's
# automatic exposure and white balance stray from the scan's (the colour gate's README figures).
COLOR_NOISE_PRESETS: dict[str, ColorNoise] = {
    "camera": ColorNoise(gamma=(0.6, 1.6), exposure=(0.6, 1.4), white_balance=0.25, offset=0.08, blur_px=2.5,
                         shift_px=6, noise=0.03),
}


def corrupt_colors(color: np.ndarray, noise: ColorNoise, rng: np.random.Generator) -> np.ndarray:
    """A copy of `color` ((h, w, 3) uint8) with `noise`'s faults, uint8."""
    x = np.asarray(color, dtype=np.float64) / 255.0
    if noise.blur_px:
        x = ndimage.gaussian_filter(x, (rng.uniform(0, noise.blur_px), rng.uniform(0, noise.blur_px), 0))
    if noise.shift_px:
        dy, dx = rng.integers(-noise.shift_px, noise.shift_px + 1, 2)
        x = np.roll(x, (int(dy), int(dx)), axis=(0, 1))
    x = x * rng.uniform(*noise.exposure) * rng.uniform(1.0 - noise.white_balance, 1.0 + noise.white_balance, 3)
    x = np.clip(x, 0.0, 1.0) ** rng.uniform(*noise.gamma)
    x = x + rng.uniform(-noise.offset, noise.offset, 3)
    if noise.noise:
        x = x + rng.normal(0.0, noise.noise, x.shape)
    return np.rint(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)
