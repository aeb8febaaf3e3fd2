"""`cadreg localize`: one recorded frame -> the JSON result on stdout (and optionally a picture)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm


def register(sub) -> None:
    from ..config import REFINE_METHODS

    p = sub.add_parser("localize", help="localize one recorded frame in a site; prints the JSON result")
    p.add_argument("--site", required=True, type=Path, help="site bundle directory")
    p.add_argument("--frames", required=True, type=Path, help="recorded frames folder")
    p.add_argument("--index", required=True, type=int, help="frame number")
    p.add_argument("--top-k", type=int, default=None, help="hypotheses to report")
    p.add_argument("--method", choices=REFINE_METHODS, default=None, help="refinement method")
    p.add_argument("--png", type=Path, default=None, help="write a top view of the frame over the map here")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import InvalidFileError
    from ..io.frames import RecordedFrames
    from ..localize.localizer import Localizer
    from ..site.bundle import Site

    site = Site.load(args.site)
    frames = RecordedFrames.open(args.frames)
    if args.index not in frames:
        raise InvalidFileError(args.frames, f"has no frame {args.index}")
    frame, _ = frames.load(args.index)
    localizer = Localizer.from_site(site)
    with tqdm(total=6, desc="localize", unit="stage", file=sys.stderr, leave=False) as bar:
        result = localizer.localize(frame, top_k=args.top_k, method=args.method,
                                    progress=lambda done, total: bar.update(done - bar.n))
    print(json.dumps(result.to_dict(), indent=2))
    if args.png:
        from ..localize.picture import render_localization_png

        args.png.write_bytes(render_localization_png(site, frame, result, localizer=localizer))
    return 0
