"""What a hostile client found (issue 14), each reproduced against a real uvicorn on loopback with real workers:
an unloadable upload, CR/LF in a site id, an over-long site id, archive bombs and stray files, a reload while a
worker hangs."""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
import signal
import tarfile
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from service.settings import Settings
from test_service_support import LiveServer, free_port, load_frames, multipart, render_frames

SITE = "scene0470"
TOKEN = "hardening-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
TIMEOUT_S = 8.0
BUNDLE_LIMIT = 32 * 1024 * 1024  # archive and unpacked files; the scene0470 bundle is about 11 MB
BOMB_BYTES = 48 * 1024 * 1024


def _version(bundle: Path) -> str:
    return json.loads((bundle / "site.json").read_text())["version"]


@pytest.fixture(scope="module")
def bundles(scene0470_site_dir: Path, tmp_path_factory) -> dict[str, Path]:
    """The served copy, a second version (one map point recoloured), and a valid bundle with an empty map."""
    from cadreg.pointset import PointSet
    from cadreg.site.bundle import Site

    root = tmp_path_factory.mktemp("hardening")
    served = root / "sites" / SITE
    shutil.copytree(scene0470_site_dir, served)
    site = Site.load(scene0470_site_dir)
    site.map.colors = site.map.colors.copy()
    site.map.colors[0] = 255 - site.map.colors[0]
    site.save(root / "v2" / SITE)
    empty = Site.load(scene0470_site_dir)
    empty.map, empty.raw = PointSet.empty(), PointSet.empty()
    empty.save(root / "empty" / SITE)
    return {"sites": served.parent, "v1": scene0470_site_dir, "v2": root / "v2" / SITE, "empty": root / "empty" / SITE}


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("hframes"), n=4))


def _settings(sites: Path, workers: int = 2) -> Settings:
    return Settings(sites_dir=sites, port=free_port(), workers=workers, queue_depth=4, request_timeout_s=TIMEOUT_S,
                    max_bundle_bytes=BUNDLE_LIMIT, admin_token=TOKEN, zenoh_enabled=False, test_hooks=True)


@pytest.fixture(scope="module")
def server(bundles):
    live = LiveServer(_settings(bundles["sites"]))
    yield live
    live.stop()


@pytest.fixture()
def client(server):
    server.wait_ready()
    with httpx.Client(base_url=server.url, timeout=60.0) as c:
        yield c


