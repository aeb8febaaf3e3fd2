"""Load tester core: replay encoded frames against the service and measure throughput, latency, errors, accuracy.

Two ways to drive load (`LoadPlan`):
- closed loop, `concurrency=C`: C requests in flight at all times; each latency is send -> answer.
- open loop, `rate_hz=R`: request k is *scheduled* at t0 + k/R whether or not earlier ones came back; its latency
  counts from the scheduled time, so time spent queued behind a slow service (or in the client's own pool) is
  measured, not hidden (coordinated omission).
The run is bounded by `n` requests and/or `duration_s` of sending, then at most `drain_timeout_s` for the requests
still in flight (any left are cancelled and counted as `cancelled`). Frames are cycled when n exceeds their number.

Encoding happens before the run (`clients.frames.encode_folder`); the timed loop only sends bytes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import math
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from cadreg.geometry import pose_errors

from .errors import ClientError
from .frames import EncodedFrame
from .http import AsyncClient, pose_of
from .retry import RetryPolicy
from .zenoh_client import ZenohClient

SUCCESS_T_M, SUCCESS_R_DEG = 0.05, 5.0


class Target(Protocol):
    """Something that localizes an EncodedFrame and counts its retries."""

    name: str
    retries: int

    def prepare(self, frames: Sequence[EncodedFrame]) -> None: ...

    async def localize(self, frame: EncodedFrame) -> dict[str, Any]: ...

    async def aclose(self) -> None: ...


class HttpTarget:
    """The service over HTTP, through `AsyncClient` (one event loop, one connection pool)."""

    def __init__(self, url: str, site_id: str, *, timeout_s: float = 60.0, retry: RetryPolicy | None = None,
                 max_connections: int = 256, transport: Any = None) -> None:
        self.name = f"http {url}"
        self.url = url
        self.site_id = site_id
        self._client = AsyncClient(url, read_timeout_s=timeout_s, deadline_s=timeout_s, retry=retry,
                                   max_connections=max_connections, transport=transport)

    @property
    def retries(self) -> int:
        return self._client.retries

    async def localize(self, frame: EncodedFrame) -> dict[str, Any]:
        return await self._client.localize(self.site_id, frame)

    async def metrics_text(self) -> str:
        return await self._client.metrics_text()

    def prepare(self, frames: Sequence[EncodedFrame]) -> None:
        """Nothing to pack: httpx builds the multipart body from the encoded parts per request."""

    async def aclose(self) -> None:
        await self._client.aclose()


class ZenohTarget:
    """The service over zenoh (queryable `cadreg/<site>/localize`); zenoh queries block, so they run on threads."""

    def __init__(self, endpoint: str, site_id: str, *, timeout_s: float = 60.0, retry: RetryPolicy | None = None,
                 max_threads: int = 64) -> None:
        self.name = f"zenoh {endpoint}"
        self.site_id = site_id
        self._client = ZenohClient(endpoint, timeout_s=timeout_s, deadline_s=timeout_s, retry=retry)
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=max_threads, thread_name_prefix="cadreg-load")
        self._envelopes: dict[int, bytes] = {}

    @property
    def retries(self) -> int:
        return self._client.retries

    def prepare(self, frames: Sequence[EncodedFrame]) -> None:
        """Pack every envelope before the timed loop."""
        self._envelopes = {id(f): f.envelope() for f in frames}

    async def localize(self, frame: EncodedFrame) -> dict[str, Any]:
        payload = self._envelopes.get(id(frame))
        if payload is None:
            payload = frame.envelope()
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, self._client.localize_envelope, self.site_id, payload)

    async def aclose(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._client.close()


@dataclass(frozen=True)
class LoadPlan:
    """concurrency XOR rate_hz; at least one of n and duration_s bounds the run."""

    concurrency: int | None = None
    rate_hz: float | None = None
    n: int | None = None
    duration_s: float | None = None
    drain_timeout_s: float = 60.0
    max_in_flight: int = 512  # open loop: beyond this the client itself is the bottleneck; such sends wait

    def __post_init__(self) -> None:
        if (self.concurrency is None) == (self.rate_hz is None):
            raise ValueError("give exactly one of concurrency (closed loop) and rate_hz (open loop)")
        if self.concurrency is not None and self.concurrency < 1:
            raise ValueError("concurrency must be >= 1")
        if self.rate_hz is not None and not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError("rate_hz must be a positive number")
        if self.n is None and self.duration_s is None:
            raise ValueError("bound the run with n and/or duration_s")
        if self.n is not None and self.n < 1:
            raise ValueError("n must be >= 1")
        if self.duration_s is not None and self.duration_s <= 0:
            raise ValueError("duration_s must be positive")

    @property
    def mode(self) -> str:
        return "closed" if self.concurrency is not None else "open"


@dataclass
class RequestRecord:
    """One request of a run. Times are seconds from the start of the run (monotonic clock).

    scheduled_s : when it was due (open loop) or sent (closed loop); latency_ms counts from here.
    code : None when the service answered with a result, else the error code (wire code or client-only code).
    status : the result's status (ok, ambiguous, no_match, ...) when answered.
    t_err_m, r_err_deg : pose errors against the frame's T_map_camera when both exist.
    """

    seq: int
    frame: int
    scheduled_s: float
    sent_s: float
    done_s: float = math.nan
    latency_ms: float = math.nan
    code: str | None = None
    status: str | None = None
    t_err_m: float | None = None
    r_err_deg: float | None = None
    has_truth: bool = False


@dataclass
class LoadRun:
    records: list[RequestRecord]
    wall_s: float
    retries: int
    plan: LoadPlan
    target: str
    rss_mb: dict[str, float] = field(default_factory=dict)


def _score(record: RequestRecord, result: dict[str, Any], frame: EncodedFrame) -> None:
    record.status = str(result.get("status"))
    if frame.T_map_camera is None:
        return
    record.has_truth = True
    T = pose_of(result)
    if T is not None and T.shape == (4, 4) and np.all(np.isfinite(T)):
        record.t_err_m, record.r_err_deg = pose_errors(T, frame.T_map_camera)


async def run_load(
    target: Target,
    frames: Sequence[EncodedFrame],
    plan: LoadPlan,
    *,
    progress: Callable[[RequestRecord], None] | None = None,
    rss_sampler: Callable[[], float | None] | None = None,
) -> LoadRun:
    """Drive `target` with `frames` (cycled) according to `plan`; one RequestRecord per request sent.

    progress(record) is called as each request completes. rss_sampler() -> MiB is read at the start and the end
    (and every ~5 s in between) to report the service's memory.
    """
    if not frames:
        raise ValueError("no frames to send")
    target.prepare(frames)
    records: list[RequestRecord] = []
    t0 = time.monotonic()
    stop_at = None if plan.duration_s is None else t0 + plan.duration_s
    n_max = plan.n if plan.n is not None else 2**62
    rss: list[float] = []

    def now_s() -> float:
        return time.monotonic() - t0

    async def one(seq: int, scheduled_s: float) -> None:
        frame = frames[seq % len(frames)]
        rec = RequestRecord(seq=seq, frame=seq % len(frames), scheduled_s=scheduled_s, sent_s=now_s())
        records.append(rec)
        try:
            result = await target.localize(frame)
        except ClientError as exc:
            rec.code = exc.code
        except asyncio.CancelledError:
            rec.code = "cancelled"
            rec.done_s = now_s()
            raise
        except Exception as exc:  # noqa: BLE001 - an answer the client could not handle must not stop the run
            rec.code = f"exception:{type(exc).__name__}"
        else:
            _score(rec, result, frame)
        rec.done_s = now_s()
        rec.latency_ms = (rec.done_s - rec.scheduled_s) * 1e3
        if progress is not None:
            progress(rec)

    async def sample_rss() -> None:
        while True:
            value = rss_sampler() if rss_sampler else None
            if value is not None:
                rss.append(value)
            await asyncio.sleep(5.0)

    sampler = asyncio.create_task(sample_rss()) if rss_sampler else None
    tasks: set[asyncio.Task] = set()
    seq = 0
    if plan.concurrency is not None:
        counter = iter(range(n_max))

        async def worker() -> None:
            while True:
                k = next(counter, None)
                if k is None or (stop_at is not None and time.monotonic() >= stop_at):
                    return
                await one(k, now_s())

        tasks = {asyncio.create_task(worker()) for _ in range(plan.concurrency)}
    else:
        period = 1.0 / plan.rate_hz  # type: ignore[operator]
        gate = asyncio.Semaphore(plan.max_in_flight)

        async def scheduled(k: int, due_s: float) -> None:
            async with gate:
                await one(k, due_s)

        # the schedule, not the clock, decides the count: exactly rate * duration requests
        while seq < n_max and (plan.duration_s is None or seq * period < plan.duration_s - 1e-9):
            due = seq * period
            delay = due - now_s()
            if delay > 0:
                await asyncio.sleep(delay)
            task = asyncio.create_task(scheduled(seq, due))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
            seq += 1
    if tasks:
        drain = plan.drain_timeout_s
        if plan.concurrency is not None and plan.duration_s is not None:
            drain += plan.duration_s  # closed-loop workers send until the duration is over
        if plan.concurrency is not None and plan.duration_s is None:
            drain = None  # bounded by n and by each request's own deadline
        _, pending = await asyncio.wait(tasks, timeout=drain)
        for task in pending:
            task.cancel()
        if pending:
            await asyncio.gather(*pending, return_exceptions=True)
    wall_s = now_s()
    if sampler is not None:
        sampler.cancel()
        await asyncio.gather(sampler, return_exceptions=True)
        end = rss_sampler()  # type: ignore[misc]
        if end is not None:
            rss.append(end)
    # A fresh service grows while its workers warm up (first requests, lazily built structures); the sample a tenth
    # of the way in tells that growth from a leak over the rest of the run.
    rss_mb = ({"start": rss[0], "after_10pct": rss[len(rss) // 10], "end": rss[-1], "max": max(rss), "min": min(rss),
               "samples": len(rss)} if rss else {})
    for rec in records:
        if math.isnan(rec.done_s):
            rec.code = rec.code or "cancelled"
    return LoadRun(sorted(records, key=lambda r: r.seq), wall_s, target.retries, plan, target.name, rss_mb)


def percentile(values: Sequence[float], q: float) -> float | None:
    return None if len(values) == 0 else float(np.percentile(np.asarray(values, dtype=float), q))


def summarize(run: LoadRun) -> dict[str, Any]:
    """The `cadreg load --json` document (DESIGN §8) plus retries, mode, wall time and service RSS.

    throughput_fps : answered requests (results, any status) per second of wall time.
    latency_ms : over answered requests (p50/p90/p99/max), from the scheduled time in open loop.
    accuracy : over answered requests whose frame has a ground-truth pose, scored as `cadreg bench` does: success =
        a pose within 5 cm and 5°; median translation error with "no pose" counted as infinite (None when the
        median is); None when no frame has a ground truth.
    """
    ok = [r for r in run.records if r.code is None]
    errors: dict[str, int] = {}
    for r in run.records:
        if r.code is not None:
            errors[r.code] = errors.get(r.code, 0) + 1
    lat = [r.latency_ms for r in ok]
    truth = [r for r in ok if r.has_truth]
    accuracy = None
    if truth:
        # as `cadreg bench` scores them: a frame answered without a pose counts as an infinite error
        t_err = np.array([math.inf if r.t_err_m is None else r.t_err_m for r in truth])
        r_err = np.array([math.inf if r.r_err_deg is None else r.r_err_deg for r in truth])
        median_t = float(np.median(t_err))
        accuracy = {
            "success_5cm_5deg": float(np.mean((t_err <= SUCCESS_T_M) & (r_err <= SUCCESS_R_DEG))),
            "median_translation_m": median_t if math.isfinite(median_t) else None,
            "frames_scored": len(truth),
        }
    statuses: dict[str, int] = {}
    for r in ok:
        statuses[str(r.status)] = statuses.get(str(r.status), 0) + 1
    return {
        "sent": len(run.records),
        "ok": len(ok),
        "errors": dict(sorted(errors.items())),
        "throughput_fps": len(ok) / run.wall_s if run.wall_s > 0 else 0.0,
        "latency_ms": {
            "p50": percentile(lat, 50),
            "p90": percentile(lat, 90),
            "p99": percentile(lat, 99),
            "max": max(lat) if lat else None,
        },
        "accuracy": accuracy,
        "retries": run.retries,
        "status_counts": dict(sorted(statuses.items())),
        "mode": run.plan.mode,
        "concurrency": run.plan.concurrency,
        "rate_hz": run.plan.rate_hz,
        "wall_s": run.wall_s,
        "target": run.target,
        "service_rss_mb": run.rss_mb or None,
    }


def records_as_dicts(run: LoadRun) -> list[dict[str, Any]]:
    return [asdict(r) for r in run.records]


# --- service memory -----------------------------------------------------------------------------------------------


def process_tree_rss_mb(pid: int) -> float | None:
    """Resident memory (MiB) of process `pid` and all its descendants, from /proc (Linux); None when gone."""
    stats = process_tree_stats(pid)
    return None if stats is None else stats[0]


def process_tree_stats(pid: int) -> tuple[float, float] | None:
    """(resident memory MiB, CPU seconds user+system) of `pid` and its live descendants, from /proc; None when gone."""
    tick = os.sysconf("SC_CLK_TCK")
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    total_kb = 0
    cpu_ticks = 0
    stack, seen = [pid], set()
    while stack:
        p = stack.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            status = Path(f"/proc/{p}/status").read_text()
        except OSError:
            if p == pid:
                return None
            continue
        m = re.search(r"^VmRSS:\s+(\d+)\s+kB", status, re.M)
        total_kb += int(m.group(1)) if m else 0
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            cpu_ticks += int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of stat)
        except (OSError, IndexError, ValueError):
            pass
        stack.extend(children.get(p, []))
    return total_kb / 1024.0, cpu_ticks / tick


_RSS_METRIC_RE = re.compile(r"^(process_resident_memory_bytes|cadreg_\w*rss\w*bytes)(\{[^}]*\})?\s+([0-9.eE+-]+)", re.M)


def rss_from_metrics(text: str) -> float | None:
    """Service memory (MiB) from Prometheus text: the sum of `process_resident_memory_bytes` and any
    `cadreg_*rss*_bytes` gauges (worker processes), None when none is exposed."""
    values = [float(m.group(3)) for m in _RSS_METRIC_RE.finditer(text)]
    return sum(values) / 2**20 if values else None

