"""`cadreg bench`: several methods on the same recorded frames, with a summary table and optional JSON. A building's
frames (`cadreg render --layout`) carry FRAMES/views.json: then the summary also splits unique and repeated views."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from tqdm import tqdm

log = logging.getLogger("cadreg.bench")


def register(sub) -> None:
    from ..bench_methods import METHODS

    p = sub.add_parser("bench", help="benchmark localization methods on recorded frames with ground-truth poses",
                       description="Run each --method on the same frames; time is per frame on this process "
                                   "(run with OMP_NUM_THREADS=1 for one-core figures).")
    p.add_argument("--site", required=True, type=Path, help="site bundle directory")
    p.add_argument("--frames", required=True, type=Path, help="recorded frames folder (poses = ground truth)")
    p.add_argument("--method", action="extend", nargs="+", choices=METHODS, metavar="NAME",
                   help=f"one or more (`--method a b` or `--method a --method b`) of {', '.join(METHODS)} "
                        "(default: cadreg)")
    p.add_argument("--range", dest="index_range", default=None, metavar="A:B",
                   help="only frames whose number i has A <= i < B (e.g. 250:500 for 7-Scenes queries)")
    p.add_argument("--limit", type=int, default=None, help="first N frames only (after --range)")
    p.add_argument("--map-points", choices=("raw", "enhanced", "both"), default=None,
                   help="which map the refinement uses (default: RefineConfig.map_points)")
    p.add_argument("--localize-config", type=Path, default=None, metavar="FILE",
                   help="LocalizeConfig as TOML or JSON (as `cadreg serve --localize-config`); --map-points overrides it")
    p.add_argument("--truth", type=Path, default=None, metavar="DIR",
                   help="ground truth from DIR/<index>.txt (4x4 T_map_camera, e.g. `cadreg site fuse --write-poses`: "
                        "where the map puts each frame) instead of the frames' recorded poses; frames without one "
                        "are skipped")
    p.add_argument("--room", default=None, metavar="LAYOUT:NAME",
                   help="the frames were taken in room NAME of the building `cadreg site compose LAYOUT` made: their "
                        "ground truth (recorded, or --truth), in the room's own frame, is moved into the building's "
                        "by the room's T_building_room (e.g. real 7-Scenes frames in a building holding their "
                        "fused kitchen)")
    p.add_argument("--label-noise", choices=("none", "mild", "harsh"), default="none",
                   help="a segmenter's errors in the labels the labelled methods get, seeded per frame (label_noise.py): "
                        "mild = boundaries misregistered by up to 3 px and bleeding; harsh = 6 px, classes swapped "
                        "(15 %%) and missed (20 %%), false blobs and 5 %% speckle (default: none, the frames' labels)")
    p.add_argument("--color-noise", choices=("none", "camera"), default="none",
                   help="a camera's colour faults in the colour every method gets, seeded per frame (color_noise.py): "
                        "camera = exposure 0.6-1.4, white balance 1 ± 0.25 a channel, tone curve γ 0.6-1.6, offsets "
                        "up to 8 %%, blur up to 2.5 px, colour up to 6 px off the depth, noise σ 3 %% (default: none)")
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbations of refine-from-gt-perturbed "
                   "and of the label and colour noise")
    p.add_argument("--json", type=Path, default=None, help="write the report as JSON here")
    p.set_defaults(func=run)


def read_views(frames_dir: Path):
    """Frame index -> ViewTruth from FRAMES/views.json, or None when the folder has none."""
    from ..bench import views_from_doc
    from ..errors import InvalidArgument, InvalidFileError

    path = frames_dir / "views.json"
    if not path.is_file():
        return None
    try:
        return views_from_doc(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, InvalidArgument) as exc:
        raise InvalidFileError(path, str(exc)) from None


def truth_in_building(room: str, frames, truth: dict | None) -> dict:
    """Frame index -> T_building_camera: each frame's ground truth in its room's frame (`truth`, else the recorded
    pose; frames with neither are left out) moved by T_building_room of the room `room` ("LAYOUT:NAME") names."""
    import numpy as np

    from ..errors import ConfigError
    from ..site.compose import read_layout

    layout_path, sep, name = room.rpartition(":")
    if not sep or not layout_path or not name:
        raise ConfigError(f"--room must be LAYOUT:NAME, got {room!r}")
    entry = next((r for r in read_layout(layout_path).rooms if r.name == name), None)
    if entry is None:
        raise ConfigError(f"--room: no room {name!r} in {layout_path}")
    T_building_room = np.asarray(entry.T_building_room, dtype=np.float64)
    in_room = truth if truth is not None else {i: frames.pose(i) for i in frames.indices}
    return {i: T_building_room @ T for i, T in in_room.items() if T is not None}


def run(args: argparse.Namespace) -> int:
    from ..bench import format_table, run_bench
    from ..io.frames import RecordedFrames, read_indexed_poses
    from ..localize.localizer import Localizer
    from ..site.bundle import Site

    from ..config import LocalizeConfig, RefineConfig, load_localize_config
    from ..errors import ConfigError
    from ..color_noise import COLOR_NOISE_PRESETS
    from ..label_noise import LABEL_NOISE_PRESETS

    site = Site.load(args.site)
    frames = RecordedFrames.open(args.frames)
    if args.index_range:
        try:
            a, b = (int(x) for x in args.index_range.split(":"))
        except ValueError as exc:
            raise ConfigError(f"--range must be A:B with integers, got {args.index_range!r}") from exc
        frames.indices = [i for i in frames.indices if a <= i < b]
    methods = list(dict.fromkeys(args.method or ["cadreg"]))  # a method named twice runs once
    config = LocalizeConfig() if args.localize_config is None else load_localize_config(args.localize_config)
    if args.map_points:
        config = config.model_copy(update={"refine": RefineConfig(**{**config.refine.model_dump(), "map_points": args.map_points})})
    localizer = Localizer.from_site(site, config).warm()  # per-site structures now, not in a frame's time
    n = len(frames.indices) if args.limit is None else min(args.limit, len(frames.indices))
    bar = tqdm(total=n, desc="bench", unit="frame", file=sys.stderr)

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    views = read_views(args.frames)
    truth = None if args.truth is None else read_indexed_poses(args.truth)
    if args.room:
        truth = truth_in_building(args.room, frames, truth)
    noise = None if args.label_noise == "none" else LABEL_NOISE_PRESETS[args.label_noise]
    color_noise = None if args.color_noise == "none" else COLOR_NOISE_PRESETS[args.color_noise]
    report = run_bench(site, frames, methods, localizer=localizer, limit=args.limit, seed=args.seed,
                       progress=progress, warn=log.warning, views=views, truth=truth, label_noise=noise,
                       color_noise=color_noise)
    bar.close()
    print(format_table(report))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
    return 0
