"""zenoh client over real zenoh sessions on loopback (scouting off), against an in-test queryable/subscriber that
speaks the wire contract: results, typed errors via reply_err, retries, timeouts, and the pose stream."""

from __future__ import annotations

import queue
import threading
import time
from typing import Iterator

import numpy as np
import pytest
import zenoh

from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from clients import errors as cerr
from clients.frames import encode_frame
from clients.retry import RetryPolicy
from clients.zenoh_client import ZenohClient, session_config
from service import codec, errors as wire, zenoh_wire
from test_service_support import free_port


def _frame(fid: str | None = "f0") -> Frame:
    rng = np.random.default_rng(5)
    K = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    return Frame(depth=rng.integers(500, 3000, (24, 32)).astype(np.uint16),
                 color=rng.integers(0, 255, (24, 32, 3)).astype(np.uint8),
                 depth_intrinsics=K, color_intrinsics=K, frame_id=fid)


class FakeService:
    """Queryable cadreg/<site>/localize and stream subscriber, decoding frames with the real service codec.

    Work happens on a thread of its own: callbacks only enqueue (as the service must)."""

    def __init__(self, endpoint: str) -> None:
        self.session = zenoh.open(session_config(listen=[endpoint], mode="peer"))
        self.work: queue.SimpleQueue = queue.SimpleQueue()
        self.calls: dict[str, int] = {}
        self.queryable = self.session.declare_queryable("cadreg/*/localize", lambda q: self.work.put(("q", q)))
        self.sub = self.session.declare_subscriber("cadreg/*/frames/*", lambda s: self.work.put(("s", s)))
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _answer(self, site: str, payload: bytes) -> dict:
        self.calls[site] = self.calls.get(site, 0) + 1
        parts, meta = codec.unpack_envelope(payload)
        frame = codec.decode_frame(parts, meta)
        if site == "missing":
            raise wire.UnknownSite(f"no site {site}")
        if site == "busy" and self.calls[site] <= 2:
            raise wire.Overloaded("queue full", retry_after_s=0.05)
        if frame.frame_id == "err":
            raise wire.InvalidFrame("frame says err")
        if site == "slow":
            time.sleep(1.0)
        return {"status": "ok", "frame_id": frame.frame_id, "T_map_camera": np.eye(4).tolist(),
                "depth_sum": int(frame.depth.sum()), "request_id": "r", "site_id": site, "site_version": "1"}

    def _serve(self) -> None:
        while True:
            kind, item = self.work.get()
            if kind == "stop":
                return
            site = str(item.key_expr).split("/")[1]
            if kind == "q":
                try:
                    body = self._answer(site, item.payload.to_bytes())
                    item.reply(item.key_expr, codec.encode_result(body), encoding=zenoh_wire.RESULT_ENCODING)
                except wire.CadregError as exc:
                    item.reply_err(codec.encode_result(wire.error_body(exc, "r")), encoding=zenoh_wire.ERROR_ENCODING)
                item.drop()
            else:
                device = str(item.key_expr).split("/")[3]
                parts, meta = codec.unpack_envelope(item.payload.to_bytes())
                if meta.frame_id == "drop-me":
                    continue
                try:
                    body, encoding = self._answer(site, item.payload.to_bytes()), zenoh_wire.RESULT_ENCODING
                except wire.CadregError as exc:
                    body, encoding = wire.error_body(exc, "r"), zenoh_wire.ERROR_ENCODING
                    body["detail"]["frame_id"] = meta.frame_id
                self.session.put(zenoh_wire.poses_key(site, device), codec.encode_result(body), encoding=encoding)

    def close(self) -> None:
        self.work.put(("stop", None))
        self.thread.join(5)
        self.session.close()


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    svc = FakeService(ep)
    yield ep
    svc.close()


def test_localize_over_a_query(endpoint: str) -> None:
    with ZenohClient(endpoint, timeout_s=5) as z:
        result = z.localize("demo", _frame())
        assert result["status"] == "ok" and result["frame_id"] == "f0"
        assert result["depth_sum"] == int(_frame().depth.sum())
        assert z.localize("demo", encode_frame(_frame()), frame_id="other")["frame_id"] == "other"


def test_reply_err_raises_the_typed_error(endpoint: str) -> None:
    with ZenohClient(endpoint, timeout_s=5) as z:
        with pytest.raises(cerr.UnknownSite) as info:
            z.localize("missing", _frame())
        assert info.value.request_id == "r" and info.value.status is None
        with pytest.raises(cerr.InvalidFrame):
            z.localize("demo", _frame("err"))


