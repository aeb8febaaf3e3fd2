"""Load tester core with in-process targets: closed and open loop, bounds, coordinated omission, errors,
accuracy, the JSON document, the report; and the HTTP target through httpx.MockTransport."""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path

import httpx
import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from cadreg.geometry import make_T
from clients import errors as cerr
from clients.frames import EncodedFrame, encode_frame
from clients.load import (HttpTarget, LoadPlan, process_tree_rss_mb, process_tree_stats, rss_from_metrics, run_load,
                          summarize)
from clients.report import format_table, plot_run
from clients.retry import RetryPolicy


def _frames(n: int = 3, with_truth: bool = True) -> list[EncodedFrame]:
    K = CameraIntrinsics(16, 12, 15.0, 15.0, 7.5, 5.5)
    out = []
    for i in range(n):
        f = Frame(depth=np.full((12, 16), 1000 + i, np.uint16), color=np.zeros((12, 16, 3), np.uint8),
                  depth_intrinsics=K, color_intrinsics=K, frame_id=str(i))
        out.append(encode_frame(f, T_map_camera=make_T(t=np.array([float(i), 0.0, 0.0])) if with_truth else None))
    return out


class FakeTarget:
    """Answers after `service_s`, at most `capacity` at a time (a queue in front of `capacity` workers)."""

    name = "fake"

    def __init__(self, service_s: float = 0.01, capacity: int = 100, fail: dict[int, str] | None = None,
                 offset_m: float = 0.0) -> None:
        self.service_s, self.fail, self.offset_m = service_s, fail or {}, offset_m
        self.capacity = capacity
        self.retries = 0
        self.calls = 0
        self.in_flight = 0
        self.max_in_flight = 0
        self.prepared = 0
        self._gate: asyncio.Semaphore | None = None

    def prepare(self, frames) -> None:
        self.prepared = len(frames)

    async def localize(self, frame: EncodedFrame) -> dict:
        if self._gate is None:
            self._gate = asyncio.Semaphore(self.capacity)
        k = self.calls
        self.calls += 1
        self.in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        try:
            async with self._gate:
                await asyncio.sleep(self.service_s)
            if k in self.fail:
                raise cerr.ERRORS_BY_CODE[self.fail[k]]("nope")
            T = frame.T_map_camera.copy() if frame.T_map_camera is not None else np.eye(4)
            T[0, 3] += self.offset_m
            return {"status": "ok", "T_map_camera": T.tolist(), "frame_id": frame.frame_id}
        finally:
            self.in_flight -= 1

    async def aclose(self) -> None:
        pass


def test_closed_loop_keeps_concurrency_and_cycles_frames() -> None:
    target = FakeTarget(service_s=0.01)
    run = asyncio.run(run_load(target, _frames(3), LoadPlan(concurrency=3, n=20)))
    assert len(run.records) == 20 and target.calls == 20 and target.max_in_flight == 3
    assert target.prepared == 3
    assert [r.frame for r in run.records] == [k % 3 for k in range(20)]
    s = summarize(run)
    assert s["sent"] == 20 and s["ok"] == 20 and s["errors"] == {}
    assert s["accuracy"]["success_5cm_5deg"] == 1.0 and s["accuracy"]["median_translation_m"] == pytest.approx(0.0)
    assert 10 <= s["latency_ms"]["p50"] < 200


def test_open_loop_counts_queueing_from_the_scheduled_time() -> None:
    # 20 frames/s into a service doing 10 frames/s: each request waits longer; a tester that timed from its own
    # (delayed) send would not see it. Request k is answered around (k+1)*0.1 s, scheduled at k*0.05 s.
    target = FakeTarget(service_s=0.1, capacity=1)
    run = asyncio.run(run_load(target, _frames(2), LoadPlan(rate_hz=20, n=10)))
    lat = [r.latency_ms for r in run.records]
    assert len(lat) == 10 and target.max_in_flight > 3  # sends did not wait for answers
    assert lat[-1] > 450 and lat[-1] > 3 * lat[0], lat
    scheduled = [r.scheduled_s for r in run.records]
    assert scheduled == pytest.approx([k * 0.05 for k in range(10)])
    assert max(abs(r.sent_s - r.scheduled_s) for r in run.records) < 0.25  # slack for a busy machine


def test_duration_bounds_the_run() -> None:
    target = FakeTarget(service_s=0.001)
    run = asyncio.run(run_load(target, _frames(2), LoadPlan(rate_hz=50, duration_s=0.4)))
    assert len(run.records) == 20
    run = asyncio.run(run_load(FakeTarget(service_s=0.02), _frames(2), LoadPlan(concurrency=2, duration_s=0.3)))
    assert 4 <= len(run.records) <= 32 and run.wall_s < 2.0


def test_errors_by_code_and_accuracy_over_answers() -> None:
    target = FakeTarget(fail={1: "overloaded", 4: "invalid_frame", 5: "overloaded"}, offset_m=0.03)
    run = asyncio.run(run_load(target, _frames(3), LoadPlan(concurrency=1, n=10)))
    s = summarize(run)
    assert s["sent"] == 10 and s["ok"] == 7 and s["errors"] == {"invalid_frame": 1, "overloaded": 2}
    assert s["accuracy"]["success_5cm_5deg"] == 1.0 and s["accuracy"]["median_translation_m"] == pytest.approx(0.03)
    run = asyncio.run(run_load(FakeTarget(offset_m=0.08), _frames(3), LoadPlan(concurrency=1, n=3)))
    assert summarize(run)["accuracy"]["success_5cm_5deg"] == 0.0
    run = asyncio.run(run_load(FakeTarget(), _frames(3, with_truth=False), LoadPlan(concurrency=1, n=3)))
    assert summarize(run)["accuracy"] is None


