"""A pool of worker processes with a bounded queue, per-request deadlines and crash recovery.

Why not ProcessPoolExecutor: one dead worker breaks every pending future there. Here each worker is a process of
our own with one pipe; one dispatcher thread waits on every pipe, every `process.sentinel` and a wake-up pipe, so:
- a full queue refuses at once (`Overloaded`, 503 + Retry-After), never unbounded latency;
- a job past its deadline fails with `RequestTimeout` (504) and the stuck worker is killed and replaced;
- a worker that dies costs the one job it held a `WorkerCrashed` (503) and is replaced; no other job notices.
Futures are `concurrent.futures.Future`s, so HTTP (asyncio, via `asyncio.wrap_future`) and zenoh (threads) share
the pool. Processes are started with "spawn": Open3D and threads do not mix with fork.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import logging
import multiprocessing
import multiprocessing.util
import os
import signal
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from typing import Any

from cadreg.config import LocalizeConfig
from cadreg.errors import CadregError, Overloaded, RequestTimeout, WorkerCrashed
from cadreg.site.bundle import FileChecks

from .errors import error_from_body
from .logs import log_event
from .schemas import FrameMeta
from .sessions import SessionJob
from .worker import THREAD_VARS, WORKER_NAME_PREFIX, worker_main

log = logging.getLogger("cadreg.service.pool")

_MAX_RESTART_BACKOFF_S = 30.0


@dataclass
class JobResult:
    """What a localize job returns: the result dict, the bundle version that answered, where the time went."""

    result: dict[str, Any]
    site_version: str
    worker_pid: int
    queue_ms: float
    run_ms: float
    session_state: dict[str, Any] | None = None  # a session job's next tracking state (service/sessions.py)


@dataclass
class _Job:
    job_id: int
    message: tuple
    future: concurrent.futures.Future
    submitted: float  # time.monotonic()
    deadline: float
    dispatched: float = 0.0


@dataclass
class _Control:
    """A message some workers must process once (load a site: all of them; probe a site: one); resolves when each
    has answered, or at `deadline` (the request timeout) with what the workers that answered said: a worker still
    processing it then is hung and is replaced, one that has it queued still loads it later."""

    job_id: int
    message: tuple
    future: concurrent.futures.Future
    deadline: float = float("inf")
    waiting: set[int] = field(default_factory=set)  # worker slots still to answer
    errors: list[dict[str, Any]] = field(default_factory=list)
    confirmed: int = 0  # workers that answered yes
    adopt: Any = None  # called (lock held) on success, before any replacement starts

    def answer(self, slot: int, ok: bool, body: Any, outbox: list) -> None:
        if slot not in self.waiting:
            if not ok:
                log_event(log, "late_control_failed", job_id=self.job_id, slot=slot, error=body)
            return
        if ok:
            self.confirmed += 1
        else:
            self.errors.append(body)
        self.settle(slot, outbox)

    def settle(self, slot: int, outbox: list) -> None:
        self.waiting.discard(slot)
        if not self.waiting and not self.future.done():
            self.finish(outbox)

    def finish(self, outbox: list) -> None:
        self.waiting.clear()
        if self.future.done():
            return
        if self.errors:
            exc: BaseException | None = error_from_body(self.errors[0])
        elif not self.confirmed:
            exc = RequestTimeout("no worker answered within the request timeout; the hung ones are being replaced")
        else:
            exc = None
            if self.adopt is not None:
                self.adopt()
        outbox.append((self.future, None, exc))


@dataclass
class _Worker:
    slot: int
    process: Any = None
    conn: Any = None
    state: str = "stopped"  # starting | idle | busy | control | dead | stopped
    job: _Job | None = None
    control: _Control | None = None
    controls: deque = field(default_factory=deque)
    start_deadline: float = 0.0
    restart_at: float = 0.0
    failures: int = 0  # consecutive start failures, for back-off
    pid: int | None = None


class WorkerPool:
    """`workers` processes, each holding a Localizer per site; at most `workers + queue_depth` jobs at once.

    sites : {site_id: bundle directory} loaded by every worker at start (and by every replacement).
    checked : {site_id: what the parent's hash check of the bundle found} (`Site.check_files`): a worker does not
    hash again a file it maps that has not changed since.
    localize_config : the algorithm's parameters, sent as the object itself to every worker (and replacement).
    """

    def __init__(
        self,
        sites: dict[str, str],
        *,
        workers: int,
        queue_depth: int,
        timeout_s: float,
        retry_after_s: float = 1.0,
        start_timeout_s: float = 600.0,
        localize_config: LocalizeConfig | None = None,
        test_hooks: bool = False,
        checked: dict[str, FileChecks] | None = None,
    ) -> None:
        # {site_id: (bundle directory, what the parent's check of it found)}: what every worker loads
        self._sites = {sid: (path, (checked or {}).get(sid)) for sid, path in sites.items()}
        self._n = workers
        self._queue_depth = queue_depth
        self._timeout_s = timeout_s
        self._retry_after_s = retry_after_s
        self._start_timeout_s = start_timeout_s
        self._localize_config = localize_config if localize_config is not None else LocalizeConfig()
        self._test_hooks = test_hooks
        self._ctx = multiprocessing.get_context("spawn")
        # The children inherit these at exec; the worker module sets them again before its own heavy imports, but a
        # parent's __main__ re-imported by spawn may load numpy before that. The parent does no numeric work here.
        for var in THREAD_VARS:
            os.environ.setdefault(var, "1")
        self._lock = threading.Lock()
        self._queue: deque[_Job] = deque()
        self._workers = [_Worker(slot=i) for i in range(workers)]
        self._ids = itertools.count(1)
        self._wake_r, self._wake_w = multiprocessing.Pipe(duplex=False)
        self._woken = False
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._at_exit: multiprocessing.util.Finalize | None = None
        self._started_once: set[int] = set()
        self._controls: list[_Control] = []  # controls not yet settled, by deadline
        self._service_s: float | None = None  # moving average of a job's time on a worker, seconds
        self.restarts: Counter[str] = Counter()  # reason -> count, read by the metrics collector
        self.start_error: dict[str, Any] | None = None
        # Futures are settled after the lock is released: their callbacks may call back into the pool.
        self._outbox: list[tuple[concurrent.futures.Future, Any, BaseException | None]] = []
        self._settling = 0  # futures of the outbox being settled now (`_flush`), their callbacks running

    # --- public ---------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the worker processes and the dispatcher; returns at once (see `ready`)."""
        # A process that exits without `stop` stops its workers first: they ignore SIGTERM (the process group's
        # signal is the parent's to act on, `worker.worker_main`), and multiprocessing's own exit would terminate
        # them with it and then wait for them for ever. Its finalizers of a priority run before that.
        self._at_exit = multiprocessing.util.Finalize(self, self.stop, exitpriority=10)
        with self._lock:
            for w in self._workers:
                self._spawn(w)
        self._thread = threading.Thread(target=self._run, name="cadreg-pool-dispatcher", daemon=True)
        self._thread.start()

    @property
    def ready(self) -> bool:
        """Every worker has loaded every site once, and at least one is serving now."""
        with self._lock:
            serving = sum(w.state in ("idle", "busy", "control") for w in self._workers)
            return len(self._started_once) == self._n and serving > 0

    def wait_ready(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.ready:
                return True
            time.sleep(0.05)
        return self.ready

    @property
    def capacity(self) -> int:
        return self._n + self._queue_depth

    def queue_len(self) -> int:
        with self._lock:
            return len(self._queue)

    def alive(self) -> int:
        with self._lock:
            return sum(w.state in ("idle", "busy", "control") for w in self._workers)

    def workers_info(self) -> list[dict[str, Any]]:
        with self._lock:
            return [
                {"slot": w.slot, "pid": w.pid, "state": w.state, "job_id": w.job.job_id if w.job else None}
                for w in self._workers
            ]

    def free_slots(self) -> int:
        """How many more jobs `submit` would take now (idle workers + free queue places), less the jobs whose
        answers are being delivered: a worker is idle as soon as its answer is read, but the callbacks of its future
        (a tracking session's state stored, its search lease released) run a moment later, and a stream that took
        its device's next frame in between sent it without the state (answered `no_match` when it could not search)."""
        with self._lock:
            return self._free_slots() - len(self._outbox) - self._settling

    def _free_slots(self) -> int:  # lock held
        idle = sum(w.state == "idle" and not w.controls for w in self._workers)
        return self._queue_depth + idle - len(self._queue)

    def submit(self, site_id: str, version: str | None, parts: dict[str, bytes], meta: FrameMeta,
               timeout_s: float | None = None, reserve: int = 0,
               session: SessionJob | None = None) -> concurrent.futures.Future:
        """Queue one localize job; the future yields a JobResult or raises a CadregError.

        `meta` is the FrameMeta validated at the entry; it travels to the worker as that object (pickled), which
        does not validate it again.

        Raises Overloaded at once when `workers + queue_depth` jobs are already waiting or running, or when taking
        this job would leave fewer than `reserve` places free: a low-priority source (zenoh stream frames) passes a
        reserve so that it never fills the places that queries and HTTP requests need.

        `session` (a tracking session's state and the frame's time) makes the worker track the frame; the
        JobResult then carries the session's next state.
        """
        if not isinstance(meta, FrameMeta):
            # a caller bug, not a client's: text here would be parsed in the worker, a second time
            raise TypeError(f"meta must be a validated FrameMeta, not {type(meta).__name__}")
        now = time.monotonic()
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._lock:
            if self._stopping:
                raise Overloaded("the service is shutting down", retry_after_s=self._retry_after_s)
            if self._free_slots() <= max(0, reserve):
                raise Overloaded(
                    f"all {self._n} workers are busy and {len(self._queue)} requests are waiting",
                    retry_after_s=self._expected_wait_s(),
                    detail={"queue": len(self._queue), "workers": self._n},
                )
            job_id = next(self._ids)
            job = _Job(job_id, ("localize", job_id, site_id, version, parts, meta, session), future, now,
                       now + (timeout_s or self._timeout_s))
            self._queue.append(job)
        self._wake()
        return future

    def load_site(self, site_id: str, path: str, checked: FileChecks | None = None) -> concurrent.futures.Future:
        """Have every worker load `site_id` from `path`, keeping the version it replaces for jobs already dispatched
        to it. Resolves to None once every worker has it, or by the request timeout once at least one has (a worker
        still loading it then is hung: it is killed and its replacement starts with the new path; one that has it
        queued loads it later), or raises the first worker's error (RequestTimeout when none answered). Only on
        success do replacements start with the new path. checked: what the parent's hash check of it found."""
        future: concurrent.futures.Future = concurrent.futures.Future()

        def adopt() -> None:  # lock held
            self._sites[site_id] = (path, checked)

        with self._lock:
            job_id = next(self._ids)
            control = _Control(job_id, ("load", job_id, site_id, path, checked), future,
                               deadline=time.monotonic() + self._timeout_s, adopt=adopt)
            for w in self._workers:
                control.waiting.add(w.slot)
                w.controls.append(control)
            self._controls.append(control)
        self._wake()
        return future

    def probe_site(self, site_id: str, path: str, checked: FileChecks | None = None) -> concurrent.futures.Future:
        """Have one worker build `site_id`'s localizer from `path` and drop it: proves a bundle loads before it
        replaces anything. Resolves to None, or raises the worker's error (InvalidFileError naming why it cannot
        load), RequestTimeout past the request timeout (the worker is replaced), Overloaded when no worker is up."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._lock:
            up = [w for w in self._workers if w.state in ("idle", "busy", "control")]
            if self._stopping or not up:
                raise Overloaded("no worker is up to check the bundle", retry_after_s=self._retry_after_s)
            w = min(up, key=lambda w: (w.state != "idle", len(w.controls)))
            job_id = next(self._ids)
            control = _Control(job_id, ("probe", job_id, site_id, path, checked), future,
                               deadline=time.monotonic() + self._timeout_s, waiting={w.slot})
            w.controls.append(control)
            self._controls.append(control)
        self._wake()
        return future

    def site_paths(self) -> dict[str, str]:
        """{site_id: bundle directory} that a replacement worker loads."""
        with self._lock:
            return {sid: path for sid, (path, _) in self._sites.items()}

    def kill_worker(self, slot: int) -> None:
        """SIGKILL one worker (used by the debug route in tests)."""
        with self._lock:
            pid = self._workers[slot].pid
        if pid:
            os.kill(pid, signal.SIGKILL)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the dispatcher and the workers; jobs still queued fail with Overloaded."""
        if self._at_exit is not None:
            self._at_exit.cancel()  # stopped here, not again at exit
        with self._lock:
            self._stopping = True
            queued = list(self._queue)
            self._queue.clear()
        for job in queued:
            _settle(job.future, exc=Overloaded("the service is shutting down", retry_after_s=self._retry_after_s))
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout_s)
        for w in self._workers:
            if w.conn is not None:
                try:
                    w.conn.send(("stop",))
                except (OSError, ValueError):
                    pass
        deadline = time.monotonic() + timeout_s
        for w in self._workers:
            if w.process is not None:
                w.process.join(max(0.0, deadline - time.monotonic()))
                if w.process.is_alive():
                    w.process.kill()
                    w.process.join(1.0)
            if w.job is not None:
                _settle(w.job.future, exc=Overloaded("the service is shutting down", retry_after_s=self._retry_after_s))
            for control in ([w.control] if w.control else []) + list(w.controls):
                _settle(control.future, exc=Overloaded("the service is shutting down",
                                                       retry_after_s=self._retry_after_s))
            w.controls.clear()
            if w.conn is not None:
                w.conn.close()
            w.state = "stopped"
        self._wake_r.close()
        self._wake_w.close()

    # --- dispatcher -----------------------------------------------------------------------------------------------

    def _resolve(self, future: concurrent.futures.Future, value: Any) -> None:
        self._outbox.append((future, value, None))

    def _fail(self, future: concurrent.futures.Future, exc: BaseException) -> None:
        self._outbox.append((future, None, exc))

    def _flush(self) -> None:
        """Settle the futures decided under the lock (call without the lock held)."""
        with self._lock:
            outbox, self._outbox = self._outbox, []
            self._settling += len(outbox)
        try:
            for future, value, exc in outbox:
                _settle(future, value, exc)
        finally:
            with self._lock:
                self._settling -= len(outbox)

    def _wake(self) -> None:
        with self._lock:
            if self._woken:
                return
            self._woken = True
        try:
            self._wake_w.send_bytes(b"w")
        except (OSError, ValueError):
            pass

    def _spawn(self, w: _Worker) -> None:
        """Start a process for slot `w` (lock held)."""
        parent_conn, child_conn = self._ctx.Pipe(duplex=True)
        sites = [(sid, path, checked) for sid, (path, checked) in sorted(self._sites.items())]
        process = self._ctx.Process(
            target=worker_main,
            args=(child_conn, sites, self._localize_config, self._test_hooks, w.slot),
            name=f"{WORKER_NAME_PREFIX}-{w.slot}",
            daemon=True,
        )
        process.start()
        child_conn.close()
        w.process, w.conn, w.pid = process, parent_conn, process.pid
        w.state, w.job, w.control = "starting", None, None
        # Controls still queued for this slot (a reload under way) are kept: the new process runs them once up.
        w.start_deadline = time.monotonic() + self._start_timeout_s
        log.info("worker %d starting (pid %d)", w.slot, process.pid)

    def _retire(self, w: _Worker, reason: str, exc: CadregError | None) -> None:
        """The process of `w` is dead or must die: fail its job, keep its unfinished reload for the replacement,
        schedule the replacement (at once, or with back-off after failed starts)."""
        if w.process is not None and w.process.is_alive():
            w.process.kill()
            w.process.join(1.0)
        if w.conn is not None:
            w.conn.close()
        if w.job is not None:
            self._fail(w.job.future, exc or WorkerCrashed(
                "the worker process holding this request died; it is being replaced",
                detail={"retry_after_s": self._retry_after_s}))
        if w.control is not None:
            w.controls.appendleft(w.control)  # the replacement redoes the load this process did not finish
        w.process, w.conn, w.job, w.control, w.pid = None, None, None, None, None
        w.state = "dead"
        self.restarts[reason] += 1
        backoff = 0.0 if reason != "start_failed" else min(_MAX_RESTART_BACKOFF_S, 0.5 * 2 ** w.failures)
        w.restart_at = time.monotonic() + backoff
        log.warning("worker %d retired (%s); restarting in %.1f s", w.slot, reason, backoff)

    def _handle(self, w: _Worker, msg: tuple) -> None:
        kind = msg[0]
        now = time.monotonic()
        if kind == "ready":
            w.state, w.failures = "idle", 0
            self._started_once.add(w.slot)
            self.start_error = None
            log.info("worker %d ready (pid %d): %s", w.slot, msg[1], msg[2])
        elif kind == "failed":
            w.failures += 1
            self.start_error = msg[1]
            log_event(log, "worker_start_failed", logging.ERROR, slot=w.slot, error=msg[1].get("message"))
            self._retire(w, "start_failed", None)
        elif kind == "result" and w.job is not None and msg[1] == w.job.job_id:
            job, w.job, w.state = w.job, None, "idle"
            _, _, ok, body, version, *more = msg
            spent = now - job.dispatched
            self._service_s = spent if self._service_s is None else 0.8 * self._service_s + 0.2 * spent
            if ok:
                self._resolve(job.future, JobResult(body, version, w.pid or 0,
                                               (job.dispatched - job.submitted) * 1e3, (now - job.dispatched) * 1e3,
                                               more[0] if more else None))
            else:
                self._fail(job.future, error_from_body(body))
        elif kind == "loaded" and w.control is not None and msg[1] == w.control.job_id:
            control, w.control, w.state = w.control, None, "idle"
            control.answer(w.slot, bool(msg[2]), msg[3], self._outbox)
        else:
            log.error("worker %d sent an unexpected message %r", w.slot, kind)

    def _expected_wait_s(self) -> float:
        """How long a turned-away request should wait (lock held): until the queue ahead of it has drained, from
        the recent time per job, at most the configured Retry-After. A job takes a fraction of a second and HTTP's
        header can only say whole seconds, so the finer figure travels in the error body and the clients prefer it
        (a fixed second left the pool idle half the time under overload)."""
        if self._service_s is None:
            return self._retry_after_s
        drain_s = (len(self._queue) + 1) * self._service_s / max(self._n, 1)
        return float(min(self._retry_after_s, max(0.05, round(drain_s, 3))))

    def _assign(self, now: float) -> None:
        """Give idle workers their pending controls first, then queued jobs (lock held)."""
        for w in self._workers:
            if w.state != "idle":
                continue
            if w.controls:
                control = w.controls.popleft()
                try:
                    w.conn.send(control.message)
                except (OSError, ValueError):
                    w.controls.appendleft(control)
                    self._retire(w, "crashed", None)
                    continue
                w.control, w.state = control, "control"
                continue
            while self._queue:
                job = self._queue.popleft()
                if not job.future.set_running_or_notify_cancel():
                    continue  # the caller gave up (client went away)
                if now >= job.deadline:
                    self._fail(job.future, RequestTimeout(f"waited {now - job.submitted:.1f} s in the queue"))
                    continue
                job.dispatched = now
                try:
                    w.conn.send(job.message)
                except (OSError, ValueError):
                    w.job = job
                    self._retire(w, "crashed", None)
                    break
                w.job, w.state = job, "busy"
                break

    def _expire(self, now: float) -> None:
        """Time out queued jobs and stuck workers; replace workers that did not start in time (lock held)."""
        expired = [j for j in self._queue if now >= j.deadline]
        if expired:
            self._queue = deque(j for j in self._queue if now < j.deadline)
            for job in expired:
                self._fail(job.future, RequestTimeout(f"no worker free within {job.deadline - job.submitted:.1f} s"))
        for control in [c for c in self._controls if now >= c.deadline or c.future.done()]:
            self._controls.remove(control)
            if control.future.done():
                continue
            for w in self._workers:
                if w.control is control:
                    # still at it past the request timeout: hung. Its replacement starts from the pool's site paths
                    # (the new one when another worker loaded it: `finish` adopts it before the respawn below).
                    w.control = None
                    self._retire(w, "control_timeout", None)
                    log_event(log, "control_timeout", logging.WARNING, slot=w.slot, job_id=control.job_id,
                              kind=control.message[0])
            control.finish(self._outbox)
            if control.message[0] == "probe" or control.errors or not control.confirmed:
                for w in self._workers:  # nobody waits for it any more; a load that failed is not redone
                    if control in w.controls:
                        w.controls.remove(control)
        for w in self._workers:
            if w.state == "busy" and w.job is not None and now >= w.job.deadline:
                spent = now - w.job.submitted
                self._retire(w, "timeout", RequestTimeout(f"the request ran past its {spent:.1f} s deadline"))
            elif w.state == "starting" and now >= w.start_deadline:
                self._retire(w, "start_timeout", None)

    def _next_timeout(self, now: float) -> float:
        times = [j.deadline for j in self._queue] + [c.deadline for c in self._controls]
        for w in self._workers:
            if w.state == "busy" and w.job is not None:
                times.append(w.job.deadline)
            elif w.state == "starting":
                times.append(w.start_deadline)
            elif w.state == "dead":
                times.append(w.restart_at)
        return max(0.0, min(times) - now) if times else 1.0

    def _run(self) -> None:
        while not self._stopping:
            try:
                self._step()
            except Exception:
                # A bug here must not silently stop every request: log it and keep dispatching.
                log.exception("pool dispatcher error")
                time.sleep(0.05)
            self._flush()
        self._flush()

    def _step(self) -> None:
        with self._lock:
            if self._stopping:
                return
            now = time.monotonic()
            objects: list[Any] = [self._wake_r]
            owners: dict[Any, _Worker] = {}
            for w in self._workers:
                if w.process is not None:
                    objects += [w.conn, w.process.sentinel]
                    owners[w.conn] = owners[w.process.sentinel] = w
            timeout = self._next_timeout(now)
        ready = wait(objects, timeout)
        with self._lock:
            if self._stopping:
                return
            if self._wake_r in ready:
                while self._wake_r.poll():
                    self._wake_r.recv_bytes()
                self._woken = False
            for w in {id(owners[o]): owners[o] for o in ready if o in owners}.values():
                self._service(w)
            now = time.monotonic()
            self._expire(now)
            for w in self._workers:
                if w.state == "dead" and now >= w.restart_at:
                    self._spawn(w)
            self._assign(now)

    def _service(self, w: _Worker) -> None:
        """Read what worker `w` sent; a closed pipe or a fired sentinel means it died (lock held)."""
        if w.process is None:
            return
        try:
            while w.conn.poll():
                self._handle(w, w.conn.recv())
                if w.process is None:
                    return
        except (EOFError, OSError):
            pass
        if not w.process.is_alive():
            code = w.process.exitcode
            log.error("worker %d (pid %s) died with exit code %s", w.slot, w.pid, code)
            if w.state == "starting":
                w.failures += 1  # dying while loading is likely to repeat: back off
                self._retire(w, "start_failed", None)
            else:
                self._retire(w, "crashed", None)


def _settle(future: concurrent.futures.Future, value: Any = None, exc: BaseException | None = None) -> None:
    try:
        if exc is not None:
            future.set_exception(exc)
        else:
            future.set_result(value)
    except concurrent.futures.InvalidStateError:
        pass  # cancelled by its caller, or already settled
