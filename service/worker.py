"""The worker process: loads every site's Localizer once, then answers jobs from its pipe one at a time.

Runs in a "spawn" child (Open3D and threads do not mix with fork). Numeric libraries get one thread each: the
variables below are set before numpy/open3d are imported in this process, which is why the heavy imports live inside
the functions. Messages (tuples over a `multiprocessing` Pipe; pydantic models travel pickled, already validated):

    start (spawn args) worker_main(conn, [(site_id, bundle_dir, checked), ...], LocalizeConfig, test_hooks, slot)
    parent -> worker   ("localize", job_id, site_id, version, parts: dict[str, bytes], meta: FrameMeta,
                        session: SessionJob | None)    a session's frame is tracked (Localizer.track)
                       ("load", job_id, site_id, path, checked)    load (or reload) one site; keeps the previous
                                                                   version
                       ("probe", job_id, site_id, path, checked)   build the site's localizer and drop it (an
                                                                   upload's check)
                       ("stop",)
    worker -> parent   ("ready", pid, [[site_id, version], ...])
                       ("result", job_id, True, result_dict, version_used[, session_state | None])
                                                       (the state only for a session's frame)
                       ("result", job_id, False, error_body, None)
                       ("loaded", job_id, True, [site_id, version] | error_body)   (answers load and probe)
                       ("failed", error_body)              start-up failed (a site could not be loaded)

`checked` is what the parent's hash check of the bundle found (`cadreg.site.bundle.FileChecks`, or None): the worker
does not hash again a file it maps that has not changed since.
"""

from __future__ import annotations

import multiprocessing
import os

WORKER_NAME_PREFIX = "cadreg-worker"
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")
# Only in the child: spawn names the process before it unpickles the target, i.e. before this import.
if multiprocessing.current_process().name.startswith(WORKER_NAME_PREFIX):
    for _var in THREAD_VARS:
        os.environ[_var] = "1"

import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import OrderedDict  # noqa: E402
from typing import TYPE_CHECKING, Any  # noqa: E402

if TYPE_CHECKING:
    from cadreg.config import LocalizeConfig
    from cadreg.site.bundle import FileChecks

    from .schemas import FrameMeta
    from .sessions import SessionJob  # noqa: F401 - named in the message table above

SLEEP_HOOK_PREFIX = "__sleep__:"  # test hook (settings.test_hooks): frame id "__sleep__:<seconds>"
VERSIONS_KEPT = 2  # the version being replaced stays for requests already dispatched to it

log = logging.getLogger("cadreg.service.worker")


class _Sites:
    """Localizers by site id, newest version last; keeps `VERSIONS_KEPT` versions per site."""

    def __init__(self, config: LocalizeConfig, slot: int = 0) -> None:
        from cadreg.config import LocalizeConfig

        if not isinstance(config, LocalizeConfig):
            raise TypeError(f"localize config must be a LocalizeConfig, not {type(config).__name__}")
        self.config = config
        # The pool's workers start together: those of odd and even slots compile the localizer's loops from opposite
        # ends (`compile_loops`), so that on a cold cache two of them each compile about half.
        self.compile_last_first = slot % 2 == 1
        self.by_site: dict[str, OrderedDict[str, Any]] = {}

    def build(self, site_id: str, path: str, checked: FileChecks | None = None) -> tuple[str, Any]:
        """(version, warmed Localizer) of the bundle at `path`. Raises the bundle's InvalidFileError, or one saying
        why the localizer cannot be built (an empty map, points that break a search structure)."""
        from cadreg.errors import CadregError, InvalidFileError, UnknownSite
        from cadreg.localize.localizer import Localizer
        from cadreg.site.bundle import Site

        site = Site.load(path, checked=checked)
        if site.site_id != site_id:
            raise UnknownSite(f"bundle at {path} is site {site.site_id!r}, expected {site_id!r}")
        try:
            if len(site.map) == 0:
                raise ValueError("map.ply has no points")
            localizer = Localizer.from_site(site, self.config).warm(compile_last_first=self.compile_last_first)
        except CadregError:
            raise
        except Exception as exc:
            log.exception("site %s cannot be loaded", site_id)
            why = str(exc) or type(exc).__name__
            raise InvalidFileError(f"{site_id}/map.ply", f"the site cannot be loaded: {why}"[:300]) from None
        return site.version, localizer

    def load(self, site_id: str, path: str, checked: FileChecks | None = None) -> str:
        version, localizer = self.build(site_id, path, checked)
        versions = self.by_site.setdefault(site_id, OrderedDict())
        versions.pop(version, None)
        versions[version] = localizer
        while len(versions) > VERSIONS_KEPT:
            versions.popitem(last=False)
        return version

    def get(self, site_id: str, version: str | None) -> tuple[Any, str]:
        from cadreg.errors import UnknownSite

        versions = self.by_site.get(site_id)
        if not versions:
            raise UnknownSite(f"unknown site {site_id!r}")
        if version in versions:
            return versions[version], version
        # Asked for a version already replaced twice over: answer with the newest, and say so in the result.
        newest = next(reversed(versions))
        return versions[newest], newest

    def loaded(self) -> list[list[str]]:
        return [[sid, v] for sid, versions in self.by_site.items() for v in versions]


