"""The zenoh wire contract (service/zenoh_wire.py): keys build and parse back, junk keys are refused, the session
config keeps scouting off unless asked, and results and error bodies carry encodings that tell them apart."""

from __future__ import annotations

import json

import pytest
import zenoh

from service import zenoh_wire as wire


@pytest.mark.parametrize(
    "key, expected",
    [
        (wire.localize_key("scene0470"), wire.WireKey("localize", "scene0470")),
        (wire.frames_key("scene0470", "robot-1"), wire.WireKey("frames", "scene0470", "robot-1")),
        (wire.poses_key("site_2", "cam.7"), wire.WireKey("poses", "site_2", "cam.7")),
    ],
)
def test_keys_build_and_parse_back(key: str, expected: wire.WireKey) -> None:
    assert wire.parse_key(key) == expected
    assert str(expected) == key
    assert wire.parse_key(zenoh.KeyExpr(key)) == expected  # what a sample or query carries


def test_key_spelling_is_the_contract() -> None:
    assert wire.localize_key("s") == "cadreg/s/localize"
    assert wire.frames_key("s", "d") == "cadreg/s/frames/d"
    assert wire.poses_key("s", "d") == "cadreg/s/poses/d"
    # the service's wildcards match exactly the concrete keys of their kind
    assert zenoh.KeyExpr(wire.QUERY_KEYS).intersects(zenoh.KeyExpr(wire.localize_key("s")))
    assert zenoh.KeyExpr(wire.FRAMES_KEYS).intersects(zenoh.KeyExpr(wire.frames_key("s", "d")))
    assert not zenoh.KeyExpr(wire.FRAMES_KEYS).intersects(zenoh.KeyExpr(wire.poses_key("s", "d")))


@pytest.mark.parametrize(
    "key",
    [
        "",
        "cadreg",
        "cadreg/s",
        "other/s/localize",
        "cadreg/s/localise",
        "cadreg/s/localize/extra",
        "cadreg/s/frames",
        "cadreg/s/frames/d/extra",
        "cadreg/s/unknown/d",
        "cadreg/*/localize",
        "cadreg/**",
        "cadreg/s/frames/*",
        "cadreg/$*/poses/d",
        "cadreg//localize",
    ],
)
def test_junk_keys_are_refused(key: str) -> None:
    with pytest.raises(ValueError):
        wire.parse_key(key)


@pytest.mark.parametrize("bad", ["", "a/b", "*", "a*", "$x", "a#b", "a?b", "a b", "@x", "@"])
def test_ids_that_are_not_one_chunk_are_refused(bad: str) -> None:
    with pytest.raises(ValueError, match="site id"):
        wire.localize_key(bad)
    with pytest.raises(ValueError, match="device id"):
        wire.poses_key("s", bad)
    with pytest.raises(ValueError, match="device id"):
        wire.frames_key("s", bad)


def _config(config: zenoh.Config, key: str):
    return json.loads(config.get_json(key))


def test_session_config_has_scouting_off_and_only_the_given_endpoints() -> None:
    config = wire.session_config(mode="peer", listen=["tcp/127.0.0.1:7001"], connect=["tcp/127.0.0.1:7002"])
    assert _config(config, "mode") == "peer"
    assert _config(config, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _config(config, "connect/endpoints") == ["tcp/127.0.0.1:7002"]
    assert _config(config, "scouting/multicast/enabled") is False
    assert _config(config, "scouting/gossip/enabled") is False
    # a bare Config leaves it unset, i.e. zenoh's default, which scouts by multicast: the builder turns it off
    assert _config(zenoh.Config(), "scouting/multicast/enabled") is None
    plain = wire.session_config()
    assert _config(plain, "mode") == "client" and _config(plain, "listen/endpoints") == []
    assert _config(plain, "scouting/multicast/enabled") is False
    asked = wire.session_config(multicast_scouting=True, gossip_scouting=True)
    assert _config(asked, "scouting/multicast/enabled") is True and _config(asked, "scouting/gossip/enabled") is True


def test_result_and_error_encodings_differ_and_are_recognised() -> None:
    assert wire.RESULT_ENCODING != wire.ERROR_ENCODING
    assert wire.body_kind(wire.RESULT_ENCODING) == "result"
    assert wire.body_kind(wire.ERROR_ENCODING) == "error"
    # as zenoh hands them back (an Encoding, not a str)
    assert wire.body_kind(zenoh.Encoding(wire.RESULT_ENCODING)) == "result"
    assert wire.body_kind(zenoh.Encoding(wire.ERROR_ENCODING)) == "error"
    # plain JSON, zenoh's default and zenoh's own error replies are no cadreg answer
    for other in (zenoh.Encoding.APPLICATION_JSON, zenoh.Encoding.ZENOH_BYTES, wire.ENVELOPE_ENCODING, None):
        assert wire.body_kind(other) is None


def test_stream_bodies_echo_the_frame_id_where_the_receiver_looks() -> None:
    result = wire.stamp_stream_body({"status": "ok", "frame_id": "from-the-worker"}, "result", "f1", "cam")
    assert result["frame_id"] == "f1" and result["device_id"] == "cam"
    assert wire.stream_frame_id(result, "result") == "f1"
    error = wire.stamp_stream_body({"code": "invalid_frame", "message": "m", "request_id": "r", "detail": {}},
                                   "error", "f2", "cam")
    assert set(error) == {"code", "message", "request_id", "detail"}  # the error body's keys stay the contract's
    assert error["detail"] == {"frame_id": "f2", "device_id": "cam"}
    assert wire.stream_frame_id(error, "error") == "f2"
    assert wire.stream_frame_id({"code": "x"}, "error") is None
