"""Live site replacement: a new bundle version uploaded (PUT, tar archive) during a run of 100 localize requests;
none fails, and every request admitted after the swap is answered by the new version. Then a reload from the sites
directory (POST .../reload), and a tampered upload that is refused while the served version stays."""

from __future__ import annotations

import concurrent.futures
import io
import json
import shutil
import tarfile
import threading
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from service.settings import Settings
from test_service_support import LiveServer, free_port, load_frames, multipart, render_frames

SITE = "scene0470"
TOKEN = "reload-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _version(bundle: Path) -> str:
    return json.loads((bundle / "site.json").read_text())["version"]


@pytest.fixture(scope="module")
def bundles(scene0470_site_dir: Path, tmp_path_factory) -> dict[str, Path]:
    """The served copy (sites/scene0470) and a second version of the same site (one map point recoloured)."""
    from cadreg.site.bundle import Site

    root = tmp_path_factory.mktemp("reload")
    served = root / "sites" / SITE
    shutil.copytree(scene0470_site_dir, served)
    site = Site.load(scene0470_site_dir)
    site.map.colors = site.map.colors.copy()
    site.map.colors[0] = 255 - site.map.colors[0]
    second = root / "v2" / SITE
    site.save(second)
    assert _version(second) != _version(served)
    return {"sites": served.parent, "v1": scene0470_site_dir, "v2": second}


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("rframes"), n=4))


@pytest.fixture(scope="module")
def server(bundles):
    settings = Settings(sites_dir=bundles["sites"], port=free_port(), workers=2, queue_depth=4,
                        request_timeout_s=60, admin_token=TOKEN, zenoh_enabled=False)
    live = LiveServer(settings)
    yield live
    live.stop()