def _error_body(exc: BaseException) -> dict[str, Any]:
    from .errors import error_body

    return error_body(exc)


def _top_k(meta: FrameMeta) -> int | None:
    """The request's top_k; None (not sent, or sent as null) lets the site's LocalizeConfig (match.top_k) decide."""
    return meta.top_k


def _localize(sites: _Sites, msg: tuple, test_hooks: bool) -> tuple:
    from .codec import decode_frame

    _, job_id, site_id, version, parts, meta, *more = msg
    session = more[0] if more else None
    try:
        if test_hooks and meta.frame_id and meta.frame_id.startswith(SLEEP_HOOK_PREFIX):
            time.sleep(float(meta.frame_id[len(SLEEP_HOOK_PREFIX):]))
        localizer, used = sites.get(site_id, version)
        frame = decode_frame(parts, meta)
        if session is None:
            result = localizer.localize(frame, top_k=_top_k(meta))
            return ("result", job_id, True, result.to_dict(), used)
        from cadreg.localize.tracking import TrackState

        # a state stored for another version was dropped by the parent; one from an older version of this worker's
        # site (answered with the newest here) is still a pose in nearly the same map, and tracking checks it
        state = None if session.state is None else TrackState.from_dict(session.state)
        tracked = localizer.track(frame, state, t_s=session.t_s, top_k=_top_k(meta), may_search=session.may_search)
        return ("result", job_id, True, tracked.result.to_dict(), used,
                None if tracked.state is None else tracked.state.to_dict())
    except Exception as exc:  # every failure goes back as an error body; the worker lives on
        if not hasattr(exc, "code"):
            log.exception("job %s failed", job_id)
        return ("result", job_id, False, _error_body(exc), None)


def worker_main(conn, sites: list[tuple[str, str, FileChecks | None]], localize_config: LocalizeConfig, test_hooks: bool,
                slot: int = 0) -> None:
    """Entry point of a worker process; `sites` = [(site_id, bundle_dir, checked)]; slot: its place in the pool."""
    import signal

    # Ctrl-C in a terminal reaches the whole process group, and so does a service manager's SIGTERM to its control
    # group (systemd's default) or `kill -- -PGID`: the parent stops the workers in order, after the requests in
    # flight are answered. A worker killed by the signal itself failed its request with `worker_crashed` and was
    # replaced by a new one the parent started during its own shutdown. A worker still ends with its parent (its
    # pipe closes), when the pool stops it (a message, then SIGKILL), and on SIGKILL: `kill -9 PID` stops one.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s")
    if "numpy" in sys.modules and os.environ.get("OMP_NUM_THREADS") != "1":
        log.warning("numpy was imported before the worker set its thread limits")
    try:
        loaded = _Sites(localize_config, slot)
        for site_id, path, checked in sites:
            loaded.load(site_id, path, checked)
    except Exception as exc:
        log.exception("worker start-up failed")
        conn.send(("failed", _error_body(exc)))
        return
    conn.send(("ready", os.getpid(), loaded.loaded()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return  # the parent went away
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "localize":
            reply = _localize(loaded, msg, test_hooks)
        elif kind == "load":
            _, job_id, site_id, path, checked = msg
            try:
                reply = ("loaded", job_id, True, [site_id, loaded.load(site_id, path, checked)])
            except Exception as exc:
                reply = ("loaded", job_id, False, _error_body(exc))
        elif kind == "probe":
            _, job_id, site_id, path, checked = msg
            try:
                version, _localizer = loaded.build(site_id, path, checked)
                del _localizer  # only the check was wanted: its memory goes now, not at the next build
                reply = ("loaded", job_id, True, [site_id, version])
            except Exception as exc:
                reply = ("loaded", job_id, False, _error_body(exc))
        else:
            log.error("unknown message %r", kind)
            continue
        try:
            conn.send(reply)
        except (EOFError, OSError, BrokenPipeError):
            return
