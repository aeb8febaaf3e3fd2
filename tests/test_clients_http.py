"""HTTP client error paths against httpx.MockTransport: typed errors, retries on 503/connection errors honouring
Retry-After, never on 4xx/504, deadlines, and the multipart request itself."""

from __future__ import annotations

import asyncio
import email.parser
import email.policy
import email.utils
import json
import random
import time

import httpx
import numpy as np
import pytest

from cadreg import errors as core
from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from clients import errors as cerr
from clients.frames import encode_frame
from clients.http import AsyncClient, Client, parse_retry_after, pose_of
from clients.retry import RetryPolicy
from service import codec

OK = {"status": "ok", "frame_id": "f0", "T_map_camera": np.eye(4).tolist(), "request_id": "r1",
      "site_id": "s", "site_version": "v1"}


def _frame() -> Frame:
    rng = np.random.default_rng(3)
    K = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    return Frame(depth=rng.integers(500, 3000, (24, 32)).astype(np.uint16),
                 color=rng.integers(0, 255, (24, 32, 3)).astype(np.uint8),
                 labels=rng.integers(0, 40, (24, 32)).astype(np.uint8),
                 depth_intrinsics=K, color_intrinsics=K, frame_id="f0")


def _error(status: int, code: str, retry_after: str | None = None) -> httpx.Response:
    headers = {"Retry-After": retry_after} if retry_after else {}
    return httpx.Response(status, json={"code": code, "message": f"{code}!", "request_id": "rq", "detail": {}},
                          headers=headers)


class Script:
    """A MockTransport handler answering from a list (responses or exceptions to raise), recording requests."""

    def __init__(self, *answers: httpx.Response | Exception) -> None:
        self.answers = list(answers)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        answer = self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]
        if isinstance(answer, Exception):
            raise answer
        return answer


def _client(script: Script, sleeps: list[float], **kw) -> Client:
    kw.setdefault("retry", RetryPolicy(max_retries=3, backoff_base_s=0.1, rng=random.Random(1)))
    return Client("http://svc", transport=httpx.MockTransport(script), sleep=sleeps.append, **kw)


def test_localize_sends_multipart_parts_the_service_can_decode() -> None:
    script = Script(httpx.Response(200, json=OK))
    with _client(script, []) as c:
        result = c.localize("my site", _frame(), top_k=4)
    assert result["status"] == "ok" and np.allclose(pose_of(result), np.eye(4))
    (req,) = script.requests
    assert req.method == "POST" and req.url.raw_path == b"/v1/sites/my%20site/localize"
    msg = email.parser.BytesParser(policy=email.policy.HTTP).parsebytes(
        b"Content-Type: " + req.headers["content-type"].encode() + b"\r\n\r\n" + req.read())
    fields = {p.get_param("name", header="content-disposition"): p for p in msg.iter_parts()}
    assert set(fields) == {"color", "depth", "labels", "meta"}
    meta = json.loads(fields["meta"].get_content())
    assert meta["top_k"] == 4 and meta["frame_id"] == "f0"
    parts = {k: fields[k].get_payload(decode=True) for k in ("color", "depth", "labels")}
    assert fields["depth"].get_content_type() == "image/png"
    got = codec.decode_frame(parts, meta)
    f = _frame()
    assert np.array_equal(got.depth, f.depth) and np.array_equal(got.labels, f.labels)


def test_503_is_retried_after_retry_after_then_succeeds() -> None:
    script = Script(_error(503, "overloaded", "2"), _error(503, "worker_crashed", "1"), httpx.Response(200, json=OK))
    sleeps: list[float] = []
    retried: list[tuple[int, str, float]] = []
    with _client(script, sleeps, on_retry=lambda n, e, d: retried.append((n, e.code, d))) as c:
        assert c.localize("s", _frame())["status"] == "ok"
        assert c.retries == 2
    assert len(script.requests) == 3
    assert 2.0 <= sleeps[0] <= 4.0 and 1.0 <= sleeps[1] <= 2.0, sleeps  # Retry-After r + jitter in [0, r]
    assert [(n, code) for n, code, _ in retried] == [(1, "overloaded"), (2, "worker_crashed")]


