"""Distinct device ids cannot grow the service: a flood of stream devices, one small real frame each, leaves the
service's memory (its process tree) within 60 MB of where it started, its device table and tracking sessions within
their caps, and a live tracked device is answered within 1 s throughout (tracked sessions go before new devices).

Real `cadreg serve` (a subprocess, 2 workers, zenoh on loopback, scouting off) and real zenoh clients. The default
run floods 1,500 ids; `CADREG_FLOOD_DEVICES=20000 pytest -m slow tests/test_stream_flood.py` is the acceptance run
of issue 12 (it prints the figures)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh

from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from cadreg.io.frames import RecordedFrames
from clients.frames import encode_frame
from clients.load import process_tree_rss_mb
from clients.zenoh_client import ZenohClient
from service import zenoh_wire
from test_service_support import free_ports
from tracking_support import SITE_ID, redkitchen_site

MAX_SESSIONS = 300
MAX_DEVICES = 300
FLOOD = int(os.environ.get("CADREG_FLOOD_DEVICES", "1500"))
LIVE_HZ = 2.0


def _small(frame: Frame, step: int = 4) -> Frame:
    """The frame at 1/step of its size (same field of view): cheap to send and to search."""
    def scaled(K: CameraIntrinsics) -> CameraIntrinsics:
        return CameraIntrinsics(K.width // step, K.height // step, K.fx / step, K.fy / step, K.cx / step, K.cy / step)

    return replace(frame, depth=np.ascontiguousarray(frame.depth[::step, ::step]),
                   color=np.ascontiguousarray(frame.color[::step, ::step]),
                   depth_intrinsics=scaled(frame.depth_intrinsics), color_intrinsics=scaled(frame.color_intrinsics))


@pytest.fixture(scope="module")
def served(redkitchen_dir: Path, tmp_path_factory):
    site_dir = redkitchen_site(redkitchen_dir, tmp_path_factory.mktemp("rk-flood"))
    port, zport = free_ports(2)
    env = {**os.environ, "CADREG_MAX_SESSIONS": str(MAX_SESSIONS), "CADREG_STREAM_MAX_DEVICES": str(MAX_DEVICES),
           "CADREG_LOG_REQUESTS": "false", "CADREG_SESSION_TTL_S": "30"}
    proc = subprocess.Popen([sys.executable, "-m", "cadreg.cli.main", "serve", "--sites", str(site_dir.parent),
                             "--port", str(port), "--workers", "2", "--zenoh-listen", f"tcp/127.0.0.1:{zport}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).json().get("ready"):
                break
        except httpx.TransportError:
            pass
        time.sleep(0.5)
    else:
        proc.kill()
        raise TimeoutError("cadreg serve did not become ready")
    yield proc, f"tcp/127.0.0.1:{zport}", f"http://127.0.0.1:{port}"
    proc.terminate()
    proc.wait(30)


def _flood(endpoint: str, payload: bytes, n: int, rate_hz: float) -> None:
    session = zenoh.open(zenoh_wire.session_config(connect=[endpoint]))
    try:
        time.sleep(0.5)
        t0 = time.monotonic()
        for k in range(n):
            session.put(zenoh_wire.frames_key(SITE_ID, f"flood-{k}"), payload)
            delay = t0 + (k + 1) / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    finally:
        session.close()


def _metric(url: str, name: str) -> float:
    text = httpx.get(url + "/metrics", timeout=10).text
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name))


def test_a_flood_of_device_ids_stays_bounded_and_a_live_device_is_answered(served, redkitchen_dir: Path) -> None:
    proc, endpoint, url = served
    recorded = RecordedFrames.open(redkitchen_dir)
    small = encode_frame(_small(recorded.load(260)[0]))
    flood_payload = small.envelope()
    live_frames = [encode_frame(recorded.load(i)[0]) for i in range(250, 290)]
    latencies: list[float] = []
    modes: list[str | None] = []
    rss: list[float] = []
    with ZenohClient(endpoint, timeout_s=30.0) as z, z.stream(SITE_ID, "live", lost_after_s=5.0) as live:
        assert live.wait_ready()

        def step(k: int) -> None:
            enc = live_frames[k % len(live_frames)]
            live.send(replace(enc, meta=enc.meta.model_copy(update={"stamp_s": k / 30.0})), frame_id=f"live-{k}")
            got = next(iter(live.results()))
            latencies.append(got.latency_ms)
            modes.append(got.mode if not got.lost else "lost")

        for k in range(6):  # warm up: the live device is tracked, the workers have built what they build lazily
            step(k)
        time.sleep(2.0)
        rss.append(process_tree_rss_mb(proc.pid))
        flood = threading.Thread(target=_flood, args=(endpoint, flood_payload, FLOOD, 400.0), daemon=True)
        started = time.monotonic()
        flood.start()
        k = 6
        while flood.is_alive() or time.monotonic() - started < 5.0:
            step(k)
            k += 1
            rss.append(process_tree_rss_mb(proc.pid))
            time.sleep(max(0.0, 1.0 / LIVE_HZ - latencies[-1] / 1e3))
        flood.join()
        # let the admitted flood frames drain, then read the memory the service is left with
        for _ in range(120):
            step(k)
            k += 1
            if _metric(url, "cadreg_queue_depth") == 0:
                break
            time.sleep(0.5)
        time.sleep(2.0)
        end_rss = process_tree_rss_mb(proc.pid)
    during = latencies[6:]
    print(json.dumps({"flood_devices": FLOOD, "live_frames": len(during), "live_latency_ms_max": max(during),
                      "live_latency_ms_p50": float(np.median(during)), "live_modes": sorted(set(modes[6:])),
                      "rss_mb_start": rss[0], "rss_mb_max": max(rss), "rss_mb_end": end_rss,
                      "refused": _metric(url, "cadreg_zenoh_refused_frames_total"),
                      "dropped": _metric(url, "cadreg_zenoh_dropped_frames_total")}))
    assert "lost" not in modes[6:]
    assert max(during) < 1000.0, during
    assert modes[6:].count("tracked") >= 0.8 * len(during)
    assert end_rss - rss[0] < 60.0, (rss[0], end_rss)
    assert max(rss) - rss[0] < 60.0 + 50.0  # pending frames are bounded too (they go once answered or dropped)
