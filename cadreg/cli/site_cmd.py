"""`cadreg site build | info | show | autocad-check`: build a site bundle, describe it, draw it, and measure automatic
CAD alignments against an annotation."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from ..config import PartitionConfig

AUTO_CAD_FILE = "auto_cad.scan2cad.json"  # written into the bundle folder by `site build --auto-cad`


def _progress_bar(desc: str):
    from tqdm import tqdm

    bar = tqdm(total=1, desc=desc, unit="step", leave=False, file=sys.stderr)

    def update(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def write_auto_cad(site, out: Path, file=None) -> Path | None:
    """Write the Scan2CAD file of a site built with auto-CAD into its bundle folder and print its notes and what
    it holds; None (nothing written) for a site built without, whose folder then holds no such file: one left by an
    earlier build into the folder listed CADs this site does not have, and is removed, saying so."""
    from ..io.scan2cad import write_scan2cad
    from ..site.build import auto_cad_document

    doc = auto_cad_document(site)
    path = Path(out) / AUTO_CAD_FILE
    if doc is None:
        if path.exists():
            path.unlink()
            print(f"removed {path}: an earlier build's automatic alignments, not this site's", file=file or sys.stderr)
        return None
    report = site.manifest["enhance"]["auto_cad"]
    for note in report["notes"]:
        print(f"note: {note}", file=file)
    write_scan2cad(path, doc)
    models = doc[0]["aligned_models"]
    n_auto = sum(1 for m in models if m.get("origin") == "auto")
    print(f"auto-cad: {n_auto} of {len(report['instances'])} instances aligned in {report['elapsed_s']:.1f} s, "
          f"{len(models)} CAD alignments -> {path} (edit it and rebuild with --scan2cad to adjust)", file=file)
    return path


def compile_site_loops(site) -> None:
    """Compile the localizer's loops for the site's kind of field now (`localizer.compile_loops_for`), so that a
    server's first start on this machine does not, and say so on stderr (stdout stays the command's summary)."""
    from ..localize.localizer import compile_loops_for

    t0 = time.perf_counter()
    compile_loops_for(site)
    print(f"the localizer's compiled loops for this site are in numba's cache ({time.perf_counter() - t0:.1f} s)",
          file=sys.stderr)


def _build(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from ..config import AutoCadConfig, SiteBuildConfig, config_problems
    from ..errors import ConfigError
    from ..site.build import build_site

    try:
        config = SiteBuildConfig(partition=PartitionConfig(above_m=args.rooms_above_m))
    except ValidationError as exc:
        raise ConfigError(f"bad --rooms-above-m: {config_problems(exc)}") from None
    t0 = time.perf_counter()
    bar, update = _progress_bar("site build")
    try:
        site = build_site(args.scan, labels_ply=args.labels, scan2cad_json=args.scan2cad, cad_root=args.cad_root,
                          site_id=args.site_id, config=config, progress=update,
                          auto_cad=AutoCadConfig() if args.auto_cad else None)
    finally:
        bar.close()
    site.save(args.out)
    write_auto_cad(site, args.out)
    compile_site_loops(site)
    n_cad = sum(1 for n in site.graph.nodes if n.source == "cad")
    regions = len(site.regions)
    print(f"site {site.site_id} version {site.version}: {len(site.map)} map points ({len(site.raw)} raw), "
          f"{len(site.graph.nodes)} objects ({n_cad} CAD), {site.graph.graph.number_of_edges()} edges"
          + (f", {regions} regions (its rooms: `cadreg site info`)" if regions > 1 else "") + f" -> {args.out}")
    if args.auto_cad:
        print(f"elapsed {time.perf_counter() - t0:.1f} s")
    return 0


def cad_origins(site) -> dict[str, dict]:
    """{CAD node id: its enhance record} with `origin` ("annotation" for bundles from before auto-CAD)."""
    return {f["id"]: {"origin": "annotation", **f} for f in site.manifest.get("enhance", {}).get("cads", [])}


def site_summary(site) -> dict:
    """The `site info --json` document (DESIGN §8), plus a few extra keys (CAD nodes: `origin` "annotation" |
    "auto", and `fit` for automatic ones)."""
    from ..site.regions import Storeys

    origins = cad_origins(site)

    def node(n) -> dict:
        d = {"id": n.id, "class": n.cls, "centroid": [round(float(x), 4) for x in n.centroid],
             "source": n.source, "points": int(n.points), "cad_id": n.cad_id}
        if n.source == "cad":
            rec = origins.get(n.id, {"origin": "annotation"})
            d["origin"] = rec["origin"]
            if "auto_fit" in rec:
                d["fit"] = rec["auto_fit"]
        return d

    return {
        "site_id": site.site_id,
        "version": site.version,
        "nodes": [node(n) for n in site.graph.nodes],
        "edges": site.graph.graph.number_of_edges(),
        "points": len(site.map),
        "raw_points": len(site.raw),
        "classes": list(site.classes),
        "label_sets": sorted(site.label_maps),
        "built_at": site.manifest.get("built_at"),
        "cad_fit": list(site.manifest.get("enhance", {}).get("cads", [])),
        "regions": [r.info() for r in site.regions],
        # the lowest floor of each storey (`Storeys`: rooms whose floors lie 2 m or more apart)
        "storeys": [round(float(b), 4) for b in Storeys.of(site.regions).base],
        "up": None if site.up is None else [round(float(x), 4) for x in site.up],
    }


def _info(args: argparse.Namespace) -> int:
    from ..site.bundle import Site

    site = Site.load(args.site_dir)
    info = site_summary(site)
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    print(f"site {info['site_id']}  version {info['version']}  built {info['built_at']}")
    print(f"map points {info['points']}  raw points {info['raw_points']}  edges {info['edges']}  up "
          + ("found from the map at load" if info["up"] is None else "({:.3f}, {:.3f}, {:.3f})".format(*info["up"])))
    storeys = info["storeys"]
    print(f"{len(info['regions'])} region(s)" + (f" on {len(storeys)} storeys (floors at "
                                                   + ", ".join(f"{b:.2f}" for b in storeys) + " m)"
                                                   if len(storeys) > 1 else "") + ":")
    print(f"{'region':<12} {'objects':>7} {'points':>9} {'floor [m]':>9}  bounds [m]")
    for r in info["regions"]:
        (x0, y0, z0), (x1, y1, z1) = r["bounds"]
        floor = "-" if r["floor_m"] is None else f"{r['floor_m']:.2f}"
        print(f"{r['id']:<12} {r['objects']:>7} {r['points']:>9} {floor:>9}  "
              f"({x0:.2f}, {y0:.2f}, {z0:.2f}) – ({x1:.2f}, {y1:.2f}, {z1:.2f})")
    print(f"{'id':<12} {'class':<16} {'source':<8} {'origin':<10} {'points':>7}  centroid [m]")
    for n in info["nodes"]:
        c = n["centroid"]
        print(f"{n['id']:<12} {n['class']:<16} {n['source']:<8} {n.get('origin', '-'):<10} {n['points']:>7}  "
              f"({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})")
    if info["cad_fit"]:
        print(f"{'CAD fit':<12} {'model':<44} {'origin':<10} {'replaced':>8}  CAD samples to scan: median / p90 [cm]"
              "; auto: instance to CAD median [cm], coverage scan / CAD")
        for f in info["cad_fit"]:
            fit = ("-" if f["median_distance_to_scan_m"] is None else
                   f"{100 * f['median_distance_to_scan_m']:.1f} / {100 * f['p90_distance_to_scan_m']:.1f}")
            auto = f.get("auto_fit")
            if auto:
                fit += (f"; {100 * auto['median_scan_to_cad_m']:.1f}, "
                        f"{auto['scan_coverage']:.2f} / {auto['cad_coverage']:.2f}")
            print(f"{f['id']:<12} {f['cad_id']:<44} {f.get('origin', 'annotation'):<10} "
                  f"{f['raw_points_replaced']:>8}  {fit}")
    return 0


def _show(args: argparse.Namespace) -> int:
    from ..site.bundle import Site
    from ..site.show import render_site_png

    site = Site.load(args.site_dir)
    Path(args.png).parent.mkdir(parents=True, exist_ok=True)
    Path(args.png).write_bytes(render_site_png(site))
    print(f"wrote {args.png}")
    return 0


def _autocad_check(args: argparse.Namespace) -> int:
    from ..io.bundle_files import read_json
    from ..io.scan2cad import read_scan2cad, select_scan
    from ..site.autocad_check import compare_alignments, format_checks

    annotated = select_scan(read_scan2cad(args.scan2cad), args.scan.name, args.scan2cad)
    if args.auto is not None:
        auto_path = args.auto
    else:
        from ..config import AutoCadConfig
        from ..site.build import build_site

        t0 = time.perf_counter()
        site = build_site(args.scan, labels_ply=args.labels, cad_root=args.cad_root, site_id=args.site_id,
                          auto_cad=AutoCadConfig())
        print(f"site build --auto-cad: elapsed {time.perf_counter() - t0:.1f} s")
        out = args.out or Path(f"/tmp/cadreg/autocad-check/{site.site_id}")
        site.save(out)
        auto_path = write_auto_cad(site, out)
    auto = read_scan2cad(auto_path)[0]
    fits = [m.get("fit") for m in read_json(auto_path)[0]["aligned_models"]]
    print(format_checks(compare_alignments(annotated, auto, fits)))
    return 0


def register(subparsers) -> None:
    parser = subparsers.add_parser("site", help="build, inspect and draw site bundles")
    site_sub = parser.add_subparsers(dest="site_command", metavar="SITE_COMMAND")
    site_sub.required = True

    b = site_sub.add_parser("build", help="build a site bundle from a scan (+ labels, + Scan2CAD CAD alignments)")
    b.add_argument("--scan", required=True, type=Path, help="scan PLY (mesh or point cloud with colours)")
    b.add_argument("--labels", type=Path, help="PLY with the same vertices and a per-vertex NYU40 'label'")
    b.add_argument("--scan2cad", type=Path, help="Scan2CAD annotation JSON (needs --cad-root)")
    b.add_argument("--cad-root", type=Path, help="ShapeNet-style CAD folder: <synset>/<id>/models/model_normalized.obj")
    b.add_argument("--out", required=True, type=Path, help="bundle directory to write")
    b.add_argument("--site-id", help="site id (default: the scan file's name up to its first dot)")
    b.add_argument("--rooms-above-m", type=float, default=PartitionConfig().above_m, metavar="M",
                   help="a scan wider than this along x or y (a building scanned in one piece, z up) is cut into its "
                        "rooms, each a region (default %(default)s; 0: one region)")
    b.add_argument("--auto-cad", action="store_true",
                   help="align the --cad-root library's models to the labelled instances no annotation covers "
                        f"(needs labels); writes all CAD alignments to SITE/{AUTO_CAD_FILE} (Scan2CAD format)")
    b.set_defaults(func=_build)

    i = site_sub.add_parser("info", help="describe a site bundle (verifies its hashes)")
    i.add_argument("site_dir", type=Path)
    i.add_argument("--json", action="store_true", help="print JSON: site_id, version, nodes, edges, points")
    i.set_defaults(func=_info)

    from .render_cmd import register_site_fuse  # `site fuse` lives with the renderer's CLI (frames -> site)

    register_site_fuse(site_sub)
    from .compose_cmd import register_site_compose  # `site compose`: rooms -> one building site

    register_site_compose(site_sub)

    s = site_sub.add_parser("show", help="draw a top view of the map and its semantic graph")
    s.add_argument("site_dir", type=Path)
    s.add_argument("--png", required=True, type=Path)
    s.set_defaults(func=_show)

    c = site_sub.add_parser(
        "autocad-check", help="measure automatic CAD alignments against a Scan2CAD annotation of the same scan",
        description="Runs `site build --auto-cad` (or reads --auto) and prints, per annotated object, the errors of "
                    "the automatic CAD's box: centre (horizontal, height), yaw modulo symmetry, extents, and its fit.")
    c.add_argument("--scan", required=True, type=Path)
    c.add_argument("--labels", type=Path)
    c.add_argument("--cad-root", required=True, type=Path)
    c.add_argument("--scan2cad", required=True, type=Path, help="the annotation to compare with")
    c.add_argument("--auto", type=Path, help=f"an automatic alignment file ({AUTO_CAD_FILE}) instead of building")
    c.add_argument("--out", type=Path, help="where the check's site goes (default /tmp/cadreg/autocad-check/ID)")
    c.add_argument("--site-id")
    c.set_defaults(func=_autocad_check)

    def _need_cad_root(args: argparse.Namespace) -> int:
        if args.scan2cad is not None and args.cad_root is None:
            b.error("--scan2cad needs --cad-root")
        if args.auto_cad and args.cad_root is None:
            b.error("--auto-cad needs --cad-root")
        return _build(args)

    b.set_defaults(func=_need_cad_root)