def test_503_exhausts_retries_and_raises_overloaded() -> None:
    script = Script(_error(503, "overloaded", "1"))
    sleeps: list[float] = []
    with _client(script, sleeps) as c, pytest.raises(cerr.Overloaded) as info:
        c.localize("s", _frame())
    assert len(script.requests) == 4 and len(sleeps) == 3
    assert info.value.status == 503 and info.value.retry_after_s == 1.0 and info.value.request_id == "rq"
    assert isinstance(info.value, core.Overloaded)


@pytest.mark.parametrize("status,code,cls", [
    (422, "invalid_frame", cerr.InvalidFrame),
    (404, "unknown_site", cerr.UnknownSite),
    (413, "payload_too_large", cerr.PayloadTooLarge),
    (504, "timeout", cerr.RequestTimeout),
    (500, "internal", cerr.InternalError),
    (401, "unauthorized", cerr.Unauthorized),
])
def test_no_retry_on_4xx_504_500(status: int, code: str, cls: type) -> None:
    script = Script(_error(status, code, "1"), httpx.Response(200, json=OK))
    sleeps: list[float] = []
    with _client(script, sleeps) as c, pytest.raises(cls) as info:
        c.localize("s", _frame())
    assert len(script.requests) == 1 and sleeps == []
    assert info.value.code == code and info.value.status == status


def test_connection_errors_are_retried_with_backoff() -> None:
    script = Script(httpx.ConnectError("refused"), httpx.RemoteProtocolError("dropped"), httpx.Response(200, json=OK))
    sleeps: list[float] = []
    with _client(script, sleeps) as c:
        assert c.localize("s", _frame())["status"] == "ok"
    assert len(script.requests) == 3
    assert 0 <= sleeps[0] <= 0.1 and 0 <= sleeps[1] <= 0.2  # full jitter under 0.1 * 2**n


def test_connection_refused_for_good_raises_unreachable() -> None:
    script = Script(httpx.ConnectError("refused"))
    with _client(script, []) as c, pytest.raises(cerr.Unreachable):
        c.health()
    assert len(script.requests) == 4


def test_read_timeout_is_not_retried() -> None:
    script = Script(httpx.ReadTimeout("slow"), httpx.Response(200, json=OK))
    with _client(script, []) as c, pytest.raises(cerr.ClientTimeout) as info:
        c.localize("s", _frame())
    assert len(script.requests) == 1 and isinstance(info.value, core.RequestTimeout)


def test_deadline_and_huge_retry_after_stop_retries() -> None:
    script = Script(_error(503, "overloaded", "3"), httpx.Response(200, json=OK))
    with _client(script, [], deadline_s=2.0) as c, pytest.raises(cerr.Overloaded):
        c.localize("s", _frame())
    assert len(script.requests) == 1
    script = Script(_error(503, "overloaded", "600"), httpx.Response(200, json=OK))
    with _client(script, []) as c, pytest.raises(cerr.Overloaded):
        c.localize("s", _frame())
    assert len(script.requests) == 1


def test_503_without_our_body_and_non_json_answers() -> None:
    script = Script(httpx.Response(503, text="<html>starting</html>"), httpx.Response(200, json=OK))
    sleeps: list[float] = []
    with _client(script, sleeps) as c:
        assert c.localize("s", _frame())["status"] == "ok"
    assert len(sleeps) == 1
    script = Script(httpx.Response(502, text="<html>bad gateway</html>"))
    with _client(script, []) as c, pytest.raises(cerr.BadResponse) as info:
        c.sites()
    assert info.value.status == 502
    script = Script(httpx.Response(200, text="not json"))
    with _client(script, []) as c, pytest.raises(cerr.BadResponse):
        c.health()


def test_site_routes() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/sites":
            return httpx.Response(200, json={"sites": [{"site_id": "a", "version": "1"}]})
        if request.url.path == "/v1/sites/a":
            return httpx.Response(200, json={"site_id": "a", "version": "1", "nodes": 3, "edges": 2, "points": 9,
                                             "classes": ["chair"]})
        if request.url.path == "/healthz":
            return httpx.Response(200, json={"status": "ok"})
        return _error(404, "unknown_site")

    with Client("http://svc", transport=httpx.MockTransport(handler)) as c:
        assert c.sites() == [{"site_id": "a", "version": "1"}]
        assert c.site("a")["nodes"] == 3
        assert c.health() == {"status": "ok"}
        with pytest.raises(cerr.UnknownSite):
            c.site("b")