def _tar(files: dict[str, bytes], top: str | None = SITE) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in files.items():
            info = tarfile.TarInfo(f"{top}/{name}" if top else name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _files(bundle: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(bundle.iterdir())}


def _assert_staging_clean(sites: Path) -> None:
    incoming = sites / ".incoming"
    assert not incoming.exists() or list(incoming.iterdir()) == [], list(incoming.iterdir())


# --- 1. an upload the workers cannot load ---------------------------------------------------------------------------

def test_an_unloadable_upload_is_refused_before_it_replaces_the_good_bundle(server, client, bundles, frames) -> None:
    v1 = _version(bundles["v1"])
    r = client.put(f"/v1/sites/{SITE}", content=_tar(_files(bundles["empty"])), headers=AUTH)
    assert r.status_code == 422 and r.json()["code"] == "invalid_file", r.text
    assert "cannot be loaded" in r.json()["message"]
    assert str(bundles["sites"]) not in r.text
    assert client.get(f"/v1/sites/{SITE}").json()["version"] == v1
    assert _version(bundles["sites"] / SITE) == v1  # the good bundle on disk was never touched
    _assert_staging_clean(bundles["sites"])
    # a worker restarted now loads the good bundle again
    pid = client.get("/debug/workers").json()[0]["pid"]
    os.kill(pid, signal.SIGKILL)
    server.wait_ready()
    files, data = multipart(frames[0][0])
    r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
    assert r.status_code == 200 and r.json()["site_version"] == v1, r.text
    # and so does a service started afresh on the same directory
    again = LiveServer(_settings(bundles["sites"], workers=1), ready_timeout_s=120.0)
    try:
        assert httpx.get(again.url + "/readyz").json()["ready"] is True
    finally:
        again.stop()


# --- 2. CR/LF in a site id ------------------------------------------------------------------------------------------

def test_crlf_in_a_site_id_cannot_forge_a_log_line(client, frames, caplog) -> None:
    caplog.set_level(logging.INFO, logger="cadreg")
    forged = "x%0d%0arequest_id=forged GET status=200 code=ok"  # no "/": the route matches, site_id is set
    r = client.get(f"/v1/sites/{forged}")
    assert r.status_code in (404, 422), r.text
    files, data = multipart(frames[0][0])
    r = client.post(f"/v1/sites/{forged}/localize", files=files, data=data)
    assert r.status_code in (404, 422), r.text
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and sum("forged" in rec.getMessage() for rec in caplog.records) < 2:
        time.sleep(0.05)
    carrying = [rec.getMessage() for rec in caplog.records if "forged" in rec.getMessage()]
    assert len(carrying) >= 2, carrying
    for message in carrying:
        assert "\n" not in message and "\r" not in message, message
        assert message.startswith("{"), message
        doc = json.loads(message)
        assert doc["event"] == "http_request" and "\r\n" in doc["site"]  # kept, escaped


# --- 3. site ids checked at the entry -------------------------------------------------------------------------------

def test_malformed_site_ids_answer_422_and_well_formed_unknown_ones_404(client, frames) -> None:
    long_id = "a" * 5000
    files, data = multipart(frames[0][0])
    answers = [
        client.post(f"/v1/sites/{long_id}/reload", headers=AUTH),
        client.put(f"/v1/sites/{long_id}", content=b"x" * 2048, headers=AUTH),
        client.get(f"/v1/sites/{long_id}"),
        client.post(f"/v1/sites/{long_id}/localize", files=files, data=data),
        client.post("/v1/sites/.hidden/reload", headers=AUTH),
        client.get("/v1/sites/-dash"),
    ]
    for r in answers:
        assert r.status_code == 422 and r.json()["code"] == "invalid_input", (r.request.url.path[:60], r.text[:300])
        assert "A-Za-z0-9" in r.json()["message"]
    r = client.post("/v1/sites/nosuch/reload", headers=AUTH)
    assert r.status_code == 404 and r.json()["code"] == "unknown_site", r.text
    r = client.get("/v1/sites/nosuch")
    assert r.status_code == 404 and r.json()["code"] == "unknown_site", r.text


# --- 4. archive bombs, stray files, broken archives ------------------------------------------------------------------

def test_files_site_json_does_not_reference_are_not_installed(client, bundles) -> None:
    files = {**_files(bundles["v1"]), "junk.bin": bytes(BOMB_BYTES), "extra/inner.txt": b"hello"}
    r = client.put(f"/v1/sites/{SITE}", content=_zip(files), headers=AUTH)
    assert r.status_code == 200 and r.json()["version"] == _version(bundles["v1"]), r.text
    installed = sorted(p.name for p in (bundles["sites"] / SITE).iterdir())
    assert installed == ["graph.json", "map.ply", "raw.ply", "site.json"], installed
    _assert_staging_clean(bundles["sites"])


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_an_archive_bomb_is_refused_while_it_unpacks(client, bundles, kind) -> None:
    files = {**_files(bundles["v1"]), "map.ply": bytes(BOMB_BYTES)}
    archive = _zip(files) if kind == "zip" else _tar(files)
    assert len(archive) < BUNDLE_LIMIT // 4
    r = client.put(f"/v1/sites/{SITE}", content=archive, headers=AUTH)
    assert r.status_code == 413 and r.json()["code"] == "payload_too_large", r.text
    assert str(BUNDLE_LIMIT) in r.json()["message"]
    assert client.get(f"/v1/sites/{SITE}").json()["version"] == _version(bundles["v1"])
    _assert_staging_clean(bundles["sites"])


def test_broken_archives_answer_422_without_server_paths(client, bundles) -> None:
    good = _tar(_files(bundles["v1"]))
    escaping = _zip({"../evil.txt": b"x", **_files(bundles["v1"])})
    for archive in (good[: len(good) // 2], escaping, b"not an archive at all" * 100):
        r = client.put(f"/v1/sites/{SITE}", content=archive, headers=AUTH)
        assert r.status_code == 422 and r.json()["code"] in ("invalid_file", "bundle_integrity"), r.text
        assert str(bundles["sites"]) not in r.text and "/tmp" not in r.text, r.text
    assert not (bundles["sites"] / "evil.txt").exists()
    _assert_staging_clean(bundles["sites"])


# --- 5. a reload while a worker hangs --------------------------------------------------------------------------------

def test_a_reload_while_a_worker_hangs_answers_within_the_request_timeout(server, client, bundles, frames) -> None:
    v2 = _version(bundles["v2"])
    hung = client.get("/debug/workers").json()[0]["pid"]
    os.kill(hung, signal.SIGSTOP)  # alive, holding its pipe, answering nothing
    try:
        for p in bundles["v2"].iterdir():
            shutil.copy2(p, bundles["sites"] / SITE / p.name)
        t0 = time.monotonic()
        try:
            r = client.post(f"/v1/sites/{SITE}/reload", headers=AUTH, timeout=TIMEOUT_S + 20)
        except httpx.TimeoutException:
            pytest.fail("the reload waited on the hung worker")
        elapsed = time.monotonic() - t0
        assert r.status_code == 200 and r.json()["version"] == v2, r.text
        assert elapsed < TIMEOUT_S + 3.0, elapsed
        # the hung worker was killed and replaced; /readyz does not count it
        pids = [w["pid"] for w in client.get("/debug/workers").json()]
        assert hung not in pids, pids
        status = Path(f"/proc/{hung}/status")
        assert not status.exists() or "zombie" in status.read_text(), "the hung worker is still alive"
        server.wait_ready()
        files, data = multipart(frames[0][0])
        for _ in range(4):  # whichever worker answers, the replacement included, serves the new version
            r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
            assert r.status_code == 200 and r.json()["site_version"] == v2, r.text
    finally:
        try:
            os.kill(hung, signal.SIGKILL)
        except ProcessLookupError:
            pass
