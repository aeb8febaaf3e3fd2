"""The service core shared by the HTTP and zenoh front ends: settings, site registry, worker pool, metrics.

Front ends call `submit` (returns a `concurrent.futures.Future` of a JobResult; raises at once for an unknown
site, bad meta or a full queue) and `finish` (the result body). Everything blocking here (`start`, `reload_site`,
`install_archive`) is meant for a thread, never the event loop.
"""

from __future__ import annotations

import concurrent.futures
import logging
import shutil
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

from cadreg.errors import CadregError, InvalidFileError, InvalidFrame, Overloaded, UnknownSite

from .codec import check_image_sizes, check_parts, parse_meta
from .metrics import Metrics
from .pool import JobResult, WorkerPool
from .registry import SiteEntry, SiteRegistry, check_site_id, inspect_bundle
from .schemas import FrameMeta
from .sessions import SessionJob, SessionKey, SessionStore, session_key
from .settings import Settings

log = logging.getLogger("cadreg.service")

def ensure_demo_site(cache_dir: Path) -> Path:
    """The bundled demo site under `cache_dir/<site id>`, built on first use (or rebuilt when the cached one fails
    its hash check). `build_demo_site` writes its inputs beside the bundle: they go to a hidden build directory
    (the registry skips dot-directories) and only the bundle is kept."""
    from cadreg.site.demo import SITE_ID, build_demo_site

    target = cache_dir / SITE_ID
    if (target / "site.json").is_file():
        try:
            inspect_bundle(target)
            return target
        except InvalidFileError as exc:
            log.warning("cached demo site is unusable (%s): rebuilding", exc.message)
            shutil.rmtree(target, ignore_errors=True)
    build_dir = cache_dir / ".demo-build"
    shutil.rmtree(build_dir, ignore_errors=True)
    build_dir.mkdir(parents=True)
    log.info("building the demo site into %s", target)
    build_demo_site(build_dir)
    shutil.rmtree(target, ignore_errors=True)
    (build_dir / "site").rename(target)
    shutil.rmtree(build_dir, ignore_errors=True)
    return target