def test_parse_retry_after() -> None:
    assert parse_retry_after("3") == 3.0 and parse_retry_after(" 1.5 ") == 1.5
    assert parse_retry_after(None) is None and parse_retry_after("soon") is None
    now = time.time()
    date = email.utils.formatdate(now + 10, usegmt=True)
    assert 8.0 <= parse_retry_after(date, now=now) <= 11.0
    assert parse_retry_after(email.utils.formatdate(now - 10, usegmt=True), now=now) == 0.0


def test_async_client_retries_like_the_sync_one() -> None:
    script = Script(_error(503, "overloaded", "1"), httpx.ConnectError("refused"), httpx.Response(200, json=OK),
                    _error(422, "invalid_frame"))
    sleeps: list[float] = []

    async def record(delay: float) -> None:
        sleeps.append(delay)

    async def main() -> None:
        async with AsyncClient("http://svc", transport=httpx.MockTransport(script), sleep=record,
                               retry=RetryPolicy(max_retries=3, backoff_base_s=0.1)) as c:
            assert (await c.localize("s", encode_frame(_frame())))["status"] == "ok"
            assert c.retries == 2
            with pytest.raises(cerr.InvalidFrame):
                await c.localize("s", _frame())

    asyncio.run(main())
    # two retries, then the fresh request waits out what is left of the Retry-After pause (no time passed here)
    assert len(script.requests) == 4 and sleeps[0] >= 1.0 and len(sleeps) == 3 and 0.9 <= sleeps[2] <= 2.0


def test_retry_policy_delays() -> None:
    policy = RetryPolicy(max_retries=12, backoff_base_s=0.2, backoff_max_s=5.0, rng=random.Random(4))
    busy, down = cerr.Overloaded("busy", retry_after_s=1.0), cerr.Unreachable("down")
    for n in range(12):
        assert 1.0 <= policy.delay_s(n, busy) <= 2.0  # Retry-After plus at most its own length of jitter
        assert 0.0 <= policy.delay_s(n, down) <= min(5.0, 0.2 * 2**n)
    assert policy.delay_s(12, busy) is None and policy.delay_s(0, cerr.InvalidFrame("bad")) is None
    assert policy.delay_s(0, cerr.RequestTimeout("late")) is None and policy.delay_s(0, cerr.ClientTimeout("x")) is None
    with pytest.raises(ValueError):
        RetryPolicy(max_retries=-1)


def test_a_retry_budget_bounds_many_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    script = Script(_error(503, "overloaded", "1"))
    clock = [time.monotonic()]
    # time passes only while "sleeping": the deadline, not the count, ends the retries
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    with _client(script, [], retry=RetryPolicy(max_retries=10**6), deadline_s=10.0) as c:
        c._sleep = lambda d: clock.__setitem__(0, clock[0] + d)  # noqa: SLF001
        with pytest.raises(cerr.Overloaded):
            c.localize("s", _frame())
    assert 5 <= len(script.requests) <= 11


def test_retry_after_pauses_fresh_requests_of_the_same_client(monkeypatch: pytest.MonkeyPatch) -> None:
    script = Script(_error(503, "overloaded", "2"), httpx.Response(200, json=OK), httpx.Response(200, json=OK),
                    httpx.Response(200, json=OK))
    clock = [1000.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    sleeps: list[float] = []
    with _client(script, sleeps) as c:
        assert c.localize("s", _frame())["status"] == "ok"  # 503 at t=1000, retried after 2 s + jitter
        assert len(sleeps) == 1 and 2.0 <= sleeps[0] <= 4.0
        clock[0] += 0.5  # a fresh request half a second after the 503: the pause still holds it ~1.5 s + jitter
        c.localize("s", _frame())
        assert len(sleeps) == 2 and 1.5 <= sleeps[1] <= 3.5
        clock[0] += 10.0  # the pause is over: no wait
        c.localize("s", _frame())
        assert len(sleeps) == 2
