"""Settings (environment prefix CADREG_, bad values fail at start), `cadreg serve` as a user runs it, the Dockerfile."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from cadreg.config import LocalizeConfig
from cadreg.errors import ConfigError
from cadreg.site.demo import SITE_ID
from service.settings import Settings, settings_from
from test_service_support import free_port, free_ports, load_frames, multipart, render_frames

REPO = Path(__file__).resolve().parents[1]


def test_defaults_are_loopback_and_scouting_off(tmp_path) -> None:
    s = Settings(demo_cache_dir=tmp_path)
    assert s.host == "127.0.0.1" and s.port == 8080 and s.sites_dir is None and s.demo_mode
    assert s.zenoh_listen == ["tcp/127.0.0.1:7447"] and s.zenoh_connect == []
    assert s.zenoh_multicast_scouting is False and s.zenoh_gossip_scouting is False
    assert s.sites_root == tmp_path and s.admin_token is None
    assert s.localize_config == LocalizeConfig()  # no CADREG_LOCALIZE_CONFIG: the code's defaults


def test_environment_prefix(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("CADREG_PORT", "9123")
    monkeypatch.setenv("CADREG_WORKERS", "3")
    monkeypatch.setenv("CADREG_ZENOH_LISTEN", '["tcp/127.0.0.1:7001", "udp/127.0.0.1:7002"]')
    monkeypatch.setenv("CADREG_ADMIN_TOKEN", "zz-secret-42")
    monkeypatch.setenv("CADREG_SITES_DIR", str(tmp_path))
    s = settings_from(port=None, workers=None)
    assert s.port == 9123 and s.workers == 3 and s.sites_dir == tmp_path
    assert s.zenoh_listen == ["tcp/127.0.0.1:7001", "udp/127.0.0.1:7002"]
    assert s.admin_token.get_secret_value() == "zz-secret-42" and "zz-secret-42" not in repr(s)
    assert settings_from(port=8181).port == 8181  # flags beat the environment


@pytest.mark.parametrize(
    "overrides, needle",
    [
        ({"port": 70000}, "port"),
        ({"workers": 0}, "workers"),
        ({"request_timeout_s": 0}, "request_timeout_s"),
        ({"zenoh_listen": ["localhost:7447"]}, "zenoh endpoint"),
        ({"zenoh_mode": "client"}, "zenoh_connect"),
        ({"zenoh_mode": "satellite"}, "zenoh_mode"),
        ({"sites_dir": "/nonexistent/sites"}, "not a directory"),
        ({"no_such_setting": 1}, "no_such_setting"),
    ],
)
def test_bad_settings_fail_with_a_clear_message(overrides, needle) -> None:
    with pytest.raises(ConfigError) as info:
        settings_from(**overrides)
    assert needle in info.value.message and info.value.message.startswith("bad service settings")


def test_serve_refuses_a_bad_sites_dir(tmp_path) -> None:
    run = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "serve", "--sites", str(tmp_path / "nope")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "error [invalid_config]" in run.stderr and "not a directory" in run.stderr


def test_serve_refuses_a_tampered_bundle(scene0470_site_dir, tmp_path) -> None:
    bundle = tmp_path / "sites" / "scene0470"
    shutil.copytree(scene0470_site_dir, bundle)
    with open(bundle / "raw.ply", "r+b") as f:
        f.seek(-10, os.SEEK_END)
        f.write(b"0123456789")
    run = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "serve", "--sites", str(bundle.parent),
                          "--port", str(free_port()), "--no-zenoh"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "error [bundle_integrity]" in run.stderr and "raw.ply" in run.stderr


def test_serve_refuses_a_zenoh_endpoint_in_use(scene0470_site_dir) -> None:
    import zenoh

    from service.zenoh_server import zenoh_config

    port, zport = free_ports(2)
    holder = zenoh.open(zenoh_config(Settings(zenoh_listen=[f"tcp/127.0.0.1:{zport}"])))
    try:
        run = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "serve", "--sites",
                              str(scene0470_site_dir.parent), "--port", str(port), "--workers", "1",
                              "--zenoh-listen", f"tcp/127.0.0.1:{zport}"], capture_output=True, text=True, timeout=120)
    finally:
        holder.close()
    assert run.returncode == 2 and "error [invalid_config]: zenoh could not open" in run.stderr, run.stderr[-2000:]


def _wait_ready(url: str, proc: subprocess.Popen, timeout_s: float = 240.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read()
        try:
            if httpx.get(url + "/readyz", timeout=2.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise TimeoutError("cadreg serve did not become ready")


def test_cadreg_serve_end_to_end(scene0470_site_dir, tmp_path) -> None:
    """The command a user runs: a subprocess, real ports, one log line per request, a clean Ctrl-C; its
    --localize-config decides what a request leaves open (top_k)."""
    frames = load_frames(render_frames(scene0470_site_dir, tmp_path / "frames", n=1))
    port, zport = free_ports(2)
    env = {**os.environ, "CADREG_QUEUE_DEPTH": "2"}
    config_top_k = LocalizeConfig().match.top_k - 2
    (tmp_path / "localize.json").write_text(json.dumps({"match": {"top_k": config_top_k}}))
    proc = subprocess.Popen(
        [shutil.which("cadreg") or "cadreg", "serve", "--sites", str(scene0470_site_dir.parent), "--port", str(port),
         "--workers", "1", "--zenoh-listen", f"tcp/127.0.0.1:{zport}",
         "--localize-config", str(tmp_path / "localize.json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    try:
        url = f"http://127.0.0.1:{port}"
        _wait_ready(url, proc)
        files, data = multipart(frames[0][0])
        r = httpx.post(url + "/v1/sites/scene0470/localize", files=files, data=data,
                       headers={"X-Request-ID": "serve-test-1"}, timeout=60)
        assert r.status_code == 200 and r.json()["status"] in ("ok", "ambiguous")
        meta = json.loads(data["meta"])
        del meta["top_k"]
        r = httpx.post(url + "/v1/sites/scene0470/localize", files=files, data={"meta": json.dumps(meta)}, timeout=60)
        assert r.status_code == 200 and len(r.json()["hypotheses"]) == config_top_k
        r = httpx.get(url + "/v1/sites/elsewhere", headers={"X-Request-ID": "serve-test-2"})
        assert r.status_code == 404
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err[-2000:]
    log = out + err
    events = [json.loads(line[line.index("{"):]) for line in log.splitlines() if '{"event": "http_request"' in line]
    by_id = {e["request_id"]: e for e in events}
    assert {k: by_id["serve-test-1"][k] for k in ("method", "path", "site", "status", "code")} == {
        "method": "POST", "path": "/v1/sites/scene0470/localize", "site": "scene0470", "status": 200, "code": "ok"}
    assert by_id["serve-test-1"]["ms"] > 0
    assert {k: by_id["serve-test-2"][k] for k in ("method", "site", "status", "code")} == {
        "method": "GET", "site": "elsewhere", "status": 404, "code": "unknown_site"}
    started = [json.loads(line[line.index("{"):]) for line in log.splitlines() if '{"event": "zenoh_started"' in line]
    assert started and started[0]["mode"] == "peer" and started[0]["listen"][0].startswith("tcp/127.0.0.1:")
    assert f"localize config: {{'match': {{'top_k': {config_top_k}}}}}" in log


def test_cadreg_serve_with_no_arguments_serves_the_demo_site(tmp_path) -> None:
    """`cadreg serve` alone: builds the demo site into the cache dir and serves it on 127.0.0.1:8080."""
    try:
        with httpx.Client() as probe:
            probe.get("http://127.0.0.1:8080/healthz", timeout=0.5)
        pytest.fail("port 8080 is taken on this machine: cannot test the default port")
    except httpx.TransportError:
        pass
    env = {**os.environ, "CADREG_DEMO_CACHE_DIR": str(tmp_path / "cache"),
           "CADREG_ZENOH_LISTEN": f'["tcp/127.0.0.1:{free_port()}"]', "CADREG_WORKERS": "1"}
    proc = subprocess.Popen([shutil.which("cadreg") or "cadreg", "serve"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        _wait_ready("http://127.0.0.1:8080", proc)
        sites = httpx.get("http://127.0.0.1:8080/v1/sites").json()["sites"]
        assert len(sites) == 1
        bundle = tmp_path / "cache" / SITE_ID
        assert sites[0]["site_id"] == SITE_ID and sites[0]["version"] == json.loads((bundle / "site.json").read_text())["version"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    assert proc.returncode == 0


def test_dockerfile_follows_the_house_rules() -> None:
    text = (REPO / "Dockerfile").read_text()
    lines = [line.strip() for line in text.splitlines()]
    assert lines[[i for i, l in enumerate(lines) if l.startswith("FROM")][0]] == "FROM python:3.11-slim"
    for lib in ("libusb-1.0-0", "libgl1", "libegl1", "libx11-6"):
        assert lib in text
    # dependencies before code: pyproject is copied and installed before any source directory
    assert text.index("COPY pyproject.toml") < text.index("pip install -r") < text.index("COPY cadreg")
    assert re.search(r"^USER (?!root)\w+", text, re.M)
    assert 'VOLUME ["/sites"]' in text and "CADREG_SITES_DIR=/sites" in text
    assert re.search(r"^EXPOSE 8080", text, re.M)
    assert "HEALTHCHECK" in text and "/healthz" in text and "curl" not in text
    assert 'CMD ["cadreg", "serve", "--host", "0.0.0.0", "--sites", "/sites"]' in text
    # the CMD's flags are ones `cadreg serve` accepts
    run = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "serve", "--help"], capture_output=True, text=True)
    assert run.returncode == 0 and "--host" in run.stdout and "--sites" in run.stdout
    ignore = (REPO / ".dockerignore").read_text().split()
    assert ".git" in ignore and "tests" in ignore


def test_frame_pixel_cap_and_http_limits(monkeypatch, tmp_path) -> None:
    s = Settings(demo_cache_dir=tmp_path)
    assert s.max_frame_pixels == 4096 * 3072
    assert s.http_header_timeout_s > 0 and s.http_keep_alive_s > 0 and s.http_max_header_bytes == 16 * 1024
    monkeypatch.setenv("CADREG_MAX_FRAME_PIXELS", str(640 * 480))
    monkeypatch.setenv("CADREG_HTTP_HEADER_TIMEOUT_S", "2.5")
    s = settings_from()
    assert s.max_frame_pixels == 640 * 480 and s.http_header_timeout_s == 2.5
    from service.codec import MAX_IMAGE_PIXELS
    from service.http_app import uvicorn_options

    options = uvicorn_options(s)
    assert options["http"].header_timeout_s == 2.5 and options["timeout_keep_alive"] == s.http_keep_alive_s
    assert options["h11_max_incomplete_event_size"] == s.http_max_header_bytes
    for name, value in (("max_frame_pixels", 0), ("max_frame_pixels", MAX_IMAGE_PIXELS + 1),
                        ("http_header_timeout_s", 0), ("http_max_header_bytes", 10)):
        with pytest.raises(ConfigError, match=name):
            settings_from(**{name: value})
