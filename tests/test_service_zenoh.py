"""The zenoh front end: a real service (uvicorn + zenoh peer on tcp/127.0.0.1:<free port>, scouting off) and a real
client session; query mode gives the library's pose, errors arrive through reply_err with the one error body, and
stream mode echoes frame ids and drops the oldest frames of a device that outruns the pool."""

from __future__ import annotations

import json
import struct
import threading
import time
from pathlib import Path

import httpx
import pytest
import zenoh

from service import codec, zenoh_wire
from service.settings import Settings
from service.worker import SLEEP_HOOK_PREFIX
from service.zenoh_server import zenoh_config
from test_service_support import (LiveServer, free_port, free_ports, library_results, load_frames, pose_error,
                                  render_frames)

SITE = "scene0470"


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("zframes"), n=4))


@pytest.fixture(scope="module")
def server(scene0470_site_dir: Path):
    port, zport = free_ports(2)
    settings = Settings(
        sites_dir=scene0470_site_dir.parent,
        port=port,
        workers=1,
        queue_depth=1,
        request_timeout_s=20,
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        stream_queue_per_device=2,
        test_hooks=True,
    )
    live = LiveServer(settings)
    live.zenoh_endpoint = f"tcp/127.0.0.1:{zport}"
    yield live
    live.stop()


@pytest.fixture(scope="module")
def session(server):
    config = zenoh_config(Settings(zenoh_mode="peer", zenoh_listen=[], zenoh_connect=[server.zenoh_endpoint]))
    s = zenoh.open(config)
    time.sleep(0.5)  # let the peers meet
    yield s
    s.close()


def _query(session, site: str, payload: bytes, timeout_s: float = 30.0) -> tuple[bool, dict, str]:
    replies = list(session.get(f"cadreg/{site}/localize", payload=payload, timeout=timeout_s))
    assert len(replies) == 1, replies
    reply = replies[0]
    if reply.ok is not None:
        return True, codec.decode_result(reply.ok.payload.to_bytes()), str(reply.ok.encoding)
    return False, codec.decode_result(reply.err.payload.to_bytes()), str(reply.err.encoding)


def _envelope(frame, parts_override: dict | None = None, **meta_override) -> bytes:
    """An envelope laid out by hand (not by pack_envelope, which refuses bad meta): magic, version, length,
    header, parts."""
    parts, meta = codec.encode_frame_parts(frame)
    parts.update(parts_override or {})
    doc = meta.model_dump(mode="json")
    doc.update(meta_override)
    spans, blobs, pos = {}, [], 0
    for name, data in parts.items():
        spans[name] = [pos, len(data)]
        blobs.append(data)
        pos += len(data)
    header = json.dumps({"meta": doc, "parts": spans}).encode()
    return b"CDRG" + bytes([1]) + struct.pack("<I", len(header)) + header + b"".join(blobs)


def test_hand_made_envelope_matches_the_codec(frames) -> None:
    frame = frames[0][0]
    parts, meta = codec.encode_frame_parts(frame)
    assert codec.unpack_envelope(_envelope(frame)) == codec.unpack_envelope(codec.pack_envelope(parts, meta))


def test_query_gives_the_library_pose(server, session, frames, scene0470_site_dir) -> None:
    expected = library_results(scene0470_site_dir, frames)
    for (frame, _), ref in zip(frames, expected):
        ok, body, encoding = _query(session, SITE, _envelope(frame))
        assert ok, body
        assert encoding == zenoh_wire.RESULT_ENCODING
        assert body["status"] == ref["status"] and body["frame_id"] == frame.frame_id
        assert body["site_id"] == SITE and body["site_version"] and body["request_id"]
        if ref["T_map_camera"] is not None:
            dt, dr = pose_error(body["T_map_camera"], ref["T_map_camera"])
            assert dt < 0.01 and dr < 1.0, (dt, dr)


@pytest.mark.parametrize(
    "make, site, code",
    [
        (lambda f: b"not an envelope", SITE, "invalid_frame"),
        (lambda f: _envelope(f, depth_scale=-1), SITE, "invalid_frame"),
        (lambda f: _envelope(f, unknown_key=1), SITE, "invalid_frame"),
        (lambda f: _envelope(f)[:-100], SITE, "invalid_frame"),
        (lambda f: _envelope(f), "atlantis", "unknown_site"),
    ],
)
def test_query_errors_come_back_through_reply_err(session, frames, make, site, code) -> None:
    ok, body, encoding = _query(session, site, make(frames[0][0]))
    assert not ok
    assert body["code"] == code and set(body) == {"code", "message", "request_id", "detail"}
    assert encoding == zenoh_wire.ERROR_ENCODING
    # and the next good query is answered normally
    ok, body, _ = _query(session, SITE, _envelope(frames[1][0]))
    assert ok and body["status"] in ("ok", "ambiguous")


