"""`cadreg site build | info | show`: build a site bundle, describe it, draw it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _progress_bar(desc: str):
    from tqdm import tqdm

    bar = tqdm(total=1, desc=desc, unit="step", leave=False, file=sys.stderr)

    def update(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.n = done
        bar.refresh()

    return bar, update


def _build(args: argparse.Namespace) -> int:
    from ..site.build import build_site

    bar, update = _progress_bar("site build")
    try:
        site = build_site(args.scan, labels_ply=args.labels, scan2cad_json=args.scan2cad, cad_root=args.cad_root,
                          site_id=args.site_id, progress=update)
    finally:
        bar.close()
    site.save(args.out)
    n_cad = sum(1 for n in site.graph.nodes if n.source == "cad")
    print(f"site {site.site_id} version {site.version}: {len(site.map)} map points ({len(site.raw)} raw), "
          f"{len(site.graph.nodes)} objects ({n_cad} CAD), {site.graph.graph.number_of_edges()} edges -> {args.out}")
    return 0


def site_summary(site) -> dict:
    """The `site info --json` document (DESIGN §8), plus a few extra keys."""
    return {
        "site_id": site.site_id,
        "version": site.version,
        "nodes": [{"id": n.id, "class": n.cls, "centroid": [round(float(x), 4) for x in n.centroid],
                   "source": n.source, "points": int(n.points), "cad_id": n.cad_id} for n in site.graph.nodes],
        "edges": site.graph.graph.number_of_edges(),
        "points": len(site.map),
        "raw_points": len(site.raw),
        "classes": list(site.classes),
        "label_sets": sorted(site.label_maps),
        "built_at": site.manifest.get("built_at"),
        "cad_fit": list(site.manifest.get("enhance", {}).get("cads", [])),
    }


def _info(args: argparse.Namespace) -> int:
    from ..site.bundle import Site

    site = Site.load(args.site_dir)
    info = site_summary(site)
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    print(f"site {info['site_id']}  version {info['version']}  built {info['built_at']}")
    print(f"map points {info['points']}  raw points {info['raw_points']}  edges {info['edges']}")
    print(f"{'id':<12} {'class':<16} {'source':<8} {'points':>7}  centroid [m]")
    for n in info["nodes"]:
        c = n["centroid"]
        print(f"{n['id']:<12} {n['class']:<16} {n['source']:<8} {n['points']:>7}  ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f})")
    if info["cad_fit"]:
        print(f"{'CAD fit':<12} {'model':<44} {'replaced':>8}  CAD samples to scan: median / p90 [cm]")
        for f in info["cad_fit"]:
            fit = ("-" if f["median_distance_to_scan_m"] is None else
                   f"{100 * f['median_distance_to_scan_m']:.1f} / {100 * f['p90_distance_to_scan_m']:.1f}")
            print(f"{f['id']:<12} {f['cad_id']:<44} {f['raw_points_replaced']:>8}  {fit}")
    return 0


def _show(args: argparse.Namespace) -> int:
    from ..site.bundle import Site
    from ..site.show import render_site_png

    site = Site.load(args.site_dir)
    Path(args.png).parent.mkdir(parents=True, exist_ok=True)
    Path(args.png).write_bytes(render_site_png(site))
    print(f"wrote {args.png}")
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
    b.set_defaults(func=_build)

    i = site_sub.add_parser("info", help="describe a site bundle (verifies its hashes)")
    i.add_argument("site_dir", type=Path)
    i.add_argument("--json", action="store_true", help="print JSON: site_id, version, nodes, edges, points")
    i.set_defaults(func=_info)

    from .render_cmd import register_site_fuse  # `site fuse` lives with the renderer's CLI (frames -> site)

    register_site_fuse(site_sub)

    s = site_sub.add_parser("show", help="draw a top view of the map and its semantic graph")
    s.add_argument("site_dir", type=Path)
    s.add_argument("--png", required=True, type=Path)
    s.set_defaults(func=_show)

    def _need_cad_root(args: argparse.Namespace) -> int:
        if args.scan2cad is not None and args.cad_root is None:
            b.error("--scan2cad needs --cad-root")
        return _build(args)

    b.set_defaults(func=_need_cad_root)
