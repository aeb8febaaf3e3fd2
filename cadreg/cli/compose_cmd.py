"""`cadreg site compose LAYOUT.json --out SITE`: one building site from room bundles (cadreg/site/compose.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _compose(args: argparse.Namespace) -> int:
    from ..site.compose import compose_site, read_layout

    layout = read_layout(args.layout)
    site = compose_site(layout, args.layout.parent)
    site.save(args.out)
    counts = site.manifest["counts"]
    print(json.dumps({"site_id": site.site_id, "version": site.version, "rooms": len(layout.rooms),
                      "points": counts["points"], "raw_points": counts["raw_points"], "nodes": counts["nodes"],
                      "edges": counts["edges"], "out": str(args.out)}))
    return 0


def register_site_compose(site_sub: argparse._SubParsersAction) -> None:
    c = site_sub.add_parser(
        "compose", help="compose a multi-room site from room bundles placed by a layout",
        description="LAYOUT.json: {\"site_id\", \"rooms\": [{\"name\", \"bundle\" (relative to the layout), "
                    "\"T_building_room\" (4x4), \"drop_objects\" (node ids, optional)}]}. Writes one bundle.",
    )
    c.add_argument("layout", type=Path, help="layout JSON file")
    c.add_argument("--out", required=True, type=Path, help="bundle directory to write")
    c.set_defaults(func=_compose)


def register(subparsers: argparse._SubParsersAction) -> None:
    """No top-level command: `compose` is a `site` sub-command (`site_cmd` calls `register_site_compose`); the CLI
    calls `register` of every `*_cmd` module."""
