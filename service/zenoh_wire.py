"""The zenoh wire contract, one module for the service's zenoh front end and the zenoh client (DESIGN §6).

Key expressions (`<site_id>` and `<device_id>` are single chunks: no '/', no wildcard or reserved character):
    cadreg/<site_id>/localize              queryable; query payload = frame envelope (service/codec.py)
    cadreg/<site_id>/frames/<device_id>    stream input, published by a device, payload = frame envelope
    cadreg/<site_id>/poses/<device_id>     stream output, one message per frame answered

Encodings tell a result from an error body without looking inside it (both are JSON objects, service/codec.py):
    RESULT_ENCODING    application/json;cadreg-result   query reply (ok) and pose message with the result
    ERROR_ENCODING     application/json;cadreg-error    reply_err and pose message with the error body
                                                        {code, message, request_id, detail}
    ENVELOPE_ENCODING  application/octet-stream;cadreg-frame   what clients label a frame with; the service reads a
                                                        frame by its magic bytes, so a sender that sets none is served
The frame id of a stream answer is echoed at `frame_id` in a result and at `detail.frame_id` in an error body
(`stamp_stream_body`, `stream_frame_id`).

Sessions: `session_config` spells the zenoh settings once (DESIGN §9: mode, listen and connect endpoints; multicast
and gossip scouting off unless asked for, since a zenoh peer otherwise scouts the whole LAN).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Literal, Sequence

import zenoh

PREFIX = "cadreg"
LOCALIZE = "localize"
FRAMES = "frames"
POSES = "poses"
# what the service declares: every site's queryable, every device's frames
QUERY_KEYS = f"{PREFIX}/*/{LOCALIZE}"
FRAMES_KEYS = f"{PREFIX}/*/{FRAMES}/*"

RESULT_ENCODING = "application/json;cadreg-result"
ERROR_ENCODING = "application/json;cadreg-error"
ENVELOPE_ENCODING = "application/octet-stream;cadreg-frame"

BodyKind = Literal["result", "error"]
KeyKind = Literal["localize", "frames", "poses"]

# '*' and '$' are zenoh wildcards / reserved, '#' and '?' are reserved by key expressions and selectors, '/' would
# split the chunk, and a space is nothing a site or device id should hold
_BAD_CHUNK_CHARS = frozenset("*$#?/ ")
# a chunk that starts with '@' is verbatim in zenoh: only the same chunk matches it, never the service's '*', so a key
# holding one reaches no cadreg queryable or subscriber (the query would time out with no reply)
_VERBATIM = "@"


@dataclass(frozen=True)
class WireKey:
    """A parsed cadreg key: kind, site id and (for frames/poses) device id."""

    kind: KeyKind
    site_id: str
    device_id: str | None = None

    def __str__(self) -> str:
        if self.kind == LOCALIZE:
            return localize_key(self.site_id)
        return _device_key(self.kind, self.site_id, self.device_id or "")


def _chunk(value: str, what: str) -> str:
    if not isinstance(value, str) or not value or _BAD_CHUNK_CHARS & set(value) or value.startswith(_VERBATIM):
        raise ValueError(f"{what} {value!r} cannot be part of a zenoh key "
                         "(no empty, '*', '$', '#', '?', '/', ' ', no leading '@')")
    return value


def localize_key(site_id: str) -> str:
    """`cadreg/<site_id>/localize`; ValueError for a site id that is not one key chunk."""
    return f"{PREFIX}/{_chunk(site_id, 'site id')}/{LOCALIZE}"


def _device_key(kind: str, site_id: str, device_id: str) -> str:
    return f"{PREFIX}/{_chunk(site_id, 'site id')}/{kind}/{_chunk(device_id, 'device id')}"


def frames_key(site_id: str, device_id: str) -> str:
    """`cadreg/<site_id>/frames/<device_id>`; ValueError for ids that are not one key chunk each."""
    return _device_key(FRAMES, site_id, device_id)


def poses_key(site_id: str, device_id: str) -> str:
    """`cadreg/<site_id>/poses/<device_id>`; ValueError for ids that are not one key chunk each."""
    return _device_key(POSES, site_id, device_id)


def parse_key(key: str | zenoh.KeyExpr) -> WireKey:
    """The kind, site and device of a concrete cadreg key; ValueError for anything else (another prefix, a wildcard,
    a wrong number of chunks, an unknown kind)."""
    text = str(key)
    chunks = text.split("/")
    if len(chunks) < 3 or chunks[0] != PREFIX:
        raise ValueError(f"{text!r} is not a cadreg key (cadreg/<site>/localize|frames/<device>|poses/<device>)")
    site_id = _chunk(chunks[1], "site id")
    if len(chunks) == 3 and chunks[2] == LOCALIZE:
        return WireKey(LOCALIZE, site_id)
    if len(chunks) == 4 and chunks[2] in (FRAMES, POSES):
        return WireKey(chunks[2], site_id, _chunk(chunks[3], "device id"))
    raise ValueError(f"{text!r} is not a cadreg key (cadreg/<site>/localize|frames/<device>|poses/<device>)")


def session_config(
    *,
    mode: str = "client",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    gossip_scouting: bool = False,
) -> zenoh.Config:
    """A zenoh Config with only the given endpoints; scouting (multicast, gossip) off unless asked for."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    config.insert_json5("scouting/gossip/enabled", json.dumps(bool(gossip_scouting)))
    return config


def body_kind(encoding: zenoh.Encoding | str | None) -> BodyKind | None:
    """"result" or "error" for a sample or reply of that encoding; None for anything else (not ours, or zenoh's own
    error replies such as the query timeout)."""
    text = None if encoding is None else str(encoding)
    if text == RESULT_ENCODING:
        return "result"
    if text == ERROR_ENCODING:
        return "error"
    return None


def stamp_stream_body(body: dict[str, Any], kind: BodyKind, frame_id: str | None, device_id: str) -> dict[str, Any]:
    """Echo the frame id and device id in a pose message: at the top of a result, in `detail` of an error body
    (whose top-level keys are fixed: code, message, request_id, detail). Changes and returns `body`."""
    target = body if kind == "result" else body.setdefault("detail", {})
    target["frame_id"] = frame_id
    target["device_id"] = device_id
    return body


def stream_frame_id(body: dict[str, Any], kind: BodyKind) -> Any:
    """The echoed frame id of a pose message (where `stamp_stream_body` put it), None when it has none."""
    target = body if kind == "result" else body.get("detail")
    return target.get("frame_id") if isinstance(target, dict) else None