class Service:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.registry = SiteRegistry(settings.sites_root)
        self.pool: WorkerPool | None = None
        self.metrics = Metrics(lambda: self.pool, lambda: self.registry)
        self.sessions = SessionStore(ttl_s=settings.session_ttl_s, max_sessions=settings.max_sessions)
        self.started = threading.Event()

    # --- life cycle -------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Load the registry (building the demo site if serving it), start the workers; returns before the workers
        have loaded their sites (see `ready`). A bad bundle raises here, so a bad start fails loudly."""
        s = self.settings
        if s.demo_mode:
            ensure_demo_site(s.demo_cache_dir)
        entries = self.registry.load_all()
        if not entries:
            raise InvalidFileError(s.sites_root, "no site bundle here (expected <dir>/<site_id>/site.json)")
        self.pool = WorkerPool(
            self.registry.paths(),
            workers=s.workers,
            queue_depth=s.queue_depth,
            timeout_s=s.request_timeout_s,
            retry_after_s=s.retry_after_s,
            start_timeout_s=s.worker_start_timeout_s,
            localize_config=s.localize_config,
            test_hooks=s.test_hooks,
            checked=self.registry.checks(),
        )
        self.pool.start()
        self.started.set()

    def stop(self) -> None:
        if self.pool is not None:
            self.pool.stop()

    @property
    def ready(self) -> bool:
        return self.started.is_set() and self.pool is not None and self.pool.ready

    # --- localize ---------------------------------------------------------------------------------------------------

    def serves(self, site_id: str) -> bool:
        """Whether `site_id` is a loaded site (cheap: the zenoh front end asks before it keeps any state for it)."""
        try:
            self.registry.get(site_id)
        except CadregError:
            return False
        return True

    def submit(self, site_id: str, parts: dict[str, bytes], meta: FrameMeta | str | bytes | dict,
               timeout_s: float | None = None, reserve: int = 0,
               device_id: str | None = None) -> concurrent.futures.Future:
        """Validate what is cheap and queue the job; images are decoded in the worker. Checked here, for HTTP and
        zenoh alike: the site, the meta (validated once: the worker receives the FrameMeta object, not text to parse
        again), the parts present, the label set, and each image's size from its header (`max_frame_pixels`).

        A frame of a tracking session (meta `session_id`, or a zenoh stream `device_id`) goes with the session's
        state (service/sessions.py); the state the worker returns is stored when the job is done."""
        # reserve: pool places this job must leave free (WorkerPool.submit); zenoh stream frames pass one
        entry = self.registry.get(site_id)
        meta = parse_meta(meta)
        check_parts(parts)
        _check_label_set(entry, meta, has_labels=bool(parts.get("labels")))
        check_image_sizes(parts, self.settings.max_frame_pixels)
        if self.pool is None:
            raise Overloaded("the service is starting", retry_after_s=self.settings.retry_after_s)
        key = session_key(site_id, meta.session_id, device_id)
        if key is None:
            return self.pool.submit(site_id, entry.version, parts, meta, timeout_s, reserve=reserve)
        session = self.sessions.job(key, entry.version, meta.stamp_s)
        future = self.pool.submit(site_id, entry.version, parts, meta, timeout_s, reserve=reserve, session=session)
        # registered before any front end's callback: the state is stored before the device's next frame is taken
        future.add_done_callback(lambda f: self._store_session(key, session, f))
        return future

    def _store_session(self, key: SessionKey, session: SessionJob, future: concurrent.futures.Future) -> None:
        try:
            if future.cancelled() or future.exception() is not None:
                return  # an error teaches nothing about the pose: the session keeps its state
            job = future.result()
            if job.session_state is not None:  # None: the frame taught nothing (not searched), the session stays
                self.sessions.store(key, job.session_state, job.site_version, stamped=session.stamped)
        finally:
            self.sessions.release(key, session.lease)

    def finish(self, job: JobResult, site_id: str, request_id: str) -> dict[str, Any]:
        """The answer body: the result plus request id, site id and the bundle version that answered."""
        self.metrics.observe_job(job)
        return {**job.result, "request_id": request_id, "site_id": site_id, "site_version": job.site_version}

    # --- admin ------------------------------------------------------------------------------------------------------

    def reload_site(self, site_id: str, bundle_dir: Path | None = None) -> SiteEntry:
        """(Re)load `site_id` from `bundle_dir` (default `<root>/<site_id>`): validate, have every worker load it,
        then swap. Answers within the request timeout even when a worker hangs (it is replaced). Blocking; run in
        a thread."""
        check_site_id(site_id)
        path = Path(bundle_dir) if bundle_dir is not None else self.registry.root / site_id
        if not (path / "site.json").is_file():
            raise UnknownSite(f"no bundle for site {site_id!r}", detail={"site_id": site_id})
        with self.registry.reload_lock(site_id):
            entry = inspect_bundle(path)
            if entry.site_id != site_id:
                raise InvalidFileError(f"{site_id}/site.json", f"bundle is site {entry.site_id!r}, not {site_id!r}")
            self._load_everywhere(entry)
            self.registry.swap(entry)
            self.sessions.drop_site(site_id)  # their poses are in the map just replaced
            return entry

    def install_archive(self, site_id: str, archive: Path) -> SiteEntry:
        """Unpack an uploaded bundle archive into a staging directory, hash-check it, have one worker prove that it
        loads (a "probe": a bundle whose hashes agree may still hold no usable map), and only then install it as
        `<root>/<site_id>`, have every worker load it and swap it in. Until the probe succeeds the served bundle on
        disk is untouched; a bundle that cannot load answers InvalidFileError (422) naming why."""
        check_site_id(site_id)
        with self.registry.reload_lock(site_id):
            staged = self.registry.stage_archive(site_id, archive, self.settings.max_bundle_bytes)
            try:
                entry = _relative_errors(inspect_bundle, staged)
                if entry.site_id != site_id:
                    raise InvalidFileError("upload", f"bundle is site {entry.site_id!r}, not {site_id!r}")
                self._probe(entry)
            except BaseException:
                shutil.rmtree(staged, ignore_errors=True)
                raise
            target = self.registry.install(site_id, staged)
            # Moving the checked directory into place changes no byte: the entry is the staged one at its new path
            # (hashing a large bundle a second time only delayed the swap).
            entry = replace(entry, path=str(target.resolve()))
            self._load_everywhere(entry)
            self.registry.swap(entry)
            self.sessions.drop_site(site_id)
            return entry

    def _probe(self, entry: SiteEntry) -> None:
        if self.pool is None:
            raise Overloaded("the service is starting", retry_after_s=self.settings.retry_after_s)
        try:
            self.pool.probe_site(entry.site_id, entry.path, entry.checked).result(timeout=self._control_wait_s())
        except InvalidFileError as exc:
            raise _relative(exc, Path(entry.path)) from None

    def _load_everywhere(self, entry: SiteEntry) -> None:
        if self.pool is None:
            raise Overloaded("the service is starting", retry_after_s=self.settings.retry_after_s)
        self.pool.load_site(entry.site_id, entry.path, entry.checked).result(timeout=self._control_wait_s())

    def _control_wait_s(self) -> float:
        # The pool settles a control by the request timeout (hung workers are replaced); the margin is for its
        # dispatcher only, never the worker start timeout.
        return self.settings.request_timeout_s + 5.0


def _check_label_set(entry: SiteEntry, meta: FrameMeta, has_labels: bool) -> None:
    """A label set the site has no map for is refused whenever the meta names one or labels come with the frame
    (never ignored: a client that sent the wrong name would otherwise get answers without its labels' help)."""
    if (has_labels or "label_set" in meta.model_fields_set) and meta.label_set not in entry.label_sets:
        known = list(entry.label_sets)
        raise InvalidFrame(f"site {entry.site_id!r} has no label map {meta.label_set!r}; known label sets: {known}",
                           detail={"label_set": meta.label_set, "known": known})


def _relative(exc: InvalidFileError, root: Path) -> InvalidFileError:
    """The same error naming its file relative to the staged bundle ("upload/map.ply"), not by a server path."""
    path = Path(exc.path) if exc.path else None
    if path is None or not path.is_absolute():
        return exc
    try:
        shown = "upload/" + str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        shown = "upload"
    reason = exc.message.split(": ", 1)[1] if exc.message.startswith(exc.path + ": ") else exc.message
    reason = reason.replace(str(root.resolve()), "upload").replace(str(root), "upload")
    detail = {k: v for k, v in exc.detail.items() if k != "path"}
    return type(exc)(shown, reason, detail=detail)


def _relative_errors(check, staged: Path):
    try:
        return check(staged)
    except InvalidFileError as exc:
        raise _relative(exc, staged) from None
