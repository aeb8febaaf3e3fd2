"""Prometheus metrics, one CollectorRegistry per app (tests start several apps in one process).

    cadreg_requests_total{transport, route, code}       answered requests; code = "ok" or the wire error code
    cadreg_request_latency_seconds{transport, route}    arrival to answer
    cadreg_stage_latency_seconds{stage}                 per pipeline stage (diagnostics.stage_ms) and the pool's
                                                        own stages (queue, worker)
    cadreg_queue_depth                                  jobs waiting for a worker
    cadreg_workers_alive                                worker processes serving
    cadreg_worker_restarts_total{reason}                crashed | timeout | start_failed | start_timeout
    cadreg_zenoh_dropped_frames_total{site}             stream frames dropped because a device outran the pool
                                                        (loaded sites only: no state is kept for any other)
    cadreg_zenoh_refused_frames_total{reason}           stream frames refused on arrival: unknown_site,
                                                        payload_too_large, device_cap, stream_budget,
                                                        shutting_down (no per-site label: a client picks sites)
    cadreg_site_info{site_id, version}                  1 per served site version
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

if TYPE_CHECKING:
    from .pool import WorkerPool
    from .registry import SiteRegistry

_LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class _StateCollector:
    """Reads the pool and registry at scrape time, so the numbers are never stale."""

    def __init__(self, pool: Callable[[], "WorkerPool | None"], registry: Callable[[], "SiteRegistry | None"]) -> None:
        self._pool = pool
        self._registry = registry

    def collect(self):
        pool = self._pool()
        queue = GaugeMetricFamily("cadreg_queue_depth", "jobs waiting for a worker")
        alive = GaugeMetricFamily("cadreg_workers_alive", "worker processes serving")
        restarts = CounterMetricFamily("cadreg_worker_restarts", "worker processes replaced", labels=["reason"])
        if pool is not None:
            queue.add_metric([], pool.queue_len())
            alive.add_metric([], pool.alive())
            for reason, n in sorted(pool.restarts.items()):
                restarts.add_metric([reason], n)
        yield queue
        yield alive
        yield restarts
        sites = GaugeMetricFamily("cadreg_site_info", "served site versions", labels=["site_id", "version"])
        registry = self._registry()
        if registry is not None:
            for entry in registry.entries():
                sites.add_metric([entry.site_id, entry.version], 1)
        yield sites


class Metrics:
    def __init__(self, pool: Callable[[], Any], registry: Callable[[], Any]) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("cadreg_requests", "answered requests", ["transport", "route", "code"],
                                registry=self.registry)
        self.latency = Histogram("cadreg_request_latency_seconds", "arrival to answer", ["transport", "route"],
                                 buckets=_LATENCY_BUCKETS_S, registry=self.registry)
        self.stage = Histogram("cadreg_stage_latency_seconds", "time per stage", ["stage"],
                               buckets=_LATENCY_BUCKETS_S, registry=self.registry)
        self.zenoh_dropped = Counter("cadreg_zenoh_dropped_frames", "stream frames dropped (device outran the pool)",
                                     ["site"], registry=self.registry)
        self.zenoh_refused = Counter("cadreg_zenoh_refused_frames", "stream frames refused on arrival", ["reason"],
                                     registry=self.registry)
        self.registry.register(_StateCollector(pool, registry))

    def observe_request(self, transport: str, route: str, code: str, seconds: float) -> None:
        self.requests.labels(transport, route, code).inc()
        self.latency.labels(transport, route).observe(seconds)

    def observe_job(self, job: Any) -> None:
        """Stage timings of a finished localize job (a pool JobResult)."""
        self.stage.labels("queue").observe(job.queue_ms / 1e3)
        self.stage.labels("worker").observe(job.run_ms / 1e3)
        stage_ms = (job.result.get("diagnostics") or {}).get("stage_ms") or {}
        for name, ms in stage_ms.items():
            if isinstance(ms, (int, float)) and ms >= 0:
                self.stage.labels(str(name)).observe(float(ms) / 1e3)

    def render(self) -> bytes:
        return generate_latest(self.registry)