def test_stream_mode_echoes_frame_ids_and_drops_the_oldest(server, session, frames) -> None:
    received: list[dict] = []
    encodings: list[str] = []
    done = threading.Event()

    def on_pose(sample) -> None:  # enqueue only: no zenoh calls in a callback
        received.append(codec.decode_result(sample.payload.to_bytes()))
        encodings.append(str(sample.encoding))
        if len(received) >= 2 and received[-1].get("frame_id") == "last":
            done.set()

    sub = session.declare_subscriber(f"cadreg/{SITE}/poses/cam-1", on_pose)
    # blocking: the frames dropped must be the service's choice (its queue of 2), not zenoh's full send queue
    pub = session.declare_publisher(f"cadreg/{SITE}/frames/cam-1", congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.3)
    # the first frame holds the only worker for a while; the device keeps sending, faster than the pool can go
    frame = frames[0][0]
    burst = [_envelope(frame, frame_id=f"burst-{i}") for i in range(6)] + [_envelope(frame, frame_id="last")]
    pub.put(_envelope(frame, frame_id=f"{SLEEP_HOOK_PREFIX}1.5"))
    time.sleep(0.3)
    for payload in burst:
        pub.put(payload)
    assert done.wait(60), [r.get("frame_id") for r in received]
    ids = [r.get("frame_id") for r in received]
    # queue of 2 per device: the sleeping frame, then only the newest two survive
    assert ids[0] == f"{SLEEP_HOOK_PREFIX}1.5"
    assert ids[-1] == "last" and len(ids) <= 3, ids
    assert all(r["status"] in ("ok", "ambiguous") and r["device_id"] == "cam-1" for r in received), [(r.get("frame_id"), r["status"], r.get("diagnostics", {}).get("notes")) for r in received]
    assert encodings == [zenoh_wire.RESULT_ENCODING] * len(received)
    metrics = httpx.get(server.url + "/metrics").text
    dropped = [line for line in metrics.splitlines() if line.startswith('cadreg_zenoh_dropped_frames_total{site="scene0470"}')]
    assert dropped and float(dropped[0].split()[-1]) >= 5 - 1, dropped
    sub.undeclare()
    pub.undeclare()


def test_stream_errors_are_published_with_the_frame_id(session, frames) -> None:
    received: list[dict] = []
    encodings: list[str] = []
    got = threading.Event()

    def on_pose(sample) -> None:
        received.append(json.loads(sample.payload.to_bytes()))
        encodings.append(str(sample.encoding))
        got.set()

    sub = session.declare_subscriber(f"cadreg/{SITE}/poses/cam-2", on_pose)
    time.sleep(0.3)
    session.put(f"cadreg/{SITE}/frames/cam-2", _envelope(frames[0][0], {"depth": b"junk"}, frame_id="bad-1"))
    assert got.wait(30)
    body = received[0]
    assert body["code"] == "invalid_frame" and "depth" in body["message"]
    assert body["detail"]["frame_id"] == "bad-1" and body["detail"]["device_id"] == "cam-2"
    # a payload that is no envelope at all fails before the pool; its error is published all the same
    got.clear()
    session.put(f"cadreg/{SITE}/frames/cam-2", b"not an envelope")
    assert got.wait(30)
    assert received[1]["code"] == "invalid_frame" and received[1]["detail"]["device_id"] == "cam-2"
    assert encodings == [zenoh_wire.ERROR_ENCODING] * 2
    sub.undeclare()


def test_a_wildcard_query_is_told_it_names_no_site(session, frames) -> None:
    # cadreg/*/localize matches the service's queryable too; it must get an answer, not silence or a crash
    ok, body, encoding = _query(session, "*", _envelope(frames[0][0]))
    assert not ok and encoding == zenoh_wire.ERROR_ENCODING
    assert body["code"] == "unknown_site" and body["detail"]["key"] == "cadreg/*/localize"
    ok, body, _ = _query(session, SITE, _envelope(frames[1][0]))
    assert ok and body["status"] in ("ok", "ambiguous")


def test_a_second_front_end_drains_zenoh_channels_on_its_own_threads_and_stops(server) -> None:
    """No callback of ours on zenoh's threads: queries and frames wait in zenoh's FIFO channels until our threads
    take them; stop() undeclares, which ends those threads, and closes the session."""
    from service.zenoh_server import ZenohServer

    zport = free_port()
    settings = server.settings.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{zport}"]})
    front = ZenohServer(server.service, settings)
    front.start()
    peer = zenoh.open(zenoh_config(Settings(zenoh_mode="peer", zenoh_listen=[],
                                            zenoh_connect=[f"tcp/127.0.0.1:{zport}"])))
    try:
        assert isinstance(front._queryable.handler, zenoh.handlers.Handler)  # noqa: SLF001
        assert isinstance(front._subscriber.handler, zenoh.handlers.Handler)  # noqa: SLF001
        names = sorted(t.name for t in front._threads if t.is_alive())  # noqa: SLF001
        assert names == ["cadreg-zenoh-frames", "cadreg-zenoh-queries", "cadreg-zenoh-replies", "cadreg-zenoh-streams"]
        time.sleep(0.5)  # let the peers meet
        ok, body, encoding = _query(peer, SITE, b"not an envelope")
        assert not ok and body["code"] == "invalid_frame" and encoding == zenoh_wire.ERROR_ENCODING
        front.stop()
        assert not any(t.is_alive() for t in front._threads)  # noqa: SLF001
        assert front.session.is_closed()
        assert list(peer.get(zenoh_wire.localize_key(SITE), payload=b"x", timeout=1.0)) == []
    finally:
        if not front.session.is_closed():
            front.stop()
        peer.close()
