"""`cadreg` entry point.

Core sub-commands are the modules `cadreg/cli/<name>_cmd.py`, each with `register(subparsers)` that adds its
parser and sets `func(args) -> int`. Sub-commands that need the service or the clients (`serve`, `load`) are
plugins registered under the entry-point group `cadreg.commands`, so that the core never imports them.
"""

from __future__ import annotations

import argparse
import logging
import os
import pkgutil
import sys
from importlib import import_module
from importlib.metadata import entry_points

from .. import __version__
from ..errors import CadregError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cadreg", description="CAD-aided RGB-D to map registration")
    parser.add_argument("--version", action="version", version=f"cadreg {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    package = import_module(__package__)
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        if info.name.endswith("_cmd"):
            import_module(f"{__package__}.{info.name}").register(sub)
    for ep in entry_points(group="cadreg.commands"):
        ep.load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a reader that left is caught below, not at the interpreter's exit
        return code
    except CadregError as exc:
        print(f"cadreg {args.command}: error [{exc.code}]: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader of the output left (`cadreg site info SITE | head`): nothing more to say, and nowhere to say it.
        # Python flushes stdout again at exit, so it points at nothing first.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
