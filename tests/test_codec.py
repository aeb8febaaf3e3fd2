"""The wire codec and the error table: round trips, every malformed input refused by InvalidFrame, a total table."""

from __future__ import annotations

import io
import json
import math
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

import cadreg.errors as core_errors
from cadreg.camera import CameraIntrinsics
from cadreg.errors import CadregError, InvalidFrame
from cadreg.frame import Frame
from service import codec
from service import errors as wire_errors
from service.schemas import ErrorBody, FrameMeta


def _frame(labels_dtype=np.uint16, color_size=(64, 48), rng_seed=0) -> Frame:
    rng = np.random.default_rng(rng_seed)
    depth = rng.integers(500, 4000, size=(30, 40), dtype=np.uint16)
    depth[0, :5] = 0
    cw, ch = color_size
    color = rng.integers(0, 256, size=(ch, cw, 3), dtype=np.uint8)
    labels = rng.integers(0, 41, size=(ch, cw)).astype(labels_dtype)
    T = np.eye(4)
    T[:3, 3] = [0.025, -0.01, 0.0]
    prior = np.eye(4)
    prior[:3, 3] = [1.0, 2.0, 0.5]
    return Frame(
        depth=depth,
        color=color,
        depth_intrinsics=CameraIntrinsics(40, 30, 35.0, 35.5, 19.5, 14.5),
        color_intrinsics=CameraIntrinsics(cw, ch, 57.0, 57.5, 31.5, 23.5),
        T_color_depth=T,
        depth_scale=1000.0,
        labels=labels,
        gravity_camera=np.array([0.0, 1.0, 0.0]),
        T_map_camera_prior=prior,
        frame_id="f-7",
        depth_range_m=4.5,
    )


def _png(array: np.ndarray, **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array, **kw).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize("labels_dtype", [np.uint8, np.uint16])
def test_frame_round_trip_through_envelope(labels_dtype) -> None:
    frame = _frame(labels_dtype)
    parts, meta = codec.encode_frame_parts(frame, top_k=3)
    assert set(parts) == {"color", "depth", "labels"}
    assert meta.top_k == 3
    payload = codec.pack_envelope(parts, meta)
    assert payload[:4] == b"CDRG" and payload[4] == 1
    header_len = struct.unpack_from("<I", payload, 5)[0]
    header = json.loads(payload[9 : 9 + header_len])
    assert set(header) == {"meta", "parts"}
    # offsets are relative to the end of the header and the parts follow in order
    body = payload[9 + header_len :]
    off, length = header["parts"]["depth"]
    assert body[off : off + length] == parts["depth"]

    parts2, meta2 = codec.unpack_envelope(payload)
    assert parts2 == parts and meta2 == meta
    back = codec.decode_frame(parts2, meta2)
    np.testing.assert_array_equal(back.depth, frame.depth)
    np.testing.assert_array_equal(back.color, frame.color)
    np.testing.assert_array_equal(back.labels, frame.labels)
    assert back.labels.dtype == labels_dtype
    assert back.depth_intrinsics == frame.depth_intrinsics
    assert back.color_intrinsics == frame.color_intrinsics
    np.testing.assert_allclose(back.T_color_depth, frame.T_color_depth)
    np.testing.assert_allclose(back.T_map_camera_prior, frame.T_map_camera_prior)
    np.testing.assert_allclose(back.gravity_camera, frame.gravity_camera)
    assert back.frame_id == "f-7"
    assert back.depth_range_m == 4.5


def test_same_camera_defaults_and_jpeg_color() -> None:
    rng = np.random.default_rng(1)
    depth = rng.integers(500, 4000, size=(30, 40), dtype=np.uint16)
    color = rng.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(color).save(buf, format="JPEG", quality=95)
    meta = {"depth_intrinsics": {"fx": 35.0, "fy": 35.0, "cx": 19.5, "cy": 14.5}}
    frame = codec.decode_frame({"color": buf.getvalue(), "depth": _png(depth)}, json.dumps(meta))
    assert frame.color.shape == (30, 40, 3) and frame.color.dtype == np.uint8
    assert frame.color_intrinsics == frame.depth_intrinsics
    np.testing.assert_array_equal(frame.T_color_depth, np.eye(4))
    assert frame.labels is None and frame.depth_scale == 1000.0 and frame.label_set == "nyu40"
    assert frame.depth_range_m is None


GOOD_META = {"depth_intrinsics": {"fx": 35.0, "fy": 35.0, "cx": 19.5, "cy": 14.5}}


