"""The worker pool on its own: workers that cannot load their sites, a failed reload, per-job deadlines, cancelled
jobs. (Kills, timeouts and overload through HTTP are in test_service_http.py.)"""

from __future__ import annotations

import concurrent.futures
import shutil
import time
from pathlib import Path

import pytest

from cadreg.errors import InvalidFileError, RequestTimeout, UnknownSite
from service import codec
from service.pool import JobResult, WorkerPool
from service.schemas import FrameMeta
from service.worker import SLEEP_HOOK_PREFIX
from test_service_support import load_frames, render_frames


def test_workers_that_cannot_start_never_leave_a_request_hanging(tmp_path) -> None:
    pool = WorkerPool({"ghost": str(tmp_path / "missing")}, workers=1, queue_depth=2, timeout_s=1.5)
    pool.start()
    try:
        deadline = time.monotonic() + 60
        while pool.start_error is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pool.start_error is not None and pool.start_error["code"] == "invalid_file"
        assert "missing" in pool.start_error["message"]
        assert not pool.ready and pool.restarts["start_failed"] >= 1
        t0 = time.monotonic()
        meta = FrameMeta(depth_intrinsics={"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5})
        future = pool.submit("ghost", None, {"color": b"x", "depth": b"y"}, meta)
        with pytest.raises(RequestTimeout):
            future.result(timeout=10)
        assert time.monotonic() - t0 < 3.0
    finally:
        pool.stop()


@pytest.fixture(scope="module")
def pool(scene0470_site_dir: Path):
    p = WorkerPool({"scene0470": str(scene0470_site_dir)}, workers=1, queue_depth=2, timeout_s=30, test_hooks=True)
    p.start()
    assert p.wait_ready(180)
    yield p
    p.stop()


@pytest.fixture(scope="module")
def envelope(scene0470_site_dir: Path, tmp_path_factory):
    frame, _ = load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("pframes"), n=1))[0]
    parts, meta = codec.encode_frame_parts(frame)
    return parts, meta


def test_a_job_gives_a_result_with_its_version_and_timings(pool, envelope, scene0470_site_dir) -> None:
    parts, meta = envelope
    job = pool.submit("scene0470", None, parts, meta).result(timeout=60)
    assert isinstance(job, JobResult) and job.result["status"] in ("ok", "ambiguous")
    assert job.site_version == codec.decode_result((scene0470_site_dir / "site.json").read_bytes())["version"]
    assert job.run_ms > 0 and job.queue_ms >= 0 and job.worker_pid == pool.workers_info()[0]["pid"]


def test_a_slot_frees_only_after_its_answer_is_delivered(pool, envelope) -> None:
    """A stream takes its device's next frame when the pool has room; the finished frame's callbacks (its tracking
    session's state stored) must have run by then, or the next frame leaves without the state."""
    parts, meta = envelope
    while pool.free_slots() < 3:  # idle: one worker and two queue places
        time.sleep(0.01)
    seen: list[int] = []
    future = pool.submit("scene0470", None, parts, meta)
    future.add_done_callback(lambda f: seen.append(pool.free_slots()))
    future.result(timeout=60)
    assert seen == [2]  # while its callbacks ran, the job still held its place
    assert pool.free_slots() == 3


def test_worker_errors_come_back_typed_and_the_worker_lives_on(pool, envelope) -> None:
    parts, meta = envelope
    with pytest.raises(UnknownSite):
        pool.submit("elsewhere", None, parts, meta).result(timeout=60)
    bad = dict(parts, depth=b"\x89PNG broken")
    with pytest.raises(Exception) as info:
        pool.submit("scene0470", None, bad, meta).result(timeout=60)
    assert info.value.code == "invalid_frame"
    assert pool.restarts == {} and pool.submit("scene0470", None, parts, meta).result(60)


def test_failed_reload_keeps_serving_the_old_version(pool, envelope, tmp_path, scene0470_site_dir) -> None:
    with pytest.raises(InvalidFileError):
        pool.load_site("scene0470", str(tmp_path / "nothing-here")).result(timeout=60)
    parts, meta = envelope
    assert pool.submit("scene0470", None, parts, meta).result(60).result["status"] in ("ok", "ambiguous")
    # a replacement worker would still load the good bundle
    assert pool.site_paths() == {"scene0470": str(scene0470_site_dir)}


def test_a_worker_replaced_during_a_reload_loads_the_new_version(pool, envelope, scene0470_site_dir, tmp_path) -> None:
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    site.map.colors = site.map.colors.copy()
    site.map.colors[1] = 255 - site.map.colors[1]
    second = tmp_path / "scene0470"
    site.save(second)
    parts, meta = envelope
    # the worker is busy when the reload arrives, and dies before it can run it
    sleeper = meta.model_copy(update={"frame_id": f"{SLEEP_HOOK_PREFIX}30"})
    busy = pool.submit("scene0470", None, parts, sleeper)
    while pool.workers_info()[0]["state"] != "busy":
        time.sleep(0.01)
    loaded = pool.load_site("scene0470", str(second))
    pool.kill_worker(0)
    with pytest.raises(Exception) as info:
        busy.result(timeout=30)
    assert info.value.code == "worker_crashed"
    loaded.result(timeout=120)
    assert pool.site_paths() == {"scene0470": str(second)}
    job = pool.submit("scene0470", site.version, parts, meta).result(60)
    assert job.site_version == site.version
    pool.load_site("scene0470", str(scene0470_site_dir)).result(timeout=120)