def test_overloaded_is_retried(endpoint: str) -> None:
    retried: list[str] = []
    with ZenohClient(endpoint, timeout_s=5, on_retry=lambda n, e, d: retried.append(e.code),
                     retry=RetryPolicy(max_retries=3, backoff_base_s=0.01)) as z:
        assert z.localize("busy", _frame())["status"] == "ok"
        assert z.retries == 2
    assert retried == ["overloaded", "overloaded"]


def test_query_timeout_is_client_timeout_not_retried(endpoint: str) -> None:
    with ZenohClient(endpoint, timeout_s=0.3) as z:
        t = time.monotonic()
        with pytest.raises(cerr.ClientTimeout):
            z.localize("slow", _frame())
        assert z.retries == 0 and time.monotonic() - t < 1.0
    time.sleep(0.8)  # let the fake finish the slow one before other tests


def test_nobody_serving_is_unreachable() -> None:
    lonely = f"tcp/127.0.0.1:{free_port()}"
    server = zenoh.open(session_config(listen=[lonely], mode="peer"))
    try:
        with ZenohClient(lonely, timeout_s=2, retry=RetryPolicy(max_retries=2, backoff_base_s=0.01)) as z:
            with pytest.raises(cerr.Unreachable):
                z.localize("demo", _frame())
            assert z.retries == 2
    finally:
        server.close()
    with pytest.raises(cerr.Unreachable):
        ZenohClient(f"tcp/127.0.0.1:{free_port()}")  # nothing listens there


def test_stream_matches_poses_by_frame_id_and_marks_lost_ones(endpoint: str) -> None:
    with ZenohClient(endpoint) as z, z.stream("demo", "robot-1", lost_after_s=1.0) as s:
        assert s.wait_ready(5.0)
        ids = ["a", "b", "drop-me", "err", "c"]
        got = {r.frame_id: r for r in s.run((_frame(i) for i in ids), rate_hz=20)}
        assert set(got) == set(ids) and s.pending == 0
        for i in ("a", "b", "c"):
            assert got[i].ok and got[i].result["frame_id"] == i and got[i].latency_ms < 1000
        assert got["drop-me"].lost and got["drop-me"].result is None and got["drop-me"].latency_ms >= 1000
        assert isinstance(got["err"].error, cerr.InvalidFrame) and not got["err"].lost
        # frames without an id get <device>-<n>
        fid = s.send(_frame(None))
        (r,) = list(s.results())
        assert r.frame_id == fid == "robot-1-0" and r.ok


def test_stream_closed_loop_keeps_a_bounded_window(endpoint: str) -> None:
    with ZenohClient(endpoint) as z, z.stream("demo", "robot-2", lost_after_s=2.0) as s:
        assert s.wait_ready(5.0)
        results = list(s.run((_frame(f"k{i}") for i in range(12)), max_in_flight=3))
        assert sorted(r.frame_id for r in results) == sorted(f"k{i}" for i in range(12))
        assert all(r.ok for r in results)