def _tar(bundle: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        tf.add(bundle, arcname=bundle.name)  # files inside one top-level folder
    return buf.getvalue()


def _zip(bundle: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(bundle.iterdir()):
            zf.write(p, p.name)  # files at the archive's top
    return buf.getvalue()


def test_swap_during_100_requests(server, bundles, frames) -> None:
    v1, v2 = _version(bundles["v1"]), _version(bundles["v2"])
    archive = _tar(bundles["v2"])
    bodies = [multipart(frames[i % len(frames)][0]) for i in range(4)]
    swap: dict[str, float] = {}
    done_count = [0]
    lock = threading.Lock()

    with httpx.Client(base_url=server.url, timeout=120.0) as client:
        def one(i: int):
            files, data = bodies[i % 4]
            t0 = time.monotonic()
            r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
            with lock:
                done_count[0] += 1
            return i, t0, time.monotonic(), r

        def upload():
            while done_count[0] < 25:
                time.sleep(0.01)
            swap["start"] = time.monotonic()
            r = client.put(f"/v1/sites/{SITE}", content=archive, headers=AUTH)
            swap["end"] = time.monotonic()
            return r

        with concurrent.futures.ThreadPoolExecutor(4) as ex:
            uploader = ex.submit(upload)
            answers = list(ex.map(one, range(100)))
            put = uploader.result()
        assert put.status_code == 200, put.text
        assert put.json() == {"site_id": SITE, "version": v2}
        assert client.get(f"/v1/sites/{SITE}").json()["version"] == v2

    assert all(r.status_code == 200 for *_, r in answers), [r.text for *_, r in answers if r.status_code != 200]
    versions = [(t0, t1, r.json()["site_version"]) for _, t0, t1, r in answers]
    assert {v for *_, v in versions} <= {v1, v2}
    assert all(v == v1 for t0, t1, v in versions if t1 < swap["start"])
    after = [v for t0, t1, v in versions if t0 > swap["end"]]
    assert after and all(v == v2 for v in after), after
    assert sum(v == v1 for *_, v in versions) >= 25
    # the new files are the served directory now
    assert _version(bundles["sites"] / SITE) == v2


def test_reload_from_the_sites_directory(server, bundles, frames) -> None:
    v1 = _version(bundles["v1"])
    served = bundles["sites"] / SITE
    for p in bundles["v1"].iterdir():
        shutil.copy2(p, served / p.name)
    with httpx.Client(base_url=server.url, timeout=120.0) as client:
        r = client.post(f"/v1/sites/{SITE}/reload", headers=AUTH)
        assert r.status_code == 200 and r.json()["version"] == v1
        files, data = multipart(frames[0][0])
        r = client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
        assert r.status_code == 200 and r.json()["site_version"] == v1


def test_tampered_upload_is_refused_and_the_served_version_stays(server, bundles, tmp_path) -> None:
    bad = tmp_path / SITE
    shutil.copytree(bundles["v2"], bad)
    graph = json.loads((bad / "graph.json").read_text())
    (bad / "graph.json").write_text(json.dumps(graph) + " ")
    v1 = _version(bundles["v1"])
    with httpx.Client(base_url=server.url, timeout=120.0) as client:
        r = client.put(f"/v1/sites/{SITE}", content=_zip(bad), headers=AUTH)
        assert r.status_code == 422 and r.json()["code"] == "bundle_integrity", r.text
        assert "graph.json" in r.json()["message"]
        assert client.get(f"/v1/sites/{SITE}").json()["version"] == v1
        # a zip with the files at the top level is accepted as well
        r = client.put(f"/v1/sites/{SITE}", content=_zip(bundles["v2"]), headers=AUTH)
        assert r.status_code == 200 and r.json()["version"] == _version(bundles["v2"])
    leftovers = [p for p in (bundles["sites"] / ".incoming").iterdir()]
    assert leftovers == [], leftovers


def test_upload_of_a_new_site_id_adds_the_site(server, scene0470_site_dir, frames, tmp_path) -> None:
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    site.site_id = "annex"
    site.save(tmp_path / "annex")
    with httpx.Client(base_url=server.url, timeout=120.0) as client:
        r = client.put("/v1/sites/annex", content=_tar(tmp_path / "annex"), headers=AUTH)
        assert r.status_code == 200 and r.json()["site_id"] == "annex", r.text
        assert {s["site_id"] for s in client.get("/v1/sites").json()["sites"]} == {SITE, "annex"}
        files, data = multipart(frames[0][0])
        r = client.post("/v1/sites/annex/localize", files=files, data=data)
        assert r.status_code == 200 and r.json()["site_id"] == "annex" and r.json()["status"] in ("ok", "ambiguous")
        # a bundle whose id is not the route's is refused
        r = client.put("/v1/sites/other", content=_tar(tmp_path / "annex"), headers=AUTH)
        assert r.status_code == 422 and r.json()["code"] == "invalid_file" and "annex" in r.json()["message"]
        assert client.get("/readyz").json()["ready"] is True
    assert (server.settings.sites_dir / "annex" / "site.json").is_file()
    assert not (server.settings.sites_dir / "other").exists()
    assert list((server.settings.sites_dir / ".incoming").iterdir()) == []  # staging cleaned after a refusal too


def test_an_upload_is_hash_checked_once_and_never_loaded_by_the_parent(server, bundles, monkeypatch) -> None:
    """The parent verifies the staged bundle's manifest and hashes once; only the workers parse its clouds (the
    uvicorn under test runs in this process, its workers do not, so the patches below touch the parent only)."""
    from cadreg.site.bundle import Site

    checked: list[str] = []
    check_files = Site.check_files

    def counted(site_dir):
        checked.append(str(site_dir))
        return check_files(site_dir)

    def no_load(*args, **kwargs):
        raise AssertionError("the parent parsed an uploaded bundle")

    monkeypatch.setattr(Site, "check_files", staticmethod(counted))
    monkeypatch.setattr(Site, "load", classmethod(no_load))
    v1 = _version(bundles["v1"])
    with httpx.Client(base_url=server.url, timeout=120.0) as client:
        r = client.put(f"/v1/sites/{SITE}", content=_tar(bundles["v1"]), headers=AUTH)
        assert r.status_code == 200 and r.json()["version"] == v1, r.text
        assert client.get(f"/v1/sites/{SITE}").json()["version"] == v1
    assert len(checked) == 1 and "/.incoming/" in checked[0], checked
    # the entry points at the installed directory, not at the staging one it was checked in
    assert server.service.registry.get(SITE).path == str((bundles["sites"] / SITE).resolve())
