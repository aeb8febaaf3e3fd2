"""The HTTP service end to end: a real uvicorn on loopback, real worker processes, the scene0470 site, frames rendered
by `cadreg render`. Every error path is asserted by status and code; the pool survives kills, timeouts and overload."""

from __future__ import annotations

import concurrent.futures
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from service.settings import Settings
from service.worker import SLEEP_HOOK_PREFIX
from test_service_support import (
    LiveServer,
    free_port,
    library_results,
    load_frames,
    multipart,
    pose_error,
    render_frames,
    rss_kib,
)

REPO = Path(__file__).resolve().parents[1]
TOKEN = "s3cret-token"
UPLOAD_LIMIT = 4 * 1024 * 1024
TIMEOUT_S = 8.0
SITE = "scene0470"


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("frames"), n=4))


@pytest.fixture(scope="module")
def server(scene0470_site_dir: Path):
    settings = Settings(
        sites_dir=scene0470_site_dir.parent,
        port=free_port(),
        workers=1,
        queue_depth=1,
        request_timeout_s=TIMEOUT_S,
        max_upload_bytes=UPLOAD_LIMIT,
        admin_token=TOKEN,
        zenoh_enabled=False,
        test_hooks=True,
    )
    live = LiveServer(settings)
    yield live
    live.stop()


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60.0) as c:
        yield c


def _localize(client, frame, **kw) -> httpx.Response:
    files, data = multipart(frame, **kw)
    return client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)


def test_health_ready_and_sites(client, scene0470_site_dir) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["ready"] is True
    version = json.loads((scene0470_site_dir / "site.json").read_text())["version"]
    assert client.get("/v1/sites").json() == {"sites": [{"site_id": SITE, "version": version}]}
    info = client.get(f"/v1/sites/{SITE}").json()
    assert info["site_id"] == SITE and info["version"] == version
    assert info["nodes"] > 7 and info["points"] > 100_000 and "chair" in info["classes"]
    missing = client.get("/v1/sites/nowhere")
    assert missing.status_code == 404 and missing.json()["code"] == "unknown_site"
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    assert "multipart/form-data" in schema["paths"]["/v1/sites/{site_id}/localize"]["post"]["requestBody"]["content"]


def test_localize_matches_the_library(client, frames, scene0470_site_dir) -> None:
    expected = library_results(scene0470_site_dir, frames)
    version = json.loads((scene0470_site_dir / "site.json").read_text())["version"]
    for (frame, T_true), ref in zip(frames, expected):
        r = _localize(client, frame)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["status"] == ref["status"]
        assert body["frame_id"] == frame.frame_id
        assert body["site_id"] == SITE and body["site_version"] == version
        assert re.fullmatch(r"[0-9a-f]{32}", body["request_id"]) and r.headers["x-request-id"] == body["request_id"]
        if ref["T_map_camera"] is None:
            assert body["T_map_camera"] is None
            continue
        dt, dr = pose_error(body["T_map_camera"], ref["T_map_camera"])
        assert dt < 0.01 and dr < 1.0, (dt, dr)  # the same pose as the library (to its own run-to-run spread)
        assert len(body["hypotheses"]) == len(ref["hypotheses"])
    # rendered frames of the real scan: the service finds them
    ok = [b for b in expected if b["status"] in ("ok", "ambiguous")]
    assert len(ok) >= 3


def test_request_id_is_taken_from_the_client(client, frames) -> None:
    files, data = multipart(frames[0][0])
    r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data, headers={"X-Request-ID": "cam-7.frame-42"})
    assert r.status_code == 200 and r.headers["x-request-id"] == "cam-7.frame-42"
    assert r.json()["request_id"] == "cam-7.frame-42"
    # an unsafe id is replaced, not echoed
    bad = client.get("/healthz", headers={"X-Request-ID": "x" * 500})
    assert re.fullmatch(r"[0-9a-f]{32}", bad.headers["x-request-id"])


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


