"""Clients and the load tester against the real service on loopback: `cadreg serve` as a subprocess (uvicorn +
worker pool + zenoh peer) serving a site built from the real scene0470 data, frames rendered from its mesh."""

from __future__ import annotations

import concurrent.futures
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

from cadreg.cli.main import main as cadreg_main
from cadreg.geometry import pose_errors
from cadreg.io.frames import RecordedFrames
from clients import errors as cerr
from clients.frames import encode_recorded
from clients.http import Client, pose_of
from clients.retry import RetryPolicy
from clients.zenoh_client import ZenohClient
from test_service_support import free_port, free_ports, wait_served

pytestmark = pytest.mark.realdata
SITE = "scene0470"
CLI = [sys.executable, "-m", "cadreg.cli.main"]


@dataclass
class Served:
    url: str
    zenoh: str
    frames: Path
    log: Path
    pid: int


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, scene0470_dir: Path) -> Iterator[Served]:
    root = tmp_path_factory.mktemp("clients_service")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    mesh, labels = scene0470_dir / "scene0470_00_vh_clean_2.ply", scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"
    subprocess.run([*CLI, "site", "build", "--scan", str(mesh), "--labels", str(labels),
                    "--scan2cad", str(scene0470_dir / "scan2cad_annotation.json"),
                    "--cad-root", str(scene0470_dir / "shapenet"), "--out", str(root / "sites" / SITE),
                    "--site-id", SITE], check=True, env=env, capture_output=True)
    subprocess.run([*CLI, "render", "--mesh", str(mesh), "--labels", str(labels), "--out", str(root / "frames"),
                    "--n", "4", "--seed", "7"], check=True, env=env, capture_output=True)
    port, zport = free_ports(2)
    log = root / "serve.log"
    # one worker and a one-deep queue make overload easy to provoke; test hooks let a frame id make a worker sleep
    env.update(CADREG_TEST_HOOKS="true", CADREG_QUEUE_DEPTH="1")
    with open(log, "wb") as out:
        proc = subprocess.Popen([*CLI, "serve", "--sites", str(root / "sites"), "--port", str(port), "--workers", "1",
                                 "--zenoh-listen", f"tcp/127.0.0.1:{zport}"], env=env, stdout=out,
                                stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_served(proc, url, log)
        yield Served(url, f"tcp/127.0.0.1:{zport}", root / "frames", log, proc.pid)
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def test_http_client_routes_and_localize(served: Served) -> None:
    rf = RecordedFrames.open(served.frames)
    with Client(served.url) as c:
        assert c.health()["status"] == "ok"
        assert c.ready()["ready"] is True
        assert [s["site_id"] for s in c.sites()] == [SITE]
        info = c.site(SITE)
        assert info["site_id"] == SITE and info["nodes"] > 5
        result = c.localize(SITE, (served.frames, 0), frame_id="mine")
    assert result["frame_id"] == "mine" and result["request_id"] and result["site_id"] == SITE
    assert result["status"] in ("ok", "ambiguous", "no_objects", "no_match", "low_overlap", "failed")
    T = pose_of(result)
    if T is not None:
        t_err, r_err = pose_errors(T, rf.pose(0))
        assert np.isfinite(t_err) and np.isfinite(r_err)


def test_http_errors_are_typed(served: Served) -> None:
    enc = encode_recorded(served.frames, 1)
    with Client(served.url) as c:
        with pytest.raises(cerr.UnknownSite) as info:
            c.localize("no-such-site", enc)
        assert info.value.status == 404 and info.value.request_id
        with pytest.raises(cerr.UnknownSite):
            c.site("no-such-site")
        broken = enc.__class__(dict(enc.parts, depth=b"\x89PNG not really"), enc.content_types, enc.meta)
        with pytest.raises(cerr.InvalidFrame) as info:
            c.localize(SITE, broken)
        assert info.value.status == 422 and "depth" in info.value.message
    with Client(f"http://127.0.0.1:{free_port()}", retry=RetryPolicy(max_retries=1, backoff_base_s=0.01)) as c:
        with pytest.raises(cerr.Unreachable):
            c.health()
        assert c.retries == 1


def test_zenoh_client_gives_the_same_answer_as_http(served: Served) -> None:
    with Client(served.url) as c:
        by_http = c.localize(SITE, (served.frames, 2))
    with ZenohClient(served.zenoh, timeout_s=60) as z:
        by_zenoh = z.localize(SITE, (served.frames, 2))
        with pytest.raises(cerr.UnknownSite):
            z.localize("no-such-site", (served.frames, 2))
    assert by_zenoh["status"] == by_http["status"] and by_zenoh["frame_id"] == "2"
    if by_http["T_map_camera"] is not None:
        t_err, r_err = pose_errors(pose_of(by_zenoh), pose_of(by_http))
        assert t_err < 0.01 and r_err < 1.0


def test_zenoh_stream_echoes_frame_ids(served: Served) -> None:
    with ZenohClient(served.zenoh) as z, z.stream(SITE, "robot-7", lost_after_s=60) as s:
        assert s.wait_ready(10)
        # the service keeps few frames per device (newer ones win): pace by answers
        results = list(s.run(((served.frames, i) for i in range(3)), max_in_flight=1))
    assert sorted(r.frame_id for r in results) == ["0", "1", "2"]
    assert all(r.ok and r.result["frame_id"] == r.frame_id for r in results)


def test_overload_503s_are_absorbed_by_retries(served: Served) -> None:
    # 1 worker + 1 queued: of 5 requests sent at once, 3 are turned away with 503 + Retry-After, then retried
    enc = encode_recorded(served.frames, 3).with_frame_id("__sleep__:0.5")
    codes: list[str] = []
    with Client(served.url, retry=RetryPolicy(max_retries=10),
                on_retry=lambda n, e, d: codes.append(e.code)) as c:
        with concurrent.futures.ThreadPoolExecutor(5) as pool:
            results = list(pool.map(lambda _: c.localize(SITE, enc), range(5)))
        assert c.retries >= 1
    assert len(results) == 5 and all(r["frame_id"] == "__sleep__:0.5" for r in results)
    assert set(codes) == {"overloaded"}


def test_load_cli_over_http_and_zenoh(served: Served, tmp_path: Path) -> None:
    out = tmp_path / "http.json"
    rc = cadreg_main(["load", "--url", served.url, "--site", SITE, "--frames", str(served.frames),
                      "--concurrency", "2", "--n", "6", "--json", str(out), "--png", str(tmp_path / "http.png"),
                      "--no-progress"])
    doc = json.loads(out.read_text())
    assert rc == 0 and doc["sent"] == 6 and doc["ok"] == 6 and doc["errors"] == {}
    assert doc["throughput_fps"] > 0 and doc["latency_ms"]["p50"] <= doc["latency_ms"]["p99"] <= doc["latency_ms"]["max"]
    assert doc["accuracy"]["frames_scored"] == 6 and 0.0 <= doc["accuracy"]["success_5cm_5deg"] <= 1.0
    assert (tmp_path / "http.png").stat().st_size > 1000
    # accuracy equals scoring the service's answers one by one
    rf = RecordedFrames.open(served.frames)
    with Client(served.url) as c:
        hits = 0
        for k in range(6):
            i = rf.indices[k % len(rf)]
            T = pose_of(c.localize(SITE, (served.frames, i)))
            if T is not None:
                t_err, r_err = pose_errors(T, rf.pose(i))
                hits += t_err <= 0.05 and r_err <= 5.0
    assert doc["accuracy"]["success_5cm_5deg"] == pytest.approx(hits / 6)
    out = tmp_path / "zenoh.json"
    rc = cadreg_main(["load", "--zenoh", served.zenoh, "--site", SITE, "--frames", str(served.frames),
                      "--rate", "4", "--n", "4", "--json", str(out), "--no-progress",
                      "--server-pid", str(served.pid), "--records", str(tmp_path / "records.jsonl")])
    doc = json.loads(out.read_text())
    assert rc == 0 and doc["sent"] == 4 and doc["ok"] == 4 and doc["mode"] == "open"
    # the service's process tree (uvicorn + worker) holds the site: well over 100 MiB
    assert doc["service_rss_mb"]["start"] > 100 and doc["service_rss_mb"]["end"] > 100
    assert doc["service_cpu_ms_per_request"] > 10 and doc["loadavg_1m"]["start"] >= 0
    records = [json.loads(line) for line in (tmp_path / "records.jsonl").read_text().splitlines()]
    assert [r["scheduled_s"] for r in records] == pytest.approx([0.0, 0.25, 0.5, 0.75])
