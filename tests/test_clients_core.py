"""The client core shared by every transport (clients/core.py, clients/retry.py): one retry loop for sync and async
calls, one frame encoder with the client's top_k and one folder cache; the HTTP and zenoh clients are built on it."""

from __future__ import annotations

import asyncio
import random
from pathlib import Path

import numpy as np
import pytest

import clients.frames as frames_mod
from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from cadreg.io.frames import FramesWriter
from clients import errors as cerr
from clients.core import ClientCore
from clients.frames import encode_frame
from clients.http import AsyncClient, Client
from clients.retry import RetryLoop, RetryPolicy
from clients.zenoh_client import ZenohClient


def _frame(fid: str | None = "f0") -> Frame:
    rng = np.random.default_rng(3)
    K = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    return Frame(depth=rng.integers(500, 3000, (24, 32)).astype(np.uint16),
                 color=rng.integers(0, 255, (24, 32, 3)).astype(np.uint8),
                 depth_intrinsics=K, color_intrinsics=K, frame_id=fid)


def _script(errors: list[cerr.ClientError]):
    """send() that raises the given errors in turn, then answers; counts its calls."""
    calls = []

    def send():
        calls.append(1)
        if len(calls) <= len(errors):
            raise errors[len(calls) - 1]
        return {"status": "ok", "attempts": len(calls)}

    return send, calls


def _loop(seed: int, **kw) -> RetryLoop:
    return RetryLoop(RetryPolicy(max_retries=3, backoff_base_s=0.1, rng=random.Random(seed)), **kw)


def test_sync_and_async_calls_retry_the_same_way() -> None:
    failures = [cerr.Overloaded("full", retry_after_s=0.5), cerr.Unreachable("down"), cerr.WorkerCrashed("died")]
    sync_sleeps: list[float] = []
    hooked: list[tuple[int, str]] = []
    loop = _loop(7, on_retry=lambda n, e, d: hooked.append((n, e.code)))
    send, calls = _script(failures)
    assert loop.call(send, sync_sleeps.append) == {"status": "ok", "attempts": 4}
    assert len(calls) == 4 and loop.count == 3
    assert hooked == [(1, "overloaded"), (2, "unreachable"), (3, "worker_crashed")]

    async_sleeps: list[float] = []

    async def record(delay: float) -> None:
        async_sleeps.append(delay)

    aloop = _loop(7)
    asend, acalls = _script(failures)

    async def coro():
        return asend()

    # a fresh loop with the same seed: the same errors must give the same waits, in the same order
    assert asyncio.run(aloop.acall(coro, record)) == {"status": "ok", "attempts": 4}
    assert async_sleeps == sync_sleeps and len(sync_sleeps) == 3
    assert 0.5 <= sync_sleeps[0] <= 1.0  # Retry-After plus its jitter


def test_a_call_raises_the_error_it_may_not_retry() -> None:
    sleeps: list[float] = []
    loop = _loop(1)
    send, calls = _script([cerr.Unreachable("down"), cerr.InvalidFrame("bad depth")])
    with pytest.raises(cerr.InvalidFrame, match="bad depth"):
        loop.call(send, sleeps.append)
    assert len(calls) == 2 and len(sleeps) == 1 and loop.count == 1
    send, calls = _script([cerr.Overloaded("full")] * 10)
    with pytest.raises(cerr.Overloaded):
        loop.call(send, sleeps.append)
    assert len(calls) == 4  # the first try and max_retries=3


def test_a_fresh_call_waits_out_the_clients_pause_first() -> None:
    sleeps: list[float] = []
    loop = _loop(2)
    send, _ = _script([cerr.Overloaded("full", retry_after_s=5.0)])
    loop.call(send, lambda d: None)  # leaves a 5 s pause on the client (no real sleeping)
    send, calls = _script([])
    loop.call(send, sleeps.append)
    assert len(calls) == 1 and len(sleeps) == 1 and 4.5 <= sleeps[0] <= 10.0


def _folder(root: Path, n: int = 3) -> Path:
    frames = [_frame(str(i)) for i in range(n)]
    writer = FramesWriter(root, frames[0].depth_intrinsics, frames[0].color_intrinsics, frames[0].T_color_depth)
    for i, f in enumerate(frames):
        writer.write(i, f, np.eye(4))
    return root


def test_the_core_encodes_with_the_clients_top_k_and_one_folder_cache(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    root = _folder(tmp_path)
    opened: list[Path] = []
    real_open = frames_mod.RecordedFrames.open

    def counting_open(path):
        opened.append(Path(path))
        return real_open(path)

    monkeypatch.setattr(frames_mod.RecordedFrames, "open", staticmethod(counting_open))
    core = ClientCore(top_k=9)
    assert core.encode((root, 1)).meta.top_k == 9 and core.encode((root, 2)).frame_id == "2"
    assert len(opened) == 1  # the folder is scanned once for all its frames
    assert core.encode((root, 1), top_k=2).meta.top_k == 2
    assert core.encode(_frame(), frame_id="x").frame_id == "x"
    enc = encode_frame(_frame(), top_k=4)
    assert core.encode(enc).meta.top_k == 9 and ClientCore().encode(enc) is enc  # None: the frame's own
    assert ClientCore().encode(_frame()).meta.top_k == 5


def test_every_transport_is_a_client_core() -> None:
    # one core, so that frames, top_k and retries cannot drift apart between HTTP and zenoh
    for cls in (Client, AsyncClient, ZenohClient):
        assert issubclass(cls, ClientCore)
    with Client("http://127.0.0.1:9", top_k=3) as c:
        assert c.encode(_frame()).meta.top_k == 3 and c.retries == 0