def test_a_reload_with_the_parents_findings_loads_and_a_file_changed_since_is_refused(
        pool, envelope, scene0470_site_dir, tmp_path) -> None:
    from cadreg.site.bundle import SETTLED_NS
    from service.registry import inspect_bundle

    copy = tmp_path / "scene0470"
    shutil.copytree(scene0470_site_dir, copy)
    time.sleep(SETTLED_NS / 1e9 + 0.1)
    entry = inspect_bundle(copy)  # the parent's check: what it found goes to the workers with the path
    assert {"map.ply", "raw.ply", "graph.json"} <= set(entry.checked)
    pool.load_site("scene0470", str(copy), entry.checked).result(timeout=120)
    parts, meta = envelope
    assert pool.submit("scene0470", None, parts, meta).result(60).site_version == entry.version
    blob = bytearray((copy / "raw.ply").read_bytes())
    blob[-1] ^= 0x01
    (copy / "raw.ply").write_bytes(bytes(blob))
    with pytest.raises(InvalidFileError, match="raw.ply: sha256 does not match"):
        pool.load_site("scene0470", str(copy), entry.checked).result(timeout=120)
    pool.load_site("scene0470", str(scene0470_site_dir)).result(timeout=120)
    assert pool.site_paths() == {"scene0470": str(scene0470_site_dir)}


def test_a_cancelled_queued_job_is_skipped(pool, envelope) -> None:
    parts, meta = envelope
    sleeper = meta.model_copy(update={"frame_id": f"{SLEEP_HOOK_PREFIX}1.0"})
    first = pool.submit("scene0470", None, parts, sleeper)
    second = pool.submit("scene0470", None, parts, meta)
    assert second.cancel()  # still queued behind the sleeper: the client went away
    third = pool.submit("scene0470", None, parts, meta)
    assert first.result(60).result["frame_id"] == sleeper.frame_id
    assert third.result(60).result["status"] in ("ok", "ambiguous")
    assert second.cancelled()
    with pytest.raises(concurrent.futures.CancelledError):
        second.result()


def test_overload_says_how_long_the_queue_takes_to_drain(pool, envelope) -> None:
    """Turned away, a request is told the expected wait (from the recent time per job), not a fixed second."""
    from cadreg.errors import Overloaded

    parts, meta = envelope
    for _ in range(3):  # a few real jobs give the pool its time per job
        pool.submit("scene0470", None, parts, meta).result(60)
    per_job_s = pool._service_s
    assert per_job_s is not None and 0.0 < per_job_s < 1.0
    # one running + queue_depth (2) waiting: the pool is full
    held = [pool.submit("scene0470", None, parts, meta)]
    try:
        deadline = time.monotonic() + 10
        while pool.workers_info()[0]["state"] != "busy" and time.monotonic() < deadline:
            time.sleep(0.002)
        held += [pool.submit("scene0470", None, parts, meta) for _ in range(2)]
        with pytest.raises(Overloaded) as info:
            pool.submit("scene0470", None, parts, meta)
        # 2 queued + this one, on 1 worker, at the recent time per job; never above the configured Retry-After
        assert info.value.retry_after_s == pytest.approx(min(1.0, max(0.05, 3 * per_job_s)), abs=0.002)
    finally:
        for f in held:
            f.result(60)


def test_a_worker_loads_a_building_without_hashing_again_what_the_parents_check_found(twin_rooms_dir: Path,
                                                                                      monkeypatch) -> None:
    """The worker's side of the hand-over, in this process: given the parent's findings, a building's mapped clouds
    and stored grids (1.3 GB for 100 rooms) are not hashed again; graph.json, read whole, is hashed from its bytes."""
    import cadreg.site.bundle as bundle
    from cadreg.config import LocalizeConfig
    from service.registry import inspect_bundle
    from service.worker import _Sites

    time.sleep(bundle.SETTLED_NS / 1e9 + 0.1)
    entry = inspect_bundle(twin_rooms_dir)
    assert {"map.ply", "raw.ply", "field.npy", "regions.npy", "pyramid.npy"} <= set(entry.checked)
    hashed: list[str] = []
    real = bundle.sha256_file
    monkeypatch.setattr(bundle, "sha256_file", lambda path: hashed.append(Path(path).name) or real(path))
    version, _ = _Sites(LocalizeConfig(label_free={"enabled": False})).build(entry.site_id, str(twin_rooms_dir),
                                                                             entry.checked)
    assert version == entry.version and hashed == []
