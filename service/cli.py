"""`cadreg serve`: the HTTP + zenoh service (a plugin sub-command, entry point group `cadreg.commands`).

    cadreg serve [--sites DIR] [--host 127.0.0.1] [--port 8080] [--workers N] [--zenoh-listen ENDPOINT]
                 [--localize-config FILE.toml|FILE.json]

With no arguments it serves the bundled demo site (built on first use into the settings' demo cache dir) on
127.0.0.1:8080 over HTTP and on tcp/127.0.0.1:7447 over zenoh. Every other setting comes from `CADREG_*`
environment variables (see service/settings.py); flags override them. `--localize-config` (or
CADREG_LOCALIZE_CONFIG) names a TOML or JSON file of algorithm parameters (cadreg.config.LocalizeConfig sections,
e.g. `[match]` / `top_k = 3`); it is validated before anything starts and every worker uses it.
"""

from __future__ import annotations

import argparse
import logging

log = logging.getLogger("cadreg.service")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="serve localization over HTTP and zenoh",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--sites", metavar="DIR", help="directory of site bundles (default: the demo site)")
    parser.add_argument("--host", help="HTTP bind address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="HTTP port (default 8080)")
    parser.add_argument("--workers", type=int, help="worker processes (default: min(2, cores))")
    parser.add_argument("--zenoh-listen", metavar="ENDPOINT", action="append",
                        help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    parser.add_argument("--no-zenoh", action="store_true", help="HTTP only")
    parser.add_argument("--localize-config", metavar="FILE",
                        help="TOML or JSON file of localizer parameters (LocalizeConfig sections); default: the "
                        "code's defaults, or CADREG_LOCALIZE_CONFIG")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported here so that `cadreg --help` stays fast; the web framework after the workers have started (below).
    from .runtime import Service
    from .settings import settings_from

    settings = settings_from(
        sites_dir=args.sites,
        host=args.host,
        port=args.port,
        workers=args.workers,
        zenoh_listen=args.zenoh_listen,
        zenoh_enabled=False if args.no_zenoh else None,
        localize_config=args.localize_config,
    )
    service = Service(settings)
    # Start here rather than in the app's lifespan: a bad sites directory or a tampered bundle then ends the
    # command with one clear error line (ConfigError / BundleIntegrityError) instead of a server traceback.
    service.start()
    # The workers load their sites meanwhile: the parent's imports from here on overlap their start.
    import uvicorn

    from .http_app import create_app, uvicorn_options

    zenoh_server = None
    try:
        if settings.zenoh_enabled:
            from .zenoh_server import ZenohServer

            zenoh_server = ZenohServer(service, settings)
            zenoh_server.start()
    except Exception:
        service.stop()
        raise
    app = create_app(settings, service, zenoh_server)
    log.info("cadreg serve: http://%s:%d (sites: %s)", settings.host, settings.port,
             settings.sites_dir or f"demo, cached in {settings.demo_cache_dir}")
    # what differs from the code's defaults, so that a log tells which parameters answered
    log.info("localize config: %s", settings.localize_config.model_dump(exclude_defaults=True) or "defaults")
    uvicorn.run(app, **uvicorn_options(settings), log_level="info", access_log=False, timeout_graceful_shutdown=10)
    return 0
