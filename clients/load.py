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
from dataclasses import asdict, dataclass, field, replace
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
    code : None when the service answered with a result, else the error code (wire code or client-only code;
        "lost" for a stream frame that got no answer in time).
    status : the result's status (ok, ambiguous, no_match, ...) when answered.
    t_err_m, r_err_deg : pose errors against the frame's T_map_camera when both exist.
    device : which of a stream run's devices sent it (0 otherwise). mode : the result's `diagnostics.mode` (tracked |
        relocalized | global for a session's frames). stage_ms : the result's `diagnostics.stage_ms` (worker time).
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
    device: int = 0
    mode: str | None = None
    stage_ms: dict[str, float] | None = None


@dataclass
class LoadRun:
    records: list[RequestRecord]
    wall_s: float
    retries: int
    plan: LoadPlan
    target: str
    rss_mb: dict[str, float] = field(default_factory=dict)
    warmup: list[RequestRecord] = field(default_factory=list)  # stream runs: each device's warm-up frames


def _settle(record: RequestRecord, answer, frame: EncodedFrame) -> None:
    """Record a stream answer (a zenoh/HTTP stream result with `lost`, `error`, `result`) on its request."""
    if answer.lost:
        record.code = "lost"
    elif answer.error is not None:
        record.code = answer.error.code
    else:
        _score(record, answer.result, frame)


def _score(record: RequestRecord, result: dict[str, Any], frame: EncodedFrame) -> None:
    record.status = str(result.get("status"))
    diagnostics = result.get("diagnostics")
    if isinstance(diagnostics, dict):
        record.mode = diagnostics.get("mode")
        stages = diagnostics.get("stage_ms")
        if isinstance(stages, dict):
            record.stage_ms = {str(k): float(v) for k, v in stages.items() if isinstance(v, (int, float))}
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


# --- stream runs: frames in order as tracked device sessions -----------------------------------------------------


def parse_ranges(spec: str) -> list[tuple[int, int]]:
    """"250:500" or "0:100,400:500" -> [(250, 500)] / [(0, 100), (400, 500)]: frame numbers A <= i < B, each range
    in order, ranges concatenated (a kidnapped-robot stream jumps from one to the next). ValueError when malformed."""
    out = []
    for part in spec.split(","):
        a, sep, b = part.strip().partition(":")
        try:
            lo, hi = int(a), int(b)
        except ValueError:
            raise ValueError(f"bad range {part!r}: expected A:B with integers A < B") from None
        if not sep or lo < 0 or hi <= lo:
            raise ValueError(f"bad range {part!r}: expected A:B with 0 <= A < B")
        out.append((lo, hi))
    if not out:
        raise ValueError("empty range")
    return out


def select_indices(indices: Sequence[int], spec: str | None) -> list[int]:
    """The folder's frame numbers inside the ranges of `spec` (all when None), in the ranges' order."""
    if spec is None:
        return list(indices)
    have = set(indices)
    return [i for lo, hi in parse_ranges(spec) for i in range(lo, hi) if i in have]


@dataclass(frozen=True)
class StreamPlan:
    """K devices, each its own tracking session, each playing the frames in order at `rate_hz`.

    n : frames per device (the sequence is cycled when longer; default: the sequence once).
    device : device name (the only one when devices == 1, else the prefix of `<device>-<k>`).
    lost_after_s : a frame with no answer this long after it was sent is lost.
    warmup : the first frames of each device are sent one at a time, each after the answer to the one before, and
        reported apart (`warmup` in the summary): a robot localizes once, then streams. The timed stream follows
        with the next frame.
    Every frame carries `stamp_s` = its place in the sequence / rate_hz (its capture time had it been recorded at
    that rate), so the service times the motion as the sequence moved, not as the frames arrived.
    """

    devices: int = 1
    rate_hz: float = 30.0
    n: int | None = None
    device: str = "load"
    lost_after_s: float = 10.0
    warmup: int = 1

    def __post_init__(self) -> None:
        if self.devices < 1:
            raise ValueError("devices must be >= 1")
        if self.warmup < 0:
            raise ValueError("warmup must be >= 0")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError("rate_hz must be a positive number")
        if self.n is not None and self.n < 1:
            raise ValueError("n must be >= 1")
        if self.lost_after_s <= 0:
            raise ValueError("lost_after_s must be positive")

    mode = "stream"
    concurrency = None

    def device_name(self, k: int) -> str:
        return self.device if self.devices == 1 else f"{self.device}-{k}"


def _stream_records(frames: Sequence[EncodedFrame], plan: StreamPlan) -> tuple[list[list[RequestRecord]], list[list[RequestRecord]]]:
    """(warm-up records, timed records) per device; `seq` is the frame's place in the device's sequence."""
    n = plan.n if plan.n is not None else len(frames)
    w = min(plan.warmup, n - 1)
    period = 1.0 / plan.rate_hz
    # devices start a fraction of a period apart, as independent robots would, not all on the same tick
    timed = [[RequestRecord(seq=k, frame=k % len(frames), scheduled_s=(k - w) * period + d * period / plan.devices,
                            sent_s=math.nan, device=d) for k in range(w, n)] for d in range(plan.devices)]
    warm = [[RequestRecord(seq=k, frame=k % len(frames), scheduled_s=math.nan, sent_s=math.nan, device=d)
             for k in range(w)] for d in range(plan.devices)]
    return warm, timed


def _stamped(frame: EncodedFrame, rec: RequestRecord, plan: StreamPlan, session_id: str | None = None) -> EncodedFrame:
    update: dict[str, Any] = {"stamp_s": rec.seq / plan.rate_hz, "frame_id": f"{rec.device}:{rec.seq}"}
    if session_id is not None:
        update["session_id"] = session_id
    return replace(frame, meta=frame.meta.model_copy(update=update))


def run_stream_zenoh(endpoint: str, site_id: str, frames: Sequence[EncodedFrame], plan: StreamPlan, *,
                     progress: Callable[[RequestRecord], None] | None = None) -> LoadRun:
    """Play `frames` in order as `plan.devices` zenoh stream devices (`ZenohClient.stream`, one thread each),
    frame k of a device published at its scheduled time; latency from that time to its pose message."""
    import threading

    if not frames:
        raise ValueError("no frames to send")
    warm, per_device = _stream_records(frames, plan)
    client = ZenohClient(endpoint)
    streams = [client.stream(site_id, plan.device_name(d), lost_after_s=plan.lost_after_s)
               for d in range(plan.devices)]
    for s in streams:
        s.wait_ready()
    lock = threading.Lock()
    start = threading.Barrier(plan.devices)
    t0 = time.monotonic()

    def warm_up(d: int) -> None:
        stream = streams[d]
        for rec in warm[d]:
            rec.sent_s = time.monotonic() - t0
            rec.scheduled_s = rec.sent_s
            stream.send(_stamped(frames[rec.frame], rec, plan))
            for r in stream.results():
                rec.done_s = rec.sent_s + r.latency_ms / 1e3
                rec.latency_ms = r.latency_ms
                _settle(rec, r, frames[rec.frame])

    def play(d: int) -> None:
        nonlocal t0
        warm_up(d)
        if start.wait() == 0:
            t0 = time.monotonic()  # the timed stream starts when every device is warm
        start.wait()
        stream, records = streams[d], per_device[d]
        by_id: dict[str, RequestRecord] = {}

        def take(results: list) -> None:
            for r in results:
                rec = by_id.pop(r.frame_id, None)
                if rec is None:
                    continue
                rec.done_s = rec.sent_s + r.latency_ms / 1e3
                rec.latency_ms = (rec.done_s - rec.scheduled_s) * 1e3
                _settle(rec, r, frames[rec.frame])
                if progress is not None:
                    with lock:
                        progress(rec)

        for rec in records:
            while (delay := rec.scheduled_s - (time.monotonic() - t0)) > 0:
                take(stream.poll(timeout_s=min(delay, 0.05)))
            rec.sent_s = time.monotonic() - t0
            by_id[stream.send(_stamped(frames[rec.frame], rec, plan))] = rec
            take(stream.poll())
        while stream.pending:
            take(stream.poll(timeout_s=0.05))

    threads = [threading.Thread(target=play, args=(d,), name=f"cadreg-load-stream-{d}") for d in range(plan.devices)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        for s in streams:
            s.close()
        client.close()
    records = sorted((r for recs in per_device for r in recs), key=lambda r: (r.scheduled_s, r.device))
    return LoadRun(records, time.monotonic() - t0, client.retries, plan, f"zenoh stream {endpoint}",  # type: ignore[arg-type]
                   warmup=[r for recs in warm for r in recs])


async def run_stream_http(url: str, site_id: str, frames: Sequence[EncodedFrame], plan: StreamPlan, *,
                          timeout_s: float = 60.0, retry: RetryPolicy | None = None,
                          progress: Callable[[RequestRecord], None] | None = None, transport: Any = None) -> LoadRun:
    """Play `frames` in order as `plan.devices` HTTP sessions (`session_id` = the device name): a device sends its
    next frame at its scheduled time, or when its previous answer came if that was later (a session's frames go
    one at a time); latency from the scheduled time."""
    if not frames:
        raise ValueError("no frames to send")
    warm, per_device = _stream_records(frames, plan)
    client = AsyncClient(url, read_timeout_s=timeout_s, deadline_s=timeout_s, retry=retry, transport=transport)
    t0 = time.monotonic()

    async def send(rec: RequestRecord, session: str, report: bool) -> None:
        rec.sent_s = time.monotonic() - t0
        if math.isnan(rec.scheduled_s):
            rec.scheduled_s = rec.sent_s
        try:
            result = await client.localize(site_id, _stamped(frames[rec.frame], rec, plan, session))
        except ClientError as exc:
            rec.code = exc.code
        else:
            _score(rec, result, frames[rec.frame])
        rec.done_s = time.monotonic() - t0
        rec.latency_ms = (rec.done_s - rec.scheduled_s) * 1e3
        if report and progress is not None:
            progress(rec)

    async def warm_up(d: int) -> None:
        for rec in warm[d]:
            await send(rec, plan.device_name(d), False)

    async def play(d: int) -> None:
        for rec in per_device[d]:
            delay = rec.scheduled_s - (time.monotonic() - t0)
            if delay > 0:
                await asyncio.sleep(delay)
            await send(rec, plan.device_name(d), True)

    try:
        await asyncio.gather(*(warm_up(d) for d in range(plan.devices)))
        t0 = time.monotonic()  # the timed stream starts when every device is warm
        await asyncio.gather(*(play(d) for d in range(plan.devices)))
    finally:
        await client.aclose()
    records = sorted((r for recs in per_device for r in recs), key=lambda r: (r.scheduled_s, r.device))
    return LoadRun(records, time.monotonic() - t0, client.retries, plan, f"http stream {url}",  # type: ignore[arg-type]
                   warmup=[r for recs in warm for r in recs])


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
    stream = _stream_summary(run, ok) if isinstance(run.plan, StreamPlan) else {}
    if stream:
        errors.pop("lost", None)  # counted on its own
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
        **stream,
    }


def _stream_summary(run: LoadRun, answered: list[RequestRecord]) -> dict[str, Any]:
    """A stream run's own keys (DESIGN §8 with --stream): answered, lost, tracked, relocalized (and global), the
    devices and their rate, and the worker's time of tracked frames (sum of `diagnostics.stage_ms`, and per stage)."""
    modes: dict[str, int] = {}
    for r in answered:
        modes[str(r.mode)] = modes.get(str(r.mode), 0) + 1
    tracked = [r for r in answered if r.mode == "tracked" and r.stage_ms]
    stages = sorted({k for r in tracked for k in r.stage_ms or {}})
    plan: StreamPlan = run.plan  # type: ignore[assignment]
    warm = run.warmup
    return {
        "warmup": {"frames": len(warm), "answered": sum(1 for r in warm if r.code is None),
                   "latency_ms_max": max((r.latency_ms for r in warm if r.code is None), default=None),
                   "modes": sorted({str(r.mode) for r in warm if r.code is None})},
        "answered": len(answered),
        "lost": sum(1 for r in run.records if r.code == "lost"),
        "tracked": modes.get("tracked", 0),
        "relocalized": modes.get("relocalized", 0),
        "global": modes.get("global", 0),
        "devices": plan.devices,
        "rate_hz_per_device": plan.rate_hz,
        "tracked_worker_ms": {
            "p50": percentile([sum(r.stage_ms.values()) for r in tracked], 50),  # type: ignore[union-attr]
            "p90": percentile([sum(r.stage_ms.values()) for r in tracked], 90),  # type: ignore[union-attr]
            "stage_ms_p50": {k: percentile([r.stage_ms.get(k, 0.0) for r in tracked], 50) for k in stages},  # type: ignore[union-attr]
        },
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