def _good_parts() -> dict[str, bytes]:
    rng = np.random.default_rng(2)
    return {
        "color": _png(rng.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)),
        "depth": _png(rng.integers(500, 4000, size=(30, 40), dtype=np.uint16)),
        "labels": _png(rng.integers(0, 40, size=(30, 40), dtype=np.uint8)),
    }


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda p, m: p.update(color=b"\x89PNG\r\n\x1a\nnot really"), "color"),
        (lambda p, m: p.update(depth=p["depth"][: len(p["depth"]) // 2]), "depth"),
        (lambda p, m: p.update(depth=_png(np.full((30, 40), 7, np.uint8))), "16-bit"),
        (lambda p, m: p.update(depth=_png(np.zeros((30, 40), np.uint16))), "all zero"),
        (lambda p, m: p.update(depth=_png(np.ones((20, 40), np.uint16))), "color_intrinsics"),
        (lambda p, m: p.update(labels=_png(np.ones((30, 41), np.uint8))), "labels"),
        (lambda p, m: p.pop("depth"), "missing part: depth"),
        (lambda p, m: p.update(extra=b"x"), "unknown part"),
        (lambda p, m: m["depth_intrinsics"].update(fx=-1.0), "fx"),
        (lambda p, m: m["depth_intrinsics"].update(fy=float("nan")), "fy"),
        (lambda p, m: m["depth_intrinsics"].update(cx=1e9), "principal point"),
        (lambda p, m: m.update(bogus=1), "bogus"),
        (lambda p, m: m.update(top_k=0), "top_k"),
        (lambda p, m: m.update(depth_scale=0), "depth_scale"),
        (lambda p, m: m.update(T_color_depth=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "4x4"),
        (lambda p, m: m.update(T_color_depth=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "rigid"),
        (lambda p, m: m.update(gravity=[0, 0, 0]), "gravity"),
        (lambda p, m: m.update(depth_range_m=0), "depth_range_m"),
        (lambda p, m: m.update(depth_range_m=-4.0), "depth_range_m"),
        (lambda p, m: m.update(depth_range_m="4"), "depth_range_m"),
    ],
)
def test_bad_frames_raise_invalid_frame(mutate, needle) -> None:
    parts, meta = _good_parts(), json.loads(json.dumps(GOOD_META))
    codec.decode_frame(dict(parts), dict(meta))  # the unmutated frame is fine
    mutate(parts, meta)
    with pytest.raises(InvalidFrame) as info:
        codec.decode_frame(parts, meta)
    assert needle in info.value.message


def test_meta_json_nan_is_refused() -> None:
    # Python's json accepts NaN literals; the schema must not
    text = '{"depth_intrinsics": {"fx": NaN, "fy": 35, "cx": 19.5, "cy": 14.5}}'
    with pytest.raises(InvalidFrame):
        codec.parse_meta(text)
    with pytest.raises(InvalidFrame, match="not valid JSON"):
        codec.parse_meta("{not json")


@pytest.mark.parametrize(
    "payload, needle",
    [
        (b"CDR", "too short"),
        (b"XXXX\x01" + struct.pack("<I", 2) + b"{}", "magic"),
        (b"CDRG\x02" + struct.pack("<I", 2) + b"{}", "version"),
        (b"CDRG\x01" + struct.pack("<I", 999) + b"{}", "length"),
        (b"CDRG\x01" + struct.pack("<I", 3) + b"{x}", "JSON"),
        (b"CDRG\x01" + struct.pack("<I", 2) + b"{}", "header must be"),
    ],
)
def test_malformed_envelopes(payload, needle) -> None:
    with pytest.raises(InvalidFrame) as info:
        codec.unpack_envelope(payload)
    assert needle in info.value.message


def test_envelope_part_outside_payload() -> None:
    parts = _good_parts()
    payload = bytearray(codec.pack_envelope(parts, GOOD_META))
    with pytest.raises(InvalidFrame, match="outside"):
        codec.unpack_envelope(bytes(payload[:-10]))


def test_result_codec_replaces_non_finite() -> None:
    body = {"status": "ok", "confidence": float("nan"), "cov": [[float("inf"), 1.0]], "n": np.int64(3)}
    back = codec.decode_result(codec.encode_result(body))
    assert back == {"status": "ok", "confidence": None, "cov": [[None, 1.0]], "n": 3}
    with pytest.raises(CadregError):
        codec.decode_result(b"[1, 2]")


def _all_error_classes() -> set[type]:
    """The service's error tree: classes of cadreg/ and service/ (the clients' mirror classes, which derive from
    them and may or may not be imported by the time this runs, are checked in test_clients_errors.py)."""
    seen: set[type] = set()
    todo = [core_errors.CadregError]
    while todo:
        cls = todo.pop()
        if cls not in seen:
            seen.add(cls)
            todo.extend(cls.__subclasses__())
    return {c for c in seen if c.__module__.split(".")[0] in ("cadreg", "service")}


def test_error_table_is_total_and_consistent() -> None:
    classes = _all_error_classes()
    assert wire_errors.Unauthorized in classes
    expected = {
        "invalid_frame": 422, "invalid_input": 422, "invalid_file": 422, "invalid_config": 422,
        "bundle_integrity": 422, "unknown_site": 404, "payload_too_large": 413, "overloaded": 503,
        "worker_crashed": 503, "timeout": 504, "unauthorized": 401, "body_timeout": 408, "client_disconnected": 499,
        "internal": 500,
    }
    for cls in classes:
        spec = wire_errors.spec_for(cls)
        assert spec.code == cls.code, f"{cls.__name__}: table says {spec.code}, class says {cls.code}"
        assert expected[spec.code] == spec.status, cls.__name__
    assert {s.code for s in wire_errors.ERROR_TABLE.values()} == set(expected)
    assert wire_errors.spec_for(RuntimeError("boom")).status == 500
    # Retry-After exactly for the retryable codes
    assert {s.code for s in wire_errors.ERROR_TABLE.values() if s.retry_after} == {"overloaded", "worker_crashed"}


@pytest.mark.parametrize("cls", sorted(_all_error_classes(), key=lambda c: c.__name__))
def test_error_body_round_trips_to_the_same_class(cls) -> None:
    if cls is core_errors.InvalidFileError or cls is core_errors.BundleIntegrityError:
        exc = cls("/sites/x/site.json", "sha256 mismatch")
    elif cls is core_errors.Overloaded:
        exc = cls("queue full", retry_after_s=2.5)
    else:
        exc = cls("something")
    body = wire_errors.error_body(exc, request_id="rid-1")
    ErrorBody.model_validate(body)
    assert set(body) == {"code", "message", "request_id", "detail"}
    assert body["code"] == cls.code and body["request_id"] == "rid-1"
    again = wire_errors.error_from_body(json.loads(json.dumps(body)))
    assert again.code == cls.code
    assert wire_errors.spec_for(again) == wire_errors.spec_for(exc)
    if cls is core_errors.Overloaded:
        assert again.retry_after_s == 2.5
        assert wire_errors.http_headers(exc)["Retry-After"] == "3"


def test_foreign_errors_do_not_leak_text() -> None:
    body = wire_errors.error_body(KeyError("/secret/path"), request_id=None)
    assert body["code"] == "internal" and "secret" not in json.dumps(body)


def test_error_from_body_keeps_unknown_codes() -> None:
    exc = wire_errors.error_from_body({"code": "teapot", "message": "short and stout"})
    assert type(exc) is CadregError and exc.code == "teapot"


def test_frame_meta_schema_forbids_extra_and_bounds() -> None:
    schema = FrameMeta.model_json_schema()
    assert schema.get("additionalProperties") is False
    m = FrameMeta.model_validate(GOOD_META)
    assert m.top_k is None and m.depth_scale == 1000 and m.label_set == "nyu40"  # None: the configured default
    assert math.isclose(m.depth_intrinsics.fx, 35.0)


def test_meta_nesting_and_size_are_bounded_before_parsing() -> None:
    """Issue 14: 100,000 levels made json.loads raise RecursionError (a 500); HTTP and the zenoh envelope alike."""
    with pytest.raises(InvalidFrame, match="65536-byte limit"):
        codec.parse_meta("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InvalidFrame, match="32-level limit"):
        codec.parse_meta('{"gravity": ' + "[" * 33 + "]" * 33 + "}")
    # brackets inside strings are not nesting
    codec.check_json_bounds('{"a": "' + "[" * 1000 + '\\" [[["}', "meta", codec.MAX_META_BYTES, codec.MAX_META_DEPTH)
    header = b'{"parts": {}, "meta": ' + b"[" * 50_000 + b"]" * 50_000 + b"}"
    payload = codec._PREFIX.pack(codec.MAGIC, codec.ENVELOPE_VERSION, len(header)) + header
    with pytest.raises(InvalidFrame, match="envelope header is .* bytes, over"):
        codec.unpack_envelope(payload)
    header = b'{"parts": {}, "meta": {"gravity": ' + b"[" * 40 + b"]" * 40 + b"}}"
    payload = codec._PREFIX.pack(codec.MAGIC, codec.ENVELOPE_VERSION, len(header)) + header
    with pytest.raises(InvalidFrame, match="33-level limit"):
        codec.unpack_envelope(payload)


def test_image_sizes_are_checked_from_headers_only() -> None:
    buf = io.BytesIO()
    Image.fromarray(np.zeros((300, 400), np.uint16)).save(buf, format="PNG")
    codec.check_image_sizes({"depth": buf.getvalue()}, 400 * 300)
    with pytest.raises(InvalidFrame, match=r"depth is 400x300 = 120000 pixels, over the 119999-pixel cap") as info:
        codec.check_image_sizes({"depth": buf.getvalue()}, 400 * 300 - 1)
    assert info.value.detail == {"part": "depth", "width": 400, "height": 300, "max_pixels": 119999}
    with pytest.raises(InvalidFrame, match="labels is not a readable PNG"):
        codec.check_image_sizes({"labels": b"\x89PNG not really"}, 10**6)
    # a header declaring 20000 x 20000 (a truncated file: only the header): refused without inflating anything
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    bomb = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 16, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))
    with pytest.raises(InvalidFrame, match="over the 1000000-pixel cap"):
        codec.check_image_sizes({"depth": bomb}, 10**6)


def test_an_unreadable_image_is_named_without_the_servers_memory_or_pillows_own_limit() -> None:
    for check in (lambda data: codec.check_image_sizes({"depth": data}, 10**6),
                  lambda data: codec.decode_frame({"color": data, "depth": data}, {"depth_intrinsics": {
                      "fx": 500.0, "fy": 500.0, "cx": 32.0, "cy": 24.0}})):
        with pytest.raises(InvalidFrame) as info:
            check(b"garbage, no image" * 4)
        assert "not a readable" in str(info.value) and "BytesIO" not in str(info.value) and "0x" not in str(info.value)
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    # past Pillow's own bomb limit (2 x 89 M pixels): our cap named alone, not Pillow's 178956970
    huge = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 16, 0, 0, 0, 0)) + chunk(b"IEND", b"")
    with pytest.raises(InvalidFrame) as info:
        codec.check_image_sizes({"depth": huge}, 10**6)
    assert str(info.value) == "depth is over the 1000000-pixel cap (max_frame_pixels)"


