"""The algorithm's configuration in the service, and "validate once":
- CADREG_LOCALIZE_CONFIG (a TOML or JSON file) is validated at start into a LocalizeConfig that every worker uses,
  replacements included; a bad file stops the start with one line naming the field (Settings and `cadreg serve`);
- the worker receives the FrameMeta validated in the parent and does not validate it again;
- the parent learns a bundle from its checked manifest and never parses its point clouds."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from cadreg.config import LocalizeConfig
from cadreg.errors import BundleIntegrityError, ConfigError
from service import codec
from service.pool import WorkerPool
from service.registry import SiteRegistry, inspect_bundle
from service.schemas import FrameMeta
from service.settings import Settings, settings_from
from service.worker import _localize, _Sites
from test_service_support import LiveServer, free_port, load_frames, render_frames

SITE = "scene0470"
CONFIG_TOP_K = 2  # differs from the code's default, checked below, so that only the file can explain it


@pytest.fixture(scope="module")
def frame(scene0470_site_dir: Path, tmp_path_factory):
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("cframes"), n=1))[0][0]


def _without_top_k(meta: FrameMeta) -> dict:
    """The meta document of a client that leaves top_k to the service."""
    doc = meta.model_dump(mode="json")
    del doc["top_k"]
    return doc


def _post(client: httpx.Client, parts: dict[str, bytes], meta_doc: dict) -> httpx.Response:
    files = {name: (f"{name}.png", data, "image/png") for name, data in parts.items()}
    return client.post(f"/v1/sites/{SITE}/localize", files=files, data={"meta": json.dumps(meta_doc)})


# --- the config file reaches the workers ---------------------------------------------------------------------------


def test_localize_config_file_is_used_by_every_worker(scene0470_site_dir, frame, tmp_path, monkeypatch) -> None:
    assert LocalizeConfig().match.top_k != CONFIG_TOP_K
    path = tmp_path / "localize.toml"
    path.write_text(f"# fewer hypotheses in each answer\n[match]\ntop_k = {CONFIG_TOP_K}\n")
    monkeypatch.setenv("CADREG_LOCALIZE_CONFIG", str(path))
    settings = settings_from(sites_dir=scene0470_site_dir.parent, port=free_port(), workers=1, queue_depth=1,
                             request_timeout_s=60, zenoh_enabled=False)
    assert settings.localize_config.match.top_k == CONFIG_TOP_K
    assert settings.localize_config.refine == LocalizeConfig().refine  # sections not in the file keep the defaults
    parts, meta = codec.encode_frame_parts(frame)
    live = LiveServer(settings)
    try:
        with httpx.Client(base_url=live.url, timeout=120.0) as client:
            r = _post(client, parts, _without_top_k(meta))
            assert r.status_code == 200, r.text
            assert r.json()["status"] in ("ok", "ambiguous") and len(r.json()["hypotheses"]) == CONFIG_TOP_K
            # a request's own top_k still wins; it also shows the frame has more hypotheses than the config keeps
            r = _post(client, parts, {**_without_top_k(meta), "top_k": CONFIG_TOP_K + 2})
            assert r.status_code == 200 and len(r.json()["hypotheses"]) == CONFIG_TOP_K + 2
            # a replacement worker gets the same config
            pool = live.service.pool
            old_pid = pool.workers_info()[0]["pid"]
            pool.kill_worker(0)
            deadline = time.monotonic() + 180
            while not (pool.ready and pool.workers_info()[0]["pid"] not in (None, old_pid)):
                assert time.monotonic() < deadline, "the killed worker was not replaced"
                time.sleep(0.1)
            r = _post(client, parts, _without_top_k(meta))
            assert r.status_code == 200 and len(r.json()["hypotheses"]) == CONFIG_TOP_K
    finally:
        live.stop()


# --- a bad config stops the start, naming the field ----------------------------------------------------------------


@pytest.mark.parametrize(
    "name, text, needle",
    [
        ("bounds.json", '{"match": {"top_k": 0}}', "match.top_k: Input should be greater than or equal to 1"),
        ("bounds.toml", "[match]\ntop_k = 0\n", "match.top_k: Input should be greater than or equal to 1"),
        ("unknown.toml", "[match]\ntop_kk = 3\n", "match.top_kk: Extra inputs are not permitted"),
        ("section.json", '{"matching": {}}', "matching: Extra inputs are not permitted"),
        ("choice.toml", '[refine]\nmethod = "icp"\n', "refine.method: Input should be"),
        ("broken.toml", "[match\ntop_k = 3\n", "not valid TOML"),
        ("broken.json", '{"match": ', "not valid JSON"),
        ("list.json", "[1, 2]", "the top level must be a table"),
        ("config.yaml", "match: {}", "expected a .toml or .json file"),
    ],
)
def test_bad_localize_config_fails_naming_the_field(tmp_path, monkeypatch, name, text, needle) -> None:
    path = tmp_path / name
    path.write_text(text)
    for given in ("flag", "environment"):
        with pytest.raises(ConfigError) as info:
            if given == "flag":
                settings_from(localize_config=str(path))
            else:
                monkeypatch.setenv("CADREG_LOCALIZE_CONFIG", str(path))
                Settings()
        message = info.value.message
        assert message.startswith(f"bad localize config {path}: ") and needle in message, message
        assert "\n" not in message
    monkeypatch.delenv("CADREG_LOCALIZE_CONFIG")


def test_missing_localize_config_fails_and_unset_means_defaults(tmp_path, monkeypatch) -> None:
    with pytest.raises(ConfigError, match=f"bad localize config {tmp_path / 'absent.toml'}: no such file"):
        settings_from(localize_config=str(tmp_path / "absent.toml"))
    assert Settings().localize_config == LocalizeConfig()
    monkeypatch.setenv("CADREG_LOCALIZE_CONFIG", "")
    assert Settings().localize_config == LocalizeConfig()
    # a LocalizeConfig given in code is taken as it is; a bad dict is a bad service setting naming the field
    config = LocalizeConfig.model_validate({"match": {"top_k": 7}})
    assert settings_from(localize_config=config).localize_config is config
    with pytest.raises(ConfigError, match=r"^bad service settings: localize_config\.match\.top_k: "):
        settings_from(localize_config={"match": {"top_k": 0}})


@pytest.mark.parametrize("given", ["flag", "environment"])
def test_cadreg_serve_refuses_a_bad_localize_config_in_one_line(scene0470_site_dir, tmp_path, given) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[match]\ntop_k = 0\n")
    args = [sys.executable, "-m", "cadreg.cli.main", "serve", "--sites", str(scene0470_site_dir.parent),
            "--port", str(free_port()), "--no-zenoh"]
    env = dict(os.environ)
    env.pop("CADREG_LOCALIZE_CONFIG", None)
    if given == "flag":
        args += ["--localize-config", str(path)]
    else:
        env["CADREG_LOCALIZE_CONFIG"] = str(path)
    run = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [
        f"cadreg serve: error [invalid_config]: bad localize config {path}: "
        "match.top_k: Input should be greater than or equal to 1"
    ], run.stderr[-2000:]


# --- the worker gets the parsed meta -------------------------------------------------------------------------------


def test_worker_localizes_the_parsed_meta_without_validating_it_again(scene0470_site_dir, frame, monkeypatch) -> None:
    sites = _Sites(LocalizeConfig.model_validate({"match": {"top_k": 3}}))
    sites.load(SITE, str(scene0470_site_dir))
    parts, meta = codec.encode_frame_parts(frame)
    left_to_service = FrameMeta.model_validate(_without_top_k(meta))
    asked = FrameMeta.model_validate({**_without_top_k(meta), "top_k": 1})

    def validated_again(*args, **kwargs):
        raise AssertionError("the worker validated the meta a second time")

    monkeypatch.setattr(FrameMeta, "model_validate", validated_again)
    monkeypatch.setattr(FrameMeta, "model_validate_json", validated_again)
    kind, job_id, ok, body, version = _localize(sites, ("localize", 7, SITE, None, parts, left_to_service), False)
    assert (kind, job_id, ok) == ("result", 7, True), body
    assert body["status"] in ("ok", "ambiguous") and len(body["hypotheses"]) == 3  # the worker's config decides
    assert version == json.loads((scene0470_site_dir / "site.json").read_text())["version"]
    _, _, ok, body, _ = _localize(sites, ("localize", 8, SITE, None, parts, asked), False)
    assert ok and len(body["hypotheses"]) == 1


def test_the_pool_takes_only_a_validated_meta(frame) -> None:
    parts, meta = codec.encode_frame_parts(frame)
    pool = WorkerPool({}, workers=1, queue_depth=1, timeout_s=1.0)  # not started: submit checks before queueing
    try:
        for text in (meta.model_dump_json(), meta.model_dump()):
            with pytest.raises(TypeError, match="FrameMeta"):
                pool.submit(SITE, None, parts, text)
        assert pool.queue_len() == 0
    finally:
        pool.stop()


def test_the_workers_config_must_be_typed() -> None:
    with pytest.raises(TypeError, match="LocalizeConfig"):
        _Sites({"match": {"top_k": 2}})


# --- the parent reads manifests ------------------------------------------------------------------------------------


def _no_load(*args, **kwargs):
    raise AssertionError("the parent parsed a bundle's point clouds")


def test_inspect_reads_the_manifest_and_never_loads_the_site(scene0470_site_dir, monkeypatch) -> None:
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    monkeypatch.setattr(Site, "load", classmethod(_no_load))
    entry = inspect_bundle(scene0470_site_dir)
    assert (entry.site_id, entry.version) == (site.site_id, site.version)
    assert entry.points == len(site.map) and entry.nodes == len(site.graph.nodes)
    assert entry.edges == site.graph.graph.number_of_edges() and entry.classes == tuple(site.classes)
    assert entry.path == str(scene0470_site_dir.resolve())


def test_a_tampered_map_is_refused_by_the_parent(scene0470_site_dir, tmp_path, monkeypatch) -> None:
    from cadreg.site.bundle import Site

    bundle = tmp_path / "sites" / SITE
    shutil.copytree(scene0470_site_dir, bundle)
    with open(bundle / "map.ply", "r+b") as f:
        f.seek(-6, os.SEEK_END)
        f.write(b"\x00\x01\x02\x03\x04\x05")
    monkeypatch.setattr(Site, "load", classmethod(_no_load))
    with pytest.raises(BundleIntegrityError) as info:
        inspect_bundle(bundle)
    assert "map.ply" in info.value.message
    with pytest.raises(BundleIntegrityError, match="map.ply"):
        SiteRegistry(bundle.parent).load_all()


def test_a_manifest_without_counts_is_refused(scene0470_site_dir, tmp_path) -> None:
    from cadreg.errors import InvalidFileError

    bundle = tmp_path / SITE
    shutil.copytree(scene0470_site_dir, bundle)
    meta = json.loads((bundle / "site.json").read_text())
    del meta["counts"]  # not among the keys Site.check_files checks: the registry needs it
    (bundle / "site.json").write_text(json.dumps(meta))
    with pytest.raises(InvalidFileError, match="counts"):
        inspect_bundle(bundle)