def test_json_document_has_the_contract_keys(tmp_path: Path) -> None:
    readings = iter([100.0, 123.0, 124.0, 125.0])
    run = asyncio.run(run_load(FakeTarget(), _frames(2), LoadPlan(concurrency=2, n=6),
                               rss_sampler=lambda: next(readings)))
    s = summarize(run)
    doc = json.loads(json.dumps(s))
    assert {"sent", "ok", "errors", "throughput_fps", "latency_ms", "accuracy"} <= set(doc)
    assert set(doc["latency_ms"]) == {"p50", "p90", "p99", "max"}
    assert {"success_5cm_5deg", "median_translation_m"} <= set(doc["accuracy"])
    assert doc["service_rss_mb"] == {"start": 100.0, "after_10pct": 100.0, "end": 123.0, "max": 123.0, "min": 100.0,
                                     "samples": 2}
    table = format_table(s)
    assert "throughput" in table and "p50" in table and "success@5cm" in table
    assert "100 / 100 / 123 / 123 MiB" in table
    png = plot_run(run, tmp_path / "lat.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_plot_marks_the_percentiles_the_table_gives(tmp_path: Path, monkeypatch) -> None:
    import matplotlib.axes

    run = asyncio.run(run_load(FakeTarget(), _frames(3), LoadPlan(concurrency=3, n=40)))
    for k, r in enumerate(run.records):  # 40 spread latencies: p99 falls between the two largest
        r.latency_ms = 10.0 + k * (k % 7)
    marked: list[float] = []
    real = matplotlib.axes.Axes.axvline

    def axvline(ax, x=0, *args, **kwargs):
        marked.append(x)
        return real(ax, x, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "axvline", axvline)
    plot_run(run, tmp_path / "lat.png")
    latency = summarize(run)["latency_ms"]
    assert marked == [latency["p50"], latency["p99"]] and latency["p99"] < latency["max"]


def test_requests_that_never_answer_are_cancelled_at_the_drain_timeout() -> None:
    target = FakeTarget(service_s=30.0)
    run = asyncio.run(run_load(target, _frames(1), LoadPlan(rate_hz=20, n=3, drain_timeout_s=0.3)))
    s = summarize(run)
    assert s["sent"] == 3 and s["ok"] == 0 and s["errors"] == {"cancelled": 3} and run.wall_s < 2.0


def test_plan_validation() -> None:
    for bad in (dict(n=3), dict(concurrency=2, rate_hz=3, n=3), dict(concurrency=2), dict(concurrency=0, n=1),
                dict(rate_hz=-1, n=2), dict(concurrency=1, n=0)):
        with pytest.raises(ValueError):
            LoadPlan(**bad)


def test_http_target_counts_retries_through_the_async_client() -> None:
    answers = iter([503, 200, 200, 503, 503, 200])

    def handler(request: httpx.Request) -> httpx.Response:
        code = next(answers)
        if code == 503:
            return httpx.Response(503, json={"code": "overloaded", "message": "busy", "detail": {}},
                                  headers={"Retry-After": "0"})
        return httpx.Response(200, json={"status": "no_match", "T_map_camera": None})

    target = HttpTarget("http://svc", "s", retry=RetryPolicy(max_retries=3, backoff_base_s=0.001),
                        transport=httpx.MockTransport(handler))
    run = asyncio.run(run_load(target, _frames(2), LoadPlan(concurrency=1, n=3)))
    s = summarize(run)
    assert s["ok"] == 3 and s["retries"] == 3 and s["status_counts"] == {"no_match": 3}
    assert s["accuracy"]["success_5cm_5deg"] == 0.0 and s["accuracy"]["median_translation_m"] is None


def test_service_memory_readers() -> None:
    text = ("# HELP process_resident_memory_bytes x\nprocess_resident_memory_bytes 1.048576e+08\n"
            'cadreg_worker_rss_bytes{worker="0"} 5.24288e+07\nother_metric 7\n')
    assert rss_from_metrics(text) == pytest.approx(150.0)
    assert rss_from_metrics("nothing 1\n") is None
    mine = process_tree_rss_mb(os.getpid())
    assert mine is not None and mine > 10
    rss, cpu_s = process_tree_stats(os.getpid())
    assert rss > 10 and cpu_s > 0
    assert process_tree_rss_mb(2**22 + 12345) is None


def test_an_unexpected_exception_is_counted_not_fatal() -> None:
    class Broken(FakeTarget):
        async def localize(self, frame: EncodedFrame) -> dict:
            if self.calls == 1:
                self.calls += 1
                raise KeyError("T_map_camera")
            return await super().localize(frame)

    for plan in (LoadPlan(concurrency=2, n=4), LoadPlan(rate_hz=100, n=4)):
        s = summarize(asyncio.run(run_load(Broken(), _frames(2), plan)))
        assert s["sent"] == 4 and s["ok"] == 3 and s["errors"] == {"exception:KeyError": 1}
