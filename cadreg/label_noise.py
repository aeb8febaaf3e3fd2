"""Segmenter-like errors in a frame's label image, for the benchmark (`cadreg bench --label-noise`).

Rendered frames carry the map's own labels, exactly; a client's labels come from a segmenter, which misplaces
boundaries, confuses furniture classes, misses objects and sees some that are not there. The labelled path must
not turn those into confident wrong answers. Each kind of error, as a segmenter makes it:

- shift: the whole label image misregistered against depth by up to `shift_px` pixels each way (labels are made
  on colour, which the depth is registered to within a few pixels);
- bleed: each labelled segment grown over its border by 2 to `bleed_px` pixels, with probability `bleed`;
- swap: each class in view that the site's graph holds replaced, everywhere in the image, by another the graph
  holds, with probability `swap` (a chair called a table: it matches the wrong map nodes, the hardest case for a
  graph);
- drop: each class in view not swapped left unlabelled (0), with probability `drop` (walls and floors too);
- blobs: up to `blobs` discs (radius 10-40 px) of a random class the graph holds: false detections;
- speckle: this share of the pixels given a random class the graph holds.

Written here: the errors are a benchmark's model of a segmenter, not a library's augmentation (those perturb
images for training, not label maps by segment). Dilation is scipy's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from .errors import InvalidArgument

BLOB_RADIUS_PX = (10, 40)
MIN_BLEED_PX = 2


@dataclass(frozen=True)
class LabelNoise:
    """How wrong a segmenter's labels are (see the module's docstring for each kind)."""

    shift_px: int = 0
    bleed: float = 0.0
    bleed_px: int = 0
    swap: float = 0.0
    drop: float = 0.0
    blobs: int = 0
    speckle: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bleed", "swap", "drop", "speckle"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InvalidArgument(f"label noise {name} must lie in [0, 1], got {getattr(self, name)}")
        for name in ("shift_px", "bleed_px", "blobs"):
            if getattr(self, name) < 0:
                raise InvalidArgument(f"label noise {name} must be >= 0, got {getattr(self, name)}")

    def as_dict(self) -> dict:
        return asdict(self)


# `cadreg bench --label-noise NAME`: mild is a good segmenter's boundaries; harsh adds every kind of error at once.
LABEL_NOISE_PRESETS: dict[str, LabelNoise] = {
    "mild": LabelNoise(shift_px=3, bleed=0.5, bleed_px=4),
    "harsh": LabelNoise(shift_px=6, bleed=0.5, bleed_px=8, swap=0.15, drop=0.2, blobs=3, speckle=0.05),
}


def corrupt_labels(labels: np.ndarray, noise: LabelNoise, object_ids: np.ndarray,
                   rng: np.random.Generator) -> np.ndarray:
    """A copy of `labels` ((h, w) label ids, 0 unlabelled) with `noise`'s errors. object_ids : the label ids of the
    object classes the site's graph holds (what is swapped, and what swaps, blobs and speckle draw from; when empty
    they draw nothing)."""
    out = np.array(labels, copy=True)
    ids = np.asarray(object_ids, dtype=out.dtype)
    if noise.shift_px:
        dy, dx = rng.integers(-noise.shift_px, noise.shift_px + 1, 2)
        out = np.roll(out, (int(dy), int(dx)), axis=(0, 1))
    if noise.bleed and noise.bleed_px >= MIN_BLEED_PX:
        for c in _present(out):
            if rng.random() < noise.bleed:
                grown = ndimage.binary_dilation(out == c, iterations=int(rng.integers(MIN_BLEED_PX, noise.bleed_px + 1)))
                out[grown] = c
    swapped = out.copy()  # classes are swapped and dropped as the segmenter saw them, not one into another
    for c in _present(out):
        if ids.size and c in ids and rng.random() < noise.swap:
            others = ids[ids != c]
            if others.size:
                swapped[out == c] = rng.choice(others)
        elif rng.random() < noise.drop:
            swapped[out == c] = 0
    out = swapped
    if ids.size:
        h, w = out.shape
        yy, xx = np.ogrid[:h, :w]
        for _ in range(int(rng.integers(0, noise.blobs + 1)) if noise.blobs else 0):
            cy, cx, r = rng.integers(0, h), rng.integers(0, w), rng.integers(*BLOB_RADIUS_PX)
            out[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.choice(ids)
        if noise.speckle:
            speck = rng.random(out.shape) < noise.speckle
            out[speck] = rng.choice(ids, int(speck.sum()))
    return out


def _present(labels: np.ndarray) -> list[int]:
    """The labelled ids in an image (0 left out), in increasing order: the draws go class by class in that order."""
    return [int(c) for c in np.unique(labels) if c != 0]
