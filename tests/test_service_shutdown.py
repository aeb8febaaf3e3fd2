"""Stopping `cadreg serve` the way service managers do: SIGTERM to the whole process group (systemd's default for a
unit's control group, `kill -- -PGID`). A real `cadreg serve` subprocess (2 workers, loopback) in a session of its
own, a request in flight when the signal comes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

from test_service_support import free_port, load_frames, multipart, render_frames, wait_served

SITE = "scene0470"
SLEEP_S = 3.0  # the test hook's frame id keeps the worker busy this long: the signal comes mid-request


def _alive(pid: int, *, group: bool = False) -> bool:
    """Whether process `pid` (with group: any process of the group `pid` leads) still exists."""
    try:
        (os.killpg if group else os.kill)(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_sigterm_to_the_process_group_answers_the_request_in_flight_and_stops_without_restarts(
        scene0470_site_dir: Path, tmp_path: Path) -> None:
    sites = tmp_path / "sites"
    sites.mkdir()
    (sites / SITE).symlink_to(scene0470_site_dir, target_is_directory=True)
    frame, _ = load_frames(render_frames(scene0470_site_dir, tmp_path / "frames", n=1))[0]
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log = tmp_path / "serve.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CADREG_TEST_HOOKS": "true"}
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "cadreg.cli.main", "serve", "--sites", str(sites),
                                 "--port", str(port), "--workers", "2", "--no-zenoh"], env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_served(proc, url, log)
        answer: dict = {}

        def request() -> None:
            files, data = multipart(frame, frame_id=f"__sleep__:{SLEEP_S}")
            answer["response"] = httpx.post(f"{url}/v1/sites/{SITE}/localize", files=files, data=data, timeout=60)

        sender = threading.Thread(target=request)
        sender.start()
        time.sleep(1.0)  # the request is in a worker now, asleep in the hook
        os.killpg(proc.pid, signal.SIGTERM)
        sender.join(60)
        # uvicorn ends a graceful shutdown by raising the signal again: the status says what stopped it
        assert proc.wait(60) in (0, -signal.SIGTERM), log.read_text()[-3000:]
        deadline = time.monotonic() + 10
        while _alive(proc.pid, group=True) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(proc.pid, group=True), "a process of the service outlived it"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    assert "response" in answer, "the request in flight got no answer"
    response = answer["response"]
    assert response.status_code == 200, response.text
    assert response.json()["status"] == "ok"
    text = log.read_text()
    # no worker died of the signal, so none failed its request or was started again during the shutdown
    assert "died with exit code" not in text and "retired" not in text, text[-3000:]
    assert "Application shutdown complete" in text


def test_a_process_that_exits_without_stopping_its_pool_stops_the_workers(scene0470_site_dir: Path) -> None:
    """The workers ignore SIGTERM, which is what multiprocessing's own exit sends its children before it waits for
    them: a process that leaves without `WorkerPool.stop` (an error between the pool's start and the server's) must
    still end, and its workers with it."""
    script = (
        "import sys\n"
        "from service.pool import WorkerPool\n"
        f"pool = WorkerPool({{'{SITE}': {str(scene0470_site_dir)!r}}}, workers=2, queue_depth=2, timeout_s=30)\n"
        "pool.start()\n"
        "assert pool.wait_ready(180)\n"
        "print(' '.join(str(w['pid']) for w in pool.workers_info()), flush=True)\n"
        "sys.exit(0)\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=240,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    pids = [int(p) for p in proc.stdout.split()]
    assert len(pids) == 2
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in pids), "a worker outlived its pool's process"