BAD_INPUTS = {
    "corrupt png": dict(parts_override={"color": b"\x89PNG\r\n\x1a\n" + b"\0" * 64}),
    "depth wrong size": dict(parts_override={"depth": _png(np.full((240, 320), 1500, np.uint16))}),
    "depth wrong dtype": dict(parts_override={"depth": _png(np.full((480, 640), 150, np.uint8))}),
    "labels not colour size": dict(parts_override={"labels": _png(np.ones((100, 100), np.uint16))}),
    "all-zero depth": dict(parts_override={"depth": _png(np.zeros((480, 640), np.uint16))}),
    "negative focal length": dict(meta_override={"depth_intrinsics": {"fx": -500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}}),
    "unknown meta field": dict(meta_override={"exposure_ms": 3}),
    "top_k out of range": dict(meta_override={"top_k": 99}),
    "depth range not positive": dict(meta_override={"depth_range_m": 0.0}),
    "missing depth": dict(drop=("depth",)),
    "missing meta": dict(drop=("meta",)),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_422_invalid_frame_and_the_next_request_is_fine(client, frames, case) -> None:
    frame = frames[0][0]
    r = _localize(client, frame, **BAD_INPUTS[case])
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["code"] == "invalid_frame" and body["message"] and body["request_id"] == r.headers["x-request-id"]
    assert set(body) == {"code", "message", "request_id", "detail"}
    good = _localize(client, frame)
    assert good.status_code == 200 and good.json()["status"] in ("ok", "ambiguous")


def test_nan_intrinsics_in_meta_text(client, frames) -> None:
    files, data = multipart(frames[0][0])
    data["meta"] = data["meta"].replace('"fx":577.87', '"fx":NaN').replace('"fx": 577.87', '"fx": NaN')
    assert "NaN" in data["meta"]
    r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
    assert r.status_code == 422 and r.json()["code"] == "invalid_frame" and "fx" in r.json()["message"]


def test_not_multipart_and_unknown_site(client, frames) -> None:
    r = client.post(f"/v1/sites/{SITE}/localize", json={"color": "x"})
    assert r.status_code == 422 and r.json()["code"] == "invalid_frame"
    files, data = multipart(frames[0][0])
    r = client.post("/v1/sites/atlantis/localize", files=files, data=data)
    assert r.status_code == 404 and r.json()["code"] == "unknown_site"


def test_upload_over_the_limit_is_413_before_decoding(client, frames) -> None:
    files, data = multipart(frames[0][0], parts_override={"color": os.urandom(UPLOAD_LIMIT + 1)})
    r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
    assert r.status_code == 413 and r.json()["code"] == "payload_too_large"
    # a lying Content-Length is caught by counting: stream a body without announcing its size
    def chunks():
        for _ in range(UPLOAD_LIMIT // 65536 + 2):
            yield b"\0" * 65536

    r = client.post(f"/v1/sites/{SITE}/localize", content=chunks(),
                    headers={"content-type": "multipart/form-data; boundary=xyz"})
    assert r.status_code == 413 and r.json()["code"] == "payload_too_large"
    assert _localize(client, frames[0][0]).status_code == 200


def test_admin_routes_need_the_bearer_token(client, scene0470_site_dir) -> None:
    for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": f"Basic {TOKEN}"}):
        r = client.post(f"/v1/sites/{SITE}/reload", headers=headers)
        assert r.status_code == 401 and r.json()["code"] == "unauthorized"
        r = client.put(f"/v1/sites/{SITE}", content=b"not an archive", headers=headers)
        assert r.status_code == 401 and r.json()["code"] == "unauthorized"
    auth = {"Authorization": f"Bearer {TOKEN}"}
    version = json.loads((scene0470_site_dir / "site.json").read_text())["version"]
    r = client.post(f"/v1/sites/{SITE}/reload", headers=auth)
    assert r.status_code == 200 and r.json() == {"site_id": SITE, "version": version}
    r = client.put(f"/v1/sites/{SITE}", content=b"not an archive", headers=auth)
    assert r.status_code == 422 and r.json()["code"] == "invalid_file"
    r = client.post("/v1/sites/atlantis/reload", headers=auth)
    assert r.status_code == 404 and r.json()["code"] == "unknown_site"


def test_metrics(client) -> None:
    text = client.get("/metrics").text
    assert 'cadreg_requests_total{code="ok",route="/v1/sites/{site_id}/localize",transport="http"}' in text
    assert 'code="invalid_frame"' in text and 'code="payload_too_large"' in text
    assert "cadreg_request_latency_seconds_bucket" in text
    assert 'cadreg_stage_latency_seconds_count{stage="worker"}' in text
    assert "cadreg_queue_depth 0.0" in text and "cadreg_workers_alive 1.0" in text
    assert 'cadreg_site_info{site_id="scene0470"' in text


def test_schemathesis_finds_no_server_error(server, tmp_path) -> None:
    # Pin the site id so that fuzzed multipart bodies reach the localize route instead of stopping at 404.
    (tmp_path / "schemathesis.toml").write_text('[parameters]\n"path.site_id" = "scene0470"\n')
    cmd = [sys.executable, "-m", "schemathesis.cli", "run", f"{server.url}/openapi.json",
           "--checks", "not_a_server_error", "--max-examples", "20", "--workers", "1",
           "--phases", "examples,fuzzing", "--suppress-health-check", "all", "--warnings", "off"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path,
                         env={**os.environ, "NO_COLOR": "1"})
    out = run.stdout + run.stderr
    print(out[-3000:])
    assert run.returncode == 0, out[-3000:]
    m = re.search(r"(\d+) generated, (\d+) passed", out)
    assert m and int(m.group(1)) >= 20 and m.group(1) == m.group(2), out[-3000:]
    # and the fuzzing did reach the localize route with the real site id
    metrics = httpx.get(server.url + "/metrics").text
    assert re.search(r'cadreg_requests_total\{code="invalid_frame",route="/v1/sites/\{site_id\}/localize"', metrics)


def test_dockerfile_healthcheck_command_works(server) -> None:
    text = (REPO / "Dockerfile").read_text().replace("\\\n", " ")  # join continued lines
    m = re.search(r'HEALTHCHECK[^\n]*CMD \["python", "-c", "(.+)"\]', text)
    assert m, "HEALTHCHECK must run python -c"
    code = m.group(1).encode().decode("unicode_escape").replace("8080", str(server.settings.port))
    assert subprocess.run([sys.executable, "-c", code], timeout=30).returncode == 0
    code_down = m.group(1).encode().decode("unicode_escape").replace("8080", str(free_port()))
    assert subprocess.run([sys.executable, "-c", code_down], timeout=30, capture_output=True).returncode != 0


# --- the pool under stress (these run last: they kill and replace workers) -------------------------------------------


def _busy_worker_pid(client, timeout_s: float = 10.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        busy = [w for w in client.get("/debug/workers").json() if w["state"] == "busy"]
        if busy:
            return busy[0]["pid"]
        time.sleep(0.02)
    raise TimeoutError("no worker picked the request up")


def test_killed_worker_costs_one_request_then_the_pool_is_whole(server, client, frames) -> None:
    frame = frames[0][0]
    with concurrent.futures.ThreadPoolExecutor(1) as ex:
        t0 = time.monotonic()
        pending = ex.submit(_localize, client, frame, frame_id=f"{SLEEP_HOOK_PREFIX}30")
        pid = _busy_worker_pid(client)
        os.kill(pid, signal.SIGKILL)
        r = pending.result(timeout=TIMEOUT_S + 5)
    assert r.status_code == 503 and r.json()["code"] == "worker_crashed", r.text
    assert int(r.headers["retry-after"]) >= 1
    assert time.monotonic() - t0 < TIMEOUT_S
    server.wait_ready()
    workers = client.get("/debug/workers").json()
    assert len(workers) == 1 and workers[0]["pid"] != pid
    for i in range(20):
        r = _localize(client, frames[i % len(frames)][0])
        assert r.status_code == 200, r.text
    assert 'cadreg_worker_restarts_total{reason="crashed"} 1.0' in client.get("/metrics").text


def test_stuck_worker_times_out_with_504_and_is_replaced(server, client, frames) -> None:
    t0 = time.monotonic()
    r = _localize(client, frames[0][0], frame_id=f"{SLEEP_HOOK_PREFIX}60")
    elapsed = time.monotonic() - t0
    assert r.status_code == 504 and r.json()["code"] == "timeout", r.text
    assert TIMEOUT_S - 0.5 < elapsed < TIMEOUT_S + 3
    server.wait_ready()
    assert _localize(client, frames[1][0]).status_code == 200
    assert 'cadreg_worker_restarts_total{reason="timeout"} 1.0' in client.get("/metrics").text


def test_overload_answers_503_at_once_and_memory_stays_flat(server, client, frames) -> None:
    capacity = server.settings.workers + server.settings.queue_depth
    frame = frames[2][0]
    files, data = multipart(frame, frame_id=f"{SLEEP_HOOK_PREFIX}2.0")

    def one(_):
        t0 = time.monotonic()
        r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
        return r, time.monotonic() - t0

    rss_before = None
    for round_ in range(3):
        with concurrent.futures.ThreadPoolExecutor(2 * capacity) as ex:
            answers = list(ex.map(one, range(2 * capacity)))
        codes = sorted(r.status_code for r, _ in answers)
        assert codes.count(503) >= capacity - 1 and codes.count(200) >= 1, codes
        assert set(codes) <= {200, 503}
        for r, elapsed in answers:
            assert elapsed < TIMEOUT_S  # nobody waits past the deadline
            if r.status_code == 503:
                assert r.json()["code"] == "overloaded" and int(r.headers["retry-after"]) >= 1
                assert elapsed < 1.5  # refused at once, not after waiting for a worker (busy for 2 s)
        workers = client.get("/debug/workers").json()
        rss = rss_kib(os.getpid()) + sum(rss_kib(w["pid"]) for w in workers if w["pid"])
        if round_ == 0:
            rss_before = rss
    assert rss - rss_before < 50 * 1024, (rss_before, rss)  # KiB: flat within 50 MiB over the rounds