@pytest.fixture()
def raw_peer() -> Iterator[tuple[zenoh.Session, str]]:
    """A bare peer with no cadreg service on it: the test itself speaks for the service, message by message."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    peer = zenoh.open(session_config(listen=[ep], mode="peer"))
    yield peer, ep
    peer.close()


def _publisher_matched(pub, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not pub.matching_status.matching:
        time.sleep(0.02)
    return bool(pub.matching_status.matching)


def test_stream_tells_results_from_errors_by_encoding_not_by_body(raw_peer) -> None:
    peer, ep = raw_peer
    # bodies that a guess by their keys gets wrong: a result holding "code" and no "status", an error body with a
    # "status"; plus one in plain JSON, which no cadreg service sends
    result_like_error = {"frame_id": "r1", "code": "looks-like-an-error", "message": "m", "T_map_camera": None}
    error_like_result = {"code": "invalid_frame", "message": "bad depth", "request_id": "q", "status": "ok",
                         "frame_id": "not-here", "detail": {"frame_id": "e1"}}
    with ZenohClient(ep) as z, z.stream("demo", "robot-9", lost_after_s=5.0) as s:
        for fid in ("r1", "e1", "j1"):
            s.send(_frame(fid))
        pub = peer.declare_publisher(zenoh_wire.poses_key("demo", "robot-9"))
        assert _publisher_matched(pub)
        pub.put(codec.encode_result(result_like_error), encoding=zenoh_wire.RESULT_ENCODING)
        pub.put(codec.encode_result(error_like_result), encoding=zenoh_wire.ERROR_ENCODING)
        pub.put(codec.encode_result({"status": "ok", "frame_id": "j1"}), encoding=zenoh.Encoding.APPLICATION_JSON)
        got: dict[str, object] = {}
        end = time.monotonic() + 5.0
        while len(got) < 2 and time.monotonic() < end:
            got.update({r.frame_id: r for r in s.poll(timeout_s=0.1)})
        assert got["r1"].ok and got["r1"].error is None and got["r1"].result == result_like_error
        assert isinstance(got["e1"].error, cerr.InvalidFrame) and got["e1"].result is None
        assert got["e1"].error.request_id == "q"
        time.sleep(0.2)
        assert not s.poll() and s.foreign == 1 and s.pending == 1  # the plain JSON one answers nothing
        pub.undeclare()


def test_query_reply_kind_comes_from_its_encoding(raw_peer) -> None:
    peer, ep = raw_peer
    error_shaped = {"code": "unknown_site", "message": "m", "request_id": "r", "detail": {}}
    answers = {  # site -> (reply or reply_err, body, encoding)
        "result-with-code": ("ok", error_shaped, zenoh_wire.RESULT_ENCODING),
        "plain-json-ok": ("ok", {"status": "ok"}, zenoh.Encoding.APPLICATION_JSON),
        "plain-json-err": ("err", error_shaped, zenoh.Encoding.APPLICATION_JSON),
        "error": ("err", error_shaped, zenoh_wire.ERROR_ENCODING),
    }
    queries: queue.SimpleQueue = queue.SimpleQueue()
    queryable = peer.declare_queryable("cadreg/*/localize", queries.put)

    def serve() -> None:
        while (query := queries.get()) is not None:
            how, body, encoding = answers[zenoh_wire.parse_key(query.key_expr).site_id]
            if how == "ok":
                query.reply(query.key_expr, codec.encode_result(body), encoding=encoding)
            else:
                query.reply_err(codec.encode_result(body), encoding=encoding)
            query.drop()

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    try:
        with ZenohClient(ep, timeout_s=5, retry=RetryPolicy(max_retries=0)) as z:
            payload = encode_frame(_frame()).envelope()
            assert z.localize_envelope("result-with-code", payload) == error_shaped
            with pytest.raises(cerr.UnknownSite):
                z.localize_envelope("error", payload)
            for site in ("plain-json-ok", "plain-json-err"):
                with pytest.raises(cerr.BadResponse, match="no cadreg answer"):
                    z.localize_envelope(site, payload)
    finally:
        queries.put(None)
        server.join(5)
        queryable.undeclare()


def test_a_second_queryable_that_answers_otherwise_is_caught_and_one_that_agrees_passes(endpoint: str) -> None:
    """zenoh authenticates nobody: a peer's queryable on the service's key that answered after it had its forged
    pose taken (the default consolidation keeps the latest reply). Every reply is read now; replies that disagree
    raise BadResponse, and a replica that answers alike (the same status and pose) is no conflict."""
    rogue = zenoh.open(session_config(connect=[endpoint], mode="peer"))
    forged = {"status": "ok", "frame_id": "f0", "T_map_camera": [[1, 0, 0, 666], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                   [0, 0, 0, 1]]}
    agree = {"status": "ok", "frame_id": "f0", "T_map_camera": np.eye(4).tolist()}
    answer = {"with": forged}

    def later(query) -> None:
        def reply() -> None:
            time.sleep(0.3)  # after the service's reply
            query.reply(query.key_expr, codec.encode_result(answer["with"]), encoding=zenoh_wire.RESULT_ENCODING)
            query.drop()
        threading.Thread(target=reply, daemon=True).start()

    queryable = rogue.declare_queryable("cadreg/demo/localize", later)
    try:
        time.sleep(0.5)  # let the peers meet
        with ZenohClient(endpoint, timeout_s=5) as z:
            with pytest.raises(cerr.BadResponse, match="2 queryables on cadreg/demo/localize answered, and not alike"):
                z.query_once("demo", encode_frame(_frame()).envelope())
            answer["with"] = agree
            assert z.query_once("demo", encode_frame(_frame()).envelope())["T_map_camera"] == np.eye(4).tolist()
    finally:
        queryable.undeclare()
        rogue.close()
