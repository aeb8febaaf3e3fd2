"""Helpers shared by the service tests (no tests here): a real uvicorn on a free loopback port in a thread, frames
rendered by `cadreg render`, multipart requests with plain httpx, and the library's own answer for comparison."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service import codec

RENDER_SEED = 3


def free_ports(count: int) -> list[int]:
    """`count` distinct free ports on 127.0.0.1, all bound at once: a port freed and asked for again may come back
    the same (an HTTP port and a zenoh port taken one after the other coincided, and the service could not start)."""
    with ExitStack() as held:
        sockets = [held.enter_context(socket.socket()) for _ in range(count)]
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]


def free_port() -> int:
    return free_ports(1)[0]


class LiveServer:
    """`create_app(settings)` under a real uvicorn in a background thread, on 127.0.0.1; with `as_served`,
    uvicorn is configured as `cadreg serve` configures it (`uvicorn_options`: header and keep-alive limits)."""

    def __init__(self, settings, ready_timeout_s: float = 180.0, *, as_served: bool = False) -> None:
        import uvicorn

        from service.http_app import create_app, uvicorn_options

        self.settings = settings
        self.app = create_app(settings)
        self.service = self.app.state.service
        options = uvicorn_options(settings) if as_served else {"host": "127.0.0.1", "port": settings.port}
        config = uvicorn.Config(self.app, **options, log_level="warning", access_log=False, lifespan="on")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-test", daemon=True)
        self.url = f"http://127.0.0.1:{settings.port}"
        self.thread.start()
        deadline = time.monotonic() + ready_timeout_s
        while time.monotonic() < deadline:
            if not self.thread.is_alive():
                raise RuntimeError("uvicorn exited during start-up")
            try:
                if httpx.get(self.url + "/readyz", timeout=2.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.stop()
        raise TimeoutError("the service did not become ready")

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            r = httpx.get(self.url + "/readyz", timeout=2.0)
            if r.status_code == 200 and r.json()["workers_alive"] == self.settings.workers:
                return
            time.sleep(0.1)
        raise TimeoutError("pool not whole again")

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30.0)


_RENDERED: dict[tuple[str, int], Path] = {}
_LIBRARY: dict[tuple[str, str], list[dict[str, Any]]] = {}


def wait_served(proc: subprocess.Popen, url: str, log: Path, timeout_s: float = 180.0) -> None:
    """Until the `cadreg serve` subprocess `proc` (its output in `log`) answers /readyz at `url` ready; it must not
    exit meanwhile (the log's tail says why it did)."""
    deadline = time.monotonic() + timeout_s
    while True:
        assert proc.poll() is None, f"cadreg serve exited:\n{log.read_text()[-3000:]}"
        try:
            if httpx.get(url + "/readyz", timeout=2).json().get("ready"):
                return
        except (httpx.HTTPError, ValueError):
            pass
        assert time.monotonic() < deadline, f"service not ready:\n{log.read_text()[-3000:]}"
        time.sleep(0.3)


def render_frames(site_dir: Path, out: Path, n: int = 4) -> Path:
    """Render `n` frames of a site with `cadreg render` (the user's command) into `out`; a session renders each
    (site, n) once and hands the same folder to later callers."""
    key = (str(site_dir), n)
    if key in _RENDERED:
        return _RENDERED[key]
    subprocess.run(
        [sys.executable, "-m", "cadreg.cli.main", "render", "--site", str(site_dir), "--out", str(out),
         "--n", str(n), "--seed", str(RENDER_SEED)],
        check=True, capture_output=True, timeout=300,
    )
    _RENDERED[key] = out
    return out


def load_frames(frames_dir: Path) -> list[tuple[Any, np.ndarray | None]]:
    from cadreg.io.frames import RecordedFrames

    rec = RecordedFrames.open(frames_dir)
    return [rec.load(i) for i in range(len(rec))]


def library_results(site_dir: Path, frames: list) -> list[dict[str, Any]]:
    """What the library itself answers for each frame (the reference the service must match); memoised per
    (site, frame ids) for the session."""
    from cadreg.localize.localizer import Localizer
    from cadreg.site.bundle import Site

    key = (str(site_dir), ",".join(str(frame.frame_id) for frame, _ in frames))
    if key not in _LIBRARY:
        localizer = Localizer.from_site(Site.load(site_dir))
        _LIBRARY[key] = [localizer.localize(frame).to_dict() for frame, _ in frames]
    return _LIBRARY[key]


def multipart(frame, *, frame_id: str | None = None, top_k: int = 5, meta_override: dict | None = None,
              parts_override: dict | None = None, drop: tuple[str, ...] = ()) -> tuple[dict, dict]:
    """httpx `files` and `data` for one localize request."""
    parts, meta = codec.encode_frame_parts(frame, top_k=top_k)
    meta_doc = meta.model_dump(mode="json")
    if frame_id is not None:
        meta_doc["frame_id"] = frame_id
    meta_doc.update(meta_override or {})
    parts.update(parts_override or {})
    files = {name: (f"{name}.png", data, "image/png") for name, data in parts.items() if name not in drop}
    data = {} if "meta" in drop else {"meta": json.dumps(meta_doc)}
    return files, data


def pose_error(T_a, T_b) -> tuple[float, float]:
    """(translation m, rotation deg) between two 4x4 poses."""
    from cadreg.geometry import pose_errors

    return pose_errors(np.asarray(T_a, float), np.asarray(T_b, float))


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")