def test_a_search_centre_or_a_translation_far_off_any_map_is_refused_and_errors_are_listed_up_to_a_cap() -> None:
    base = {"depth_intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}}
    with pytest.raises(InvalidFrame, match=r"meta.search_region.center.0: Input should be less than or equal to 1000000"):
        codec.parse_meta({**base, "search_region": {"center": [1e300, 0.0, 0.0], "radius_m": 1.0}})
    far = [[1.0, 0.0, 0.0, 2e6], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    with pytest.raises(InvalidFrame, match="within 1e\\+06 m of the origin"):
        codec.parse_meta({**base, "pose_prior": far})
    assert codec.parse_meta({**base, "search_region": {"center": [1e5, -1e5, 3.0], "radius_m": 5.0}})
    with pytest.raises(InvalidFrame) as info:
        codec.parse_meta({**base, **{f"unknown_{i}": i for i in range(100)}})
    assert len(info.value.detail["errors"]) == codec.MAX_LISTED_ERRORS and info.value.detail["error_count"] == 100


def test_frame_meta_numbers_are_strict_and_top_k_optional() -> None:
    base = {"depth_intrinsics": {"fx": 500, "fy": 500.0, "cx": 320, "cy": 240}}
    assert FrameMeta.model_validate(base).top_k is None
    assert FrameMeta.model_validate({**base, "top_k": None}).top_k is None
    for field, value in (("top_k", True), ("top_k", "3"), ("top_k", 2.5), ("depth_scale", True),
                         ("gravity", [0, True, 1])):
        with pytest.raises(InvalidFrame, match=f"meta.{field}"):
            codec.parse_meta({**base, field: value})
    with pytest.raises(InvalidFrame, match="meta.depth_intrinsics.fx"):
        codec.parse_meta({"depth_intrinsics": {**base["depth_intrinsics"], "fx": True}})
