"""`cadreg site compose LAYOUT.json --out SITE`: one building site from room bundles (cadreg/site/compose.py), and
`cadreg site layout --room NAME=BUNDLE ... --rooms N --site-id ID --out LAYOUT.json`: a benchmark building's layout
(cadreg/site/layout.py)."""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

from ..errors import ConfigError


def _compose(args: argparse.Namespace) -> int:
    from ..site.compose import compose_site, read_layout
    from .site_cmd import compile_site_loops

    layout = read_layout(args.layout)
    site = compose_site(layout, args.layout.parent, versioned=False)
    site.save(args.out)
    compile_site_loops(site)
    counts = site.manifest["counts"]
    print(json.dumps({"site_id": site.site_id, "version": site.version, "rooms": len(layout.rooms),
                      "points": counts["points"], "raw_points": counts["raw_points"], "nodes": counts["nodes"],
                      "edges": counts["edges"], "out": str(args.out)}))
    return 0


def _room_arg(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"--room takes NAME=BUNDLE_DIR, got {text!r}")
    return name, Path(path)


def _layout_json(doc: dict) -> str:
    """The layout as JSON with one room (and one corridor) per line (diffable, and readable at 100 rooms); a room
    that moves no object has no "move_objects", a layout without corridors no "corridors"."""
    rooms = ",\n  ".join(json.dumps({k: v for k, v in r.items() if k != "move_objects" or v}) for r in doc["rooms"])
    head = json.dumps({k: v for k, v in doc.items() if k not in ("rooms", "corridors")})[:-1]
    corridors = ",\n  ".join(json.dumps(c) for c in doc.get("corridors", []))
    tail = f", \"corridors\": [\n  {corridors}\n]" if corridors else ""
    return f"{head}, \"rooms\": [\n  {rooms}\n]{tail}}}\n"


def _layout(args: argparse.Namespace) -> int:
    from ..site.bundle import Site
    from ..site.layout import LayoutConfig, RoomSource, generate_layout, grid_shape

    try:
        config = LayoutConfig(site_id=args.site_id, rooms=args.rooms, gap_m=args.gap_m, drop_prob=args.drop_prob,
                              move_prob=args.move_prob, move_max_m=args.move_max_m, move_max_deg=args.move_max_deg,
                              corridor_m=args.corridor_m, corridor_height_m=args.corridor_height_m,
                              storeys=args.storeys, storey_height_m=args.storey_height_m,
                              any_turn=args.any_turn, building_turn_deg=args.building_turn_deg, seed=args.seed)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    names = [name for name, _ in args.room]
    if len(set(names)) != len(names):
        raise ConfigError(f"--room names must be distinct, got {names}")
    out = args.out
    # compose reads bundle paths relative to the layout file: write them so.
    sources = [RoomSource.from_site(name, os.path.relpath(path.resolve(), out.resolve().parent), Site.load(path))
               for name, path in args.room]
    layout = generate_layout(sources, config)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(_layout_json(layout.model_dump()))
    cols, rows = grid_shape(math.ceil(config.rooms / config.storeys))
    dropped = sum(len(r.drop_objects) for r in layout.rooms)
    moved = sum(len(r.move_objects) for r in layout.rooms)
    cad = sum(len(sources[k % len(sources)].cad_ids) for k in range(config.rooms))
    print(json.dumps({"site_id": layout.site_id, "rooms": len(layout.rooms), "grid": [cols, rows],
                      "sources": {s.name: s.bundle for s in sources}, "cad_objects": cad, "dropped": dropped,
                      "moved": moved, "corridors": len(layout.corridors), "storeys": config.storeys, "seed": config.seed,
                      "out": str(out)}))
    return 0


def register_site_compose(site_sub: argparse._SubParsersAction) -> None:
    c = site_sub.add_parser(
        "compose", help="compose a multi-room site from room bundles placed by a layout",
        description="LAYOUT.json: {\"site_id\", \"rooms\": [{\"name\", \"bundle\" (relative to the layout), "
                    "\"T_building_room\" (4x4), \"drop_objects\" (node ids, optional), \"move_objects\" ({node id: "
                    "4x4 room-frame transform}, optional)}], \"corridors\" (optional): [{\"name\", "
                    "\"T_building_corridor\" (4x4), \"length_m\", \"width_m\", \"height_m\"}]}. Writes one bundle.",
    )
    c.add_argument("layout", type=Path, help="layout JSON file")
    c.add_argument("--out", required=True, type=Path, help="bundle directory to write")
    c.set_defaults(func=_compose)
    g = site_sub.add_parser(
        "layout", help="generate a benchmark building's LAYOUT.json: copies of room bundles on a grid",
        description="Rooms r000, r001, ... on a near-square grid, each a copy of a --room bundle (cycled), turned "
                    "about z by a random multiple of 90 degrees about its footprint centre, footprints --gap-m "
                    "apart, each CAD object dropped with probability --drop-prob, each one kept moved (turned and "
                    "shifted inside the room) with probability --move-prob; with --corridor-m, plain corridors "
                    "between pairs of rows; with --storeys, one such grid a storey, each above the one below; "
                    "with --any-turn, each room turned by a random angle instead; with --building-turn-deg, the "
                    "whole building turned. Deterministic per --seed.",
    )
    g.add_argument("--room", action="append", required=True, type=_room_arg, metavar="NAME=BUNDLE_DIR",
                   help="a room bundle to copy (repeatable)")
    g.add_argument("--rooms", type=int, required=True, help="number of rooms")
    g.add_argument("--gap-m", type=float, default=0.6, help="gap between neighbouring footprints, metres")
    g.add_argument("--drop-prob", type=float, default=0.35, help="probability of dropping each CAD object of a copy")
    g.add_argument("--move-prob", type=float, default=0.0,
                   help="probability of moving each CAD object a copy keeps (default 0: none)")
    g.add_argument("--move-max-m", type=float, default=0.5, help="largest shift of a moved object, metres")
    g.add_argument("--move-max-deg", type=float, default=45.0, help="largest turn of a moved object, degrees")
    g.add_argument("--corridor-m", type=float, default=0.0,
                   help="clear width of a corridor between each pair of rows, metres (default 0: no corridors)")
    g.add_argument("--corridor-height-m", type=float, default=2.5, help="height of the corridors' walls, metres")
    g.add_argument("--storeys", type=int, default=1,
                   help="storeys the rooms are shared among, each on its own grid above the one below (default 1)")
    g.add_argument("--storey-height-m", type=float, default=3.0,
                   help="floor-to-floor height of a storey, metres (plus the spread of the rooms' own floors)")
    g.add_argument("--any-turn", action="store_true",
                   help="turn each room by a random angle, not by a multiple of 90 degrees")
    g.add_argument("--building-turn-deg", type=float, default=0.0,
                   help="turn the whole building about z by this, degrees (default 0)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--site-id", required=True, help="site id of the building")
    g.add_argument("--out", required=True, type=Path, help="layout JSON to write (bundle paths relative to it)")
    g.set_defaults(func=_layout)


def register(subparsers: argparse._SubParsersAction) -> None:
    """No top-level command: `compose` is a `site` sub-command (`site_cmd` calls `register_site_compose`); the CLI
    calls `register` of every `*_cmd` module."""
