"""`cadreg render`: rendered query frames (depth, colour, labels, poses) from a labelled mesh, a site's mesh, or the
rooms of a building layout (`--layout`, cadreg/render/building.py: views inside the rooms + views.json with the
repeated-view oracle)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from tqdm import tqdm

from ..config import NoiseConfig, RenderConfig
from ..errors import ConfigError

log = logging.getLogger("cadreg.render")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render RGB-D query frames from a labelled mesh",
        description="Ray-cast depth, colour and labels at hand-held camera poses inside the room (or at --poses) and "
                    "write a recorded-frames folder (ScanNet layout, pose/<i>.txt = T_map_camera). With --layout: "
                    "views inside the rooms of a building (pose = T_building_camera) and FRAMES/views.json saying "
                    "which other rooms repeat each view.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--site", type=Path, help="site bundle: renders the scan mesh it was built from (site.json "
                     "inputs), or a Poisson mesh of its points when that mesh is not at hand")
    src.add_argument("--mesh", type=Path, help="coloured mesh PLY (z up, metres)")
    p.add_argument("--labels", type=Path, help="PLY with the same vertices and a per-vertex 'label' (NYU40)")
    p.add_argument("--layout", type=Path, help="building LAYOUT.json (`cadreg site layout`): render inside its rooms; "
                   "--mesh/--labels is every room's mesh (default: the scan each room bundle was built from)")
    p.add_argument("--oracle-agreement", type=float, default=None,
                   help="with --layout: share of agreeing pixels that makes a view repeated (default 0.97)")
    p.add_argument("--mesh-out", type=Path, metavar="PLY",
                   help="with --layout: also write the building as one mesh (colours, and NYU40 'label' where the "
                        "rooms have them), as a scan of the whole building would be: `site build --scan PLY` makes "
                        "a site of it (--n 0: the mesh alone)")
    p.add_argument("--out", type=Path, help="frames folder to write (not needed for --layout --mesh-out --n 0: the "
                   "building's mesh alone)")
    p.add_argument("--n", type=int, default=0, help="number of frames (default: all --poses)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-noise", action="store_true", help="noiseless depth and colour")
    p.add_argument("--color-size", type=int, nargs=2, metavar=("W", "H"), help="colour camera size (default = depth)")
    p.add_argument("--baseline-m", type=float, help="depth -> colour offset along x when the sizes differ")
    p.add_argument("--height", type=float, nargs=2, metavar=("MIN_M", "MAX_M"), help="camera height above floor")
    p.add_argument("--pitch", type=float, nargs=2, metavar=("MIN_DEG", "MAX_DEG"), help="downward pitch range")
    p.add_argument("--min-visible-objects", type=int, help="keep views seeing at least this many objects")
    p.add_argument("--poses", type=Path, help="render these poses (file of stacked 4x4 or a folder) instead of sampling")
    p.add_argument("--walk", type=float, metavar="STEP_M", help="frames of one camera carried through the room, STEP_M "
                   "metres apart (0.05: a slow walk at 10 frames/s), from a first view sampled as usual: a stream "
                   "to track")
    p.add_argument("--jpg", action="store_true", help="write colour as JPEG (as ScanNet) instead of PNG")
    p.set_defaults(func=run)


def _mesh_paths_from_site(site_dir: Path) -> tuple[Path, Path | None] | None:
    """The scan mesh (and labels PLY) a site was built from, as recorded in its site.json `inputs`; None when the
    site records none that exists here (fused sites, bundles copied without their inputs)."""
    from ..io.bundle_files import read_json

    meta = read_json(site_dir / "site.json")
    inputs = meta.get("inputs") or {} if isinstance(meta, dict) else {}

    def _path(key: str) -> Path | None:
        v = inputs.get(key)
        if isinstance(v, dict):
            v = v.get("path")
        if not v:
            return None
        p = Path(v)
        # build_site records paths as it was given them: relative to where it ran, or to the bundle.
        return p if p.is_absolute() or p.exists() else (site_dir / p)

    scan, labels = _path("scan"), _path("labels")
    if scan is None or not scan.is_file():
        return None
    return scan, labels if labels is not None and labels.is_file() else None


def load_site_mesh(site_dir: Path):
    """(LabelledMesh, description) for `render --site`: the scan mesh the site was built from when it is still at
    hand (best: the real scan's geometry and colours), else a Poisson mesh of the site's raw points."""
    from ..render import LabelledMesh
    from ..render.mesh import mesh_from_site
    from ..site.bundle import Site

    paths = _mesh_paths_from_site(site_dir)
    if paths is not None:
        return LabelledMesh.from_ply(*paths), str(paths[0])
    log.warning("site %s records no scan mesh that exists here: rendering a Poisson mesh of its points", site_dir)
    return mesh_from_site(Site.load(site_dir)), f"poisson mesh of {site_dir}"


def run(args: argparse.Namespace) -> int:
    from ..io.frames import read_poses
    from ..render import LabelledMesh, render_frames

    overrides: dict = {}
    if args.color_size:
        overrides["color_width"], overrides["color_height"] = args.color_size
    if args.baseline_m is not None:
        overrides["baseline_m"] = args.baseline_m
    if args.height:
        overrides["height_min_m"], overrides["height_max_m"] = args.height
    if args.pitch:
        overrides["pitch_min_deg"], overrides["pitch_max_deg"] = args.pitch
    if args.min_visible_objects is not None:
        overrides["min_visible_objects"] = args.min_visible_objects
    if args.jpg:
        overrides["color_format"] = "jpg"
    try:
        config = RenderConfig(**overrides)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    if config.height_min_m > config.height_max_m or config.pitch_min_deg > config.pitch_max_deg:
        raise ConfigError("--height and --pitch take MIN MAX with MIN <= MAX")
    if args.out is None and not (args.layout is not None and args.mesh_out is not None and args.n == 0):
        raise ConfigError("--out is required: the frames folder to write")
    if args.walk is not None and args.poses is not None:
        raise ConfigError("give --walk or --poses, not both")
    if args.layout is not None:
        if args.walk is not None:
            raise ConfigError("--walk renders inside one room (--site or --mesh), not a --layout")
        return _render_layout(args, config)
    if args.site is None and args.mesh is None:
        raise ConfigError("give one of --site, --mesh or --layout")
    if args.site is not None:
        mesh, mesh_desc = load_site_mesh(args.site)
    else:
        mesh, mesh_desc = LabelledMesh.from_ply(args.mesh, args.labels), str(args.mesh)
    poses = read_poses(args.poses) if args.poses else None
    if poses is None and args.n <= 0:
        raise ConfigError("--n must be positive (or give --poses)")
    n = args.n if args.n > 0 else len(poses or [])
    if poses is not None:
        poses = poses[:n]
        n = len(poses)
    with tqdm(total=n, desc="render", unit="frame") as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        frames = render_frames(
            mesh, args.out, n, seed=args.seed, config=config,
            noise=None if args.no_noise else NoiseConfig(), poses=poses, walk_step_m=args.walk, progress=progress,
        )
    vis = [f.visible_objects for f in frames]
    print(json.dumps({
        "frames": len(frames), "out": str(args.out), "mesh": mesh_desc,
        "visible_objects": {"min": min(vis), "mean": round(sum(vis) / len(vis), 2), "max": max(vis)},
    }))
    return 0


def _layout_meshes(args: argparse.Namespace, layout) -> tuple[dict, dict, dict[str, str]]:
    """Per bundle string of the layout: (LabelledMesh, graph nodes, mesh description)."""
    from ..render import LabelledMesh
    from ..site.bundle import Site

    bundles = sorted({r.bundle for r in layout.rooms})
    if args.mesh is not None and len(bundles) > 1:
        raise ConfigError(f"--mesh gives one mesh but the layout has {len(bundles)} room bundles: leave --mesh out "
                          "to render each bundle's own scan")
    meshes, nodes, desc = {}, {}, {}
    for bundle in bundles:
        bundle_dir = args.layout.parent / bundle
        nodes[bundle] = Site.load(bundle_dir).graph.nodes
        if args.mesh is not None:
            meshes[bundle], desc[bundle] = LabelledMesh.from_ply(args.mesh, args.labels), str(args.mesh)
        else:
            meshes[bundle], desc[bundle] = load_site_mesh(bundle_dir)
    return meshes, nodes, desc


def _render_layout(args: argparse.Namespace, config) -> int:
    """`render --layout`: views inside the building's rooms, and views.json (written here, not in the core)."""
    import time

    from ..render.building import OracleConfig, building_mesh, building_rooms, render_building_views
    from ..site.compose import read_layout

    if args.site is not None or args.poses is not None:
        raise ConfigError("--layout renders sampled views inside its rooms: no --site or --poses with it")
    if args.n < 0 or (args.n == 0 and args.mesh_out is None):
        raise ConfigError("--n must be positive (0 only with --mesh-out)")
    try:
        oracle = OracleConfig() if args.oracle_agreement is None else OracleConfig(min_agreement=args.oracle_agreement)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    t0 = time.perf_counter()
    layout = read_layout(args.layout)
    meshes, nodes, desc = _layout_meshes(args, layout)
    rooms = building_rooms(layout, meshes, nodes)
    if args.mesh_out is not None:
        building_mesh(rooms).write_ply(args.mesh_out)
        if args.n == 0:
            print(json.dumps({"mesh_out": str(args.mesh_out), "rooms": len(rooms)}))
            return 0
    with tqdm(total=args.n, desc="render", unit="frame") as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        views = render_building_views(rooms, args.out, args.n, seed=args.seed, config=config,
                                      noise=None if args.no_noise else NoiseConfig(), oracle=oracle, progress=progress)
    doc = {"site_id": layout.site_id, "layout": str(args.layout.resolve()), "seed": args.seed,
           "oracle": oracle.model_dump(),
           "rooms": {r.name: {"bundle": r.bundle, "T_building_room": r.T_building_room.tolist()}
                     | ({"corridor": True} if r.corridor else {}) for r in rooms},
           "views": [v.to_dict() for v in views]}
    (args.out / "views.json").write_text(json.dumps(doc))
    repeated = sum(bool(v.repeated_in) for v in views)
    corridor = sum(v.corridor for v in views)
    print(json.dumps({"frames": len(views), "out": str(args.out), "rooms": sum(not r.corridor for r in rooms),
                      "corridors": sum(r.corridor for r in rooms), "rooms_seen": len({v.room for v in views}),
                      "repeated": repeated, "unique": len(views) - repeated, "corridor_views": corridor,
                      "mesh": sorted(set(desc.values())), "elapsed_s": round(time.perf_counter() - t0, 1)}))
    return 0


# --- `cadreg site fuse` (registered by site_cmd.py under `cadreg site`) ------------------------------------------


def register_site_fuse(site_sub: argparse._SubParsersAction) -> None:
    f = site_sub.add_parser(
        "fuse", help="build a site bundle by TSDF fusion of recorded frames with poses",
        description="TSDF-fuse a recorded-frames folder (ScanNet or 7-Scenes layout) at its poses; labels, when the "
                    "frames carry them, are voted onto the fused points and become clustered object nodes.",
    )
    f.add_argument("--frames", required=True, type=Path, help="recorded-frames folder with poses")
    f.add_argument("--range", dest="frame_range", help="A:B = frames with index A <= i < B (default: all)")
    f.add_argument("--out", required=True, type=Path, help="bundle directory to write")
    f.add_argument("--site-id", help="site id (default: the frames folder's name)")
    f.add_argument("--voxel-m", type=float, help="TSDF voxel size in metres")
    f.add_argument("--depth-max-m", type=float, help="depth beyond this is not fused")
    f.add_argument("--check-range", metavar="A:B",
                   help="held-out frames to check the map with: median and p90 distance of their depth, at their "
                        "poses, to the fused map (e.g. 250:500 when fusing 0:250), and how far their recorded poses "
                        "disagree with it (their fused surface registered onto the map: pose_offset)")
    f.add_argument("--check-window", type=int, metavar="N",
                   help="with --check-range: pose_offset of each N consecutive held-out frames as well, and how many "
                        "frames' recorded poses lie more than 5 cm from where the map puts them (pose_offset_windows)")
    f.add_argument("--write-poses", type=Path, metavar="DIR",
                   help="with --check-window: write DIR/<index>.txt, the 4x4 pose where the map puts each held-out "
                        "frame of a window that lies on the map (fitness >= 0.5), for `cadreg bench --truth DIR`")
    f.add_argument("--auto-cad", action="store_true",
                   help="align the --cad-root library's CAD models to the labelled instances (frames need labels); "
                        "writes them to SITE/auto_cad.scan2cad.json")
    f.add_argument("--cad-root", type=Path, help="ShapeNet-style CAD library for --auto-cad")
    f.set_defaults(func=_site_fuse)


def parse_range(text: str | None, indices: list[int]) -> list[int]:
    """'A:B' -> the indices i with A <= i < B (either end may be left out); None -> all."""
    if not text:
        return list(indices)
    parts = text.split(":")
    if len(parts) != 2:
        raise ConfigError(f"--range must be A:B, got {text!r}")
    try:
        lo = int(parts[0]) if parts[0] else None
        hi = int(parts[1]) if parts[1] else None
    except ValueError:
        raise ConfigError(f"--range must be A:B with integers, got {text!r}") from None
    out = [i for i in indices if (lo is None or i >= lo) and (hi is None or i < hi)]
    if not out:
        raise ConfigError(f"--range {text} selects no frame")
    return out


def _site_fuse(args: argparse.Namespace) -> int:
    import sys

    from ..config import AutoCadConfig, FuseConfig
    from ..io.frames import RecordedFrames, write_indexed_poses
    from ..site.fuse import fuse_site, map_accuracy, pose_offset, pose_offset_by_window
    from .site_cmd import compile_site_loops, write_auto_cad

    if args.auto_cad and args.cad_root is None:
        raise ConfigError("--auto-cad needs --cad-root")
    frames = RecordedFrames.open(args.frames)
    if args.auto_cad and not frames.has_labels():
        raise ConfigError(f"--auto-cad needs labelled frames: {frames.root} has no label images")
    indices = parse_range(args.frame_range, frames.indices)
    check = parse_range(args.check_range, frames.indices) if args.check_range else []
    if args.check_window is not None and not check:
        raise ConfigError("--check-window needs --check-range")
    if args.write_poses is not None and args.check_window is None:
        raise ConfigError("--write-poses needs --check-window")
    overrides = {}
    if args.voxel_m is not None:
        overrides["voxel_size_m"] = args.voxel_m
    if args.depth_max_m is not None:
        overrides["depth_max_m"] = args.depth_max_m
    try:
        config = FuseConfig(**overrides)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    site_id = args.site_id or (frames.root.name if frames.root.name != "frames" else frames.root.parent.name)
    with tqdm(total=100, desc="site fuse", unit="%") as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        site = fuse_site(frames, indices, site_id=site_id, config=config, progress=progress,
                         cad_root=args.cad_root, auto_cad=AutoCadConfig() if args.auto_cad else None)
    site.save(args.out)
    compile_site_loops(site)
    report = {"site_id": site.site_id, "version": site.version, "frames": len(indices),
              "points": len(site.map), "nodes": len(site.graph.nodes), "out": str(args.out)}
    # stdout carries the one JSON report: the auto-CAD lines go to stderr
    path = write_auto_cad(site, args.out, file=sys.stderr)
    if args.auto_cad:
        report["auto_cad"] = {"cad_nodes": sum(1 for n in site.graph.nodes if n.source == "cad"),
                              "file": str(path)}
    if check:
        report["check"] = {"range": args.check_range, **map_accuracy(site.map.points, frames, check),
                           "pose_offset": pose_offset(site.map.points, site.map.normals, frames, check, config=config)}
        if args.check_window is not None:
            corrected: dict = {}  # frame index -> pose where the map puts it
            report["check"]["pose_offset_windows"] = pose_offset_by_window(
                site.map.points, site.map.normals, frames, check, args.check_window, config=config, corrected=corrected)
            if args.write_poses is not None:
                write_indexed_poses(args.write_poses, corrected)
                report["check"]["poses_written"] = {"frames": len(corrected), "dir": str(args.write_poses)}
    print(json.dumps(report))
    return 0
