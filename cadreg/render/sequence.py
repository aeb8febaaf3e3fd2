"""Render a recorded-frames folder (ScanNet layout) of query frames from a labelled mesh."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ..camera import CameraIntrinsics
from ..config import NoiseConfig, RenderConfig
from ..errors import ConfigError, InvalidFrame
from ..io.frames import FramesWriter
from .mesh import LabelledMesh
from .noise import depth_range_m
from .poses import WALK_MIN_LEG_M, WALK_MIN_STEP_M, Placement, PoseSampler, walk
from .raycast import MeshRenderer, View, camera_rig


@dataclass
class RenderedFrame:
    """index : frame number in the folder; T_map_camera : (4, 4) colour camera -> map;
    valid_fraction : share of depth pixels with a (noiseless) reading; visible_objects : instances seen."""

    index: int
    T_map_camera: np.ndarray
    valid_fraction: float
    visible_objects: int


def count_visible_objects(view: View, min_fraction: float) -> int:
    """Object instances covering at least `min_fraction` of the image (0 when the mesh has no labels)."""
    if view.instances is None:
        return 0
    ids = view.instances[view.instances >= 0]
    if ids.size == 0:
        return 0
    counts = np.bincount(ids)
    return int(np.count_nonzero(counts >= min_fraction * view.instances.size))


def valid_share(depth_m: np.ndarray, min_z: float, max_z: float) -> float:
    """The share of a depth image's pixels (z-depth, metres, inf where nothing) on a surface within the sensor's range
    [min_z, max_z]: a view's check."""
    return float(np.mean(np.isfinite(depth_m) & (depth_m >= min_z) & (depth_m <= max_z)))


def _walk_view_share(renderer: MeshRenderer, coarse: CameraIntrinsics, T_color_depth: np.ndarray, min_z: float,
                     max_z: float, T_map_camera: np.ndarray) -> float:
    """`valid_share` of the depth camera at T_map_camera (colour camera -> map) cast at a low resolution (`coarse`):
    a walk's view check, made for each of its candidate steps."""
    return valid_share(renderer.cast(coarse, T_map_camera @ T_color_depth, with_color=False).depth_m, min_z, max_z)


def render_frames(
    mesh: LabelledMesh,
    out_dir: str | Path,
    n: int,
    *,
    seed: int = 0,
    config: RenderConfig = RenderConfig(),
    noise: NoiseConfig | None = NoiseConfig(),
    poses: Sequence[np.ndarray] | None = None,
    walk_step_m: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[RenderedFrame]:
    """Render `n` frames into `out_dir` (ScanNet export layout, pose/<i>.txt = T_map_camera of the colour camera).

    With `poses` given, those poses are rendered as they are (n = len(poses) when n <= 0); otherwise poses are
    sampled by `PoseSampler` and a view is kept when its valid depth share and visible object count pass the
    config. With `walk_step_m`, only the first pose is sampled so; the others follow it, `walk_step_m` apart, as one
    camera carried through the room (`poses.walk`). Deterministic for a given seed. noise None = noiseless.
    """
    depth_intr, color_intr, T_color_depth = camera_rig(config)
    if poses is None and config.min_visible_objects > 0 and mesh.labels is None:
        raise ConfigError("min_visible_objects > 0 needs a mesh with per-vertex labels (or set it to 0)")
    if poses is not None and n <= 0:
        n = len(poses)
    if n <= 0:
        raise ConfigError(f"number of frames must be positive, got {n}")
    if walk_step_m is not None and (poses is not None or not WALK_MIN_STEP_M <= walk_step_m <= WALK_MIN_LEG_M):
        raise ConfigError(f"a walk takes no given poses and a step of {WALK_MIN_STEP_M:g}-{WALK_MIN_LEG_M:g} m, "
                          f"got {walk_step_m} m")
    rng = np.random.default_rng(seed)
    renderer = MeshRenderer(mesh)
    sampler = PoseSampler(renderer, config) if poses is None else None
    writer = FramesWriter(
        out_dir, depth_intr, color_intr, T_color_depth, depth_scale=1000.0, label_set=mesh.label_set,
        color_format=config.color_format, depth_range_m=depth_range_m(noise),
    )
    min_z = noise.min_depth_m if noise is not None else 0.0
    max_z = noise.max_depth_m if noise is not None else np.inf
    out: list[RenderedFrame] = []
    start: Placement | None = None  # a walk's first placement, once its view is drawn and rendered
    walked: list[Placement] | None = None  # ... and then the walk from it
    failures = 0
    while len(out) < n:
        i = len(out)
        given = poses is not None or walked is not None  # rendered as they are, no view checks
        if poses is not None:
            T = np.asarray(poses[i], dtype=np.float64)
        elif walked is not None:
            T = walked[i].pose()
        else:
            start = sampler.draw(rng)  # type: ignore[union-attr]
            if start is None:
                raise ConfigError("no camera position inside the room passes the height/clearance checks")
            T = start.pose()
        # Judge a sampled view on the depth camera's cast (labels included) before paying for the colour camera.
        dview = renderer.cast(depth_intr, T @ T_color_depth, with_color=True)
        z = dview.depth_m
        valid_fraction = valid_share(z, min_z, max_z)
        visible = count_visible_objects(dview, config.min_object_fraction)
        if not given and (valid_fraction < config.min_valid_fraction or visible < config.min_visible_objects):
            failures += 1
            if failures >= config.max_attempts_per_frame:
                raise ConfigError(
                    f"{failures} sampled views in a row failed (valid depth >= {config.min_valid_fraction}, "
                    f">= {config.min_visible_objects} visible objects): relax the render settings"
                )
            continue
        try:
            frame, _, _ = renderer.render_frame(
                T, depth_intr, color_intr, T_color_depth, rng=rng, noise=noise, frame_id=str(i), depth_view=dview
            )
        except InvalidFrame as exc:  # noise left no depth: a sampled view to redraw, a given pose to report
            if given:
                raise ConfigError(f"pose {i} sees no surface in the sensor's range: {exc.message}") from exc
            failures += 1
            if failures >= config.max_attempts_per_frame:
                raise ConfigError(f"{failures} sampled views in a row saw no surface") from exc
            continue
        failures = 0
        writer.write(i, frame, T)
        out.append(RenderedFrame(i, T, valid_fraction, visible))
        if walk_step_m is not None and walked is None and start is not None:
            sees = partial(_walk_view_share, renderer,
                           depth_intr.scaled_to(depth_intr.width // 8, depth_intr.height // 8), T_color_depth, min_z, max_z)
            walked = walk(sampler, start, rng, n, step_m=walk_step_m, sees=sees)  # type: ignore[arg-type]
        if progress is not None:
            progress(len(out), n)
    return out
