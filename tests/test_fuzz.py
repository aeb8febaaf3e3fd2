"""Fuzz acceptance (issue 14), opt-in with `-m slow`: a real service (uvicorn + worker pool + zenoh peer on
tcp/127.0.0.1, scouting off) on the scene0470 site takes thousands of generated requests and never answers with a
server error.

* HTTP: schemathesis cases for every route of /openapi.json (positive and negative generation), the site id often
  pinned to the served site, admin routes with no, a wrong and the right bearer token, and localize bodies built of
  real / corrupted / foreign image parts with generated meta JSON. No 5xx, no `internal` code, no dropped connection.
* zenoh: generated envelopes (random bytes, truncated and corrupted real envelopes, junk header JSON, junk meta,
  huge / negative / NaN intrinsics, wrong part spans and sizes) as queries on cadreg/<site>/localize and as stream
  samples on cadreg/<site>/frames/<device>, random site and device ids included. Every query gets exactly one reply,
  a result (RESULT_ENCODING) or an error body (ERROR_ENCODING) whose code is not `internal`; no pose message carries
  `internal` either.
* Afterwards a good frame still gets an ok answer over HTTP and over zenoh.

Findings are collected (not raised at the first one) and the test fails listing them all. Counts and the time
budget come from the environment: CADREG_FUZZ_CASES (both parts), CADREG_FUZZ_HTTP_CASES, CADREG_FUZZ_ZENOH_CASES,
CADREG_FUZZ_BUDGET_S; CADREG_FUZZ_SEED changes the (derandomized) seed. A quick run:
    CADREG_FUZZ_CASES=200 python -m pytest -q -m slow tests/test_fuzz.py
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import threading
import time
import zlib
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from service import codec, zenoh_wire
from service.settings import Settings
from test_service_support import LiveServer, free_ports, load_frames, multipart, render_frames

_DEFAULT_CASES = int(os.environ.get("CADREG_FUZZ_CASES", "5000"))
HTTP_CASES = int(os.environ.get("CADREG_FUZZ_HTTP_CASES", _DEFAULT_CASES))
ZENOH_CASES = int(os.environ.get("CADREG_FUZZ_ZENOH_CASES", _DEFAULT_CASES))
# wall-clock budget per part: past it the generator stops drawing new work (the count run is then reported short)
BUDGET_S = float(os.environ.get("CADREG_FUZZ_BUDGET_S", "1500"))
SEED = int(os.environ.get("CADREG_FUZZ_SEED", "14"))
PER_CASE_DEADLINE = timedelta(seconds=90)  # one example: a full localize plus a site reload fit well inside
PYTEST_TIMEOUT_S = int(BUDGET_S + 900)  # budget + server start + the good-frame checks

SITE = "scene0470"
TOKEN = "fuzz-admin-token"
UPLOAD_LIMIT = 4 * 1024 * 1024
REQUEST_TIMEOUT_S = 30.0
OK_STATUSES = ("ok", "ambiguous")


# --- service ----------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("fuzzframes"), n=4))


@pytest.fixture(scope="module")
def server(scene0470_site_dir: Path, tmp_path_factory):
    # a private copy of the sites directory: admin uploads and reloads must not touch the session's bundle
    sites = tmp_path_factory.mktemp("fuzzsites")
    shutil.copytree(scene0470_site_dir, sites / SITE)
    port, zport = free_ports(2)
    live = LiveServer(Settings(
        sites_dir=sites,
        port=port,
        workers=1,
        queue_depth=2,
        request_timeout_s=REQUEST_TIMEOUT_S,
        max_upload_bytes=UPLOAD_LIMIT,
        max_bundle_bytes=8 * 1024 * 1024,
        admin_token=TOKEN,
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        stream_queue_per_device=2,
    ))
    live.zenoh_endpoint = f"tcp/127.0.0.1:{zport}"
    yield live
    live.stop()


@pytest.fixture(scope="module")
def good(server, frames) -> dict[str, Any]:
    """The first frame the service localizes ok, its parts and meta, and a well-formed envelope of it."""
    with httpx.Client(base_url=server.url, timeout=120.0) as c:
        for frame, _ in frames:
            files, data = multipart(frame)
            r = c.post(f"/v1/sites/{SITE}/localize", files=files, data=data)
            assert r.status_code == 200, r.text
            if r.json()["status"] in OK_STATUSES:
                parts, meta = codec.encode_frame_parts(frame)
                return {"frame": frame, "parts": parts, "meta": meta.model_dump(mode="json"),
                        "envelope": codec.pack_envelope(parts, meta)}
    pytest.fail("no rendered frame localizes ok before the fuzzing even starts")


def _check_good_frame_over_http(server, good) -> None:
    files, data = multipart(good["frame"])
    r = httpx.post(f"{server.url}/v1/sites/{SITE}/localize", files=files, data=data, timeout=120.0)
    assert r.status_code == 200, r.text
    assert r.json()["status"] in OK_STATUSES, r.text


# --- generated pieces shared by both parts ---------------------------------------------------------------------------

_PNG_SIG = b"\x89PNG\r\n\x1a\n"


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _tiny_png(w: int, h: int, bit_depth: int, colour_type: int) -> bytes:
    """A syntactically valid PNG of any declared size: the IHDR says w x h, the IDAT holds almost nothing."""
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    return _PNG_SIG + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(b"\0" * 16)) + \
        _png_chunk(b"IEND", b"")


def _foreign_parts() -> dict[str, bytes]:
    import io

    from PIL import Image

    def png(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG", compress_level=1)
        return buf.getvalue()

    def jpeg(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="JPEG")
        return buf.getvalue()

    return {
        "depth_small": png(np.full((240, 320), 1500, np.uint16)),
        "depth_8bit": png(np.full((480, 640), 150, np.uint8)),
        "depth_zero": png(np.zeros((480, 640), np.uint16)),
        "depth_1px": png(np.full((1, 1), 1000, np.uint16)),
        "depth_line": png(np.full((1, 640), 1000, np.uint16)),
        "depth_max": png(np.full((480, 640), 65535, np.uint16)),
        "depth_noise": png(np.random.default_rng(0).integers(0, 65535, (480, 640)).astype(np.uint16)),
        "color_gray": png(np.full((480, 640), 128, np.uint8)),
        "color_rgba": png(np.zeros((480, 640, 4), np.uint8)),
        "color_small": png(np.zeros((240, 320, 3), np.uint8)),
        "color_jpeg": jpeg(np.zeros((480, 640, 3), np.uint8)),
        "color_16bit": png(np.full((480, 640), 1000, np.uint16)),
        "labels_small": png(np.ones((100, 100), np.uint16)),
        "labels_rgb": png(np.zeros((480, 640, 3), np.uint8)),
        "labels_big_ids": png(np.full((480, 640), 65535, np.uint16)),
        "bomb_header": _tiny_png(20000, 20000, 16, 0),
        "huge_declared": _tiny_png(2**31 - 1, 1, 8, 2),
        "zero_declared": _tiny_png(0, 0, 16, 0),
        "gif": b"GIF89a\x01\x00\x01\x00\x00\x00\x00;",
        "empty": b"",
    }


_FOREIGN = _foreign_parts()

_JUNK_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner, max_size=5),
    max_leaves=12,
)
_BAD_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 0.0, -0.0, -1, -500.0, 1e-320, 1e-9, 1e9, 1e12, 1e308, -1e308, 2**63, 2**64 + 1, 10**400]),
    st.integers(-(2**70), 2**70),
    st.text(max_size=6), st.none(), st.booleans(), st.lists(st.floats(), max_size=3),
)
_MATRIX = st.one_of(
    st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=4, max_size=4), min_size=4, max_size=4),
    st.lists(st.lists(st.floats(-1e6, 1e6), min_size=0, max_size=5), min_size=0, max_size=5),
    st.sampled_from([np.zeros((4, 4)).tolist(), (np.eye(4) * 1e300).tolist(), np.eye(4).tolist(),
                     [[1, 0, 0, 1e9], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], [[1] * 4] * 4]),
    _JUNK_JSON,
)
_FIELD_VALUES: dict[str, st.SearchStrategy] = {
    "frame_id": st.one_of(st.text(max_size=300), st.text(max_size=20).map(lambda s: "\n\r" + s), _JUNK_JSON),
    "depth_intrinsics": _JUNK_JSON,
    "color_intrinsics": _JUNK_JSON,
    "T_color_depth": _MATRIX,
    "depth_scale": _BAD_NUMBER,
    "label_set": st.one_of(st.sampled_from(["nyu40", "scannet", "", "x" * 65]), st.text(max_size=70), _JUNK_JSON),
    "gravity": st.one_of(st.lists(_BAD_NUMBER, max_size=4), st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3),
                         st.sampled_from([[0, 0, 0], [0, 1e-300, 0], [1e308, 1e308, 1e308]]), _JUNK_JSON),
    "pose_prior": _MATRIX,
    "top_k": st.one_of(st.integers(-5, 30), st.integers(-(2**70), 2**70), _BAD_NUMBER),
}
_INTRINSIC_KEYS = ("fx", "fy", "cx", "cy")


@st.composite
def meta_docs(draw, good_meta: dict[str, Any]) -> Any:
    """A FrameMeta document, mostly the good one with a few fields broken, sometimes junk of any shape."""
    kind = draw(st.sampled_from(["mutated"] * 6 + ["intrinsics"] * 3 + ["junk", "empty"]))
    if kind == "junk":
        return draw(_JUNK_JSON)
    if kind == "empty":
        return {}
    doc = json.loads(json.dumps(good_meta))
    if kind == "intrinsics":
        which = draw(st.sampled_from(["depth_intrinsics", "color_intrinsics"]))
        intr = dict(doc.get("depth_intrinsics") or {})
        for key in draw(st.lists(st.sampled_from(_INTRINSIC_KEYS + ("skew",)), min_size=1, max_size=4, unique=True)):
            if draw(st.booleans()) and key != "skew":
                intr.pop(key, None)
            else:
                intr[key] = draw(_BAD_NUMBER | st.floats(-1e4, 1e4))
        doc[which] = intr
        return doc
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["set", "set", "set", "drop", "unknown"]))
        if op == "drop":
            doc.pop(draw(st.sampled_from(sorted(_FIELD_VALUES))), None)
        elif op == "unknown":
            doc[draw(st.text(min_size=1, max_size=12))] = draw(_JUNK_JSON)
        else:
            name = draw(st.sampled_from(sorted(_FIELD_VALUES)))
            doc[name] = draw(_FIELD_VALUES[name])
    return doc


def _varied_good_meta(draw, good_meta: dict[str, Any]) -> dict[str, Any]:
    """The good meta with only what a well-behaved client varies: the frame id and top_k."""
    return {**good_meta, "frame_id": draw(st.text(max_size=40)), "top_k": draw(st.integers(1, 20))}


def _meta_text(draw, good_meta: dict[str, Any]) -> str:
    form = draw(st.sampled_from(["json"] * 8 + ["text", "truncated"]))
    if form == "text":
        return draw(st.text(max_size=200))
    text = json.dumps(draw(meta_docs(good_meta)), allow_nan=True)  # NaN / Infinity literals on purpose
    if form == "truncated":
        text = text[: draw(st.integers(0, max(0, len(text) - 1)))]
    return text


def _corrupt(draw, data: bytes, region: tuple[int, int] | None = None) -> bytes:
    """`data` with a few bytes overwritten / a span deleted / a span duplicated."""
    if not data:
        return draw(st.binary(max_size=64))
    buf = bytearray(data)
    lo, hi = region or (0, len(buf))
    hi = max(lo + 1, min(hi, len(buf)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "flip", "delete", "dup", "zero"]))
        i = draw(st.integers(lo, hi - 1))
        n = draw(st.integers(1, 64))
        if op == "flip":
            buf[i] ^= draw(st.integers(1, 255))
        elif op == "delete":
            del buf[i : i + n]
        elif op == "dup":
            buf[i:i] = buf[i : i + n]
        else:
            buf[i : i + n] = bytes(len(buf[i : i + n]))
        hi = max(lo + 1, min(hi, len(buf)))
        if len(buf) <= lo:
            break
    return bytes(buf)


def _part(draw, name: str, good_parts: dict[str, bytes]) -> bytes | None:
    real = good_parts.get(name) or good_parts["depth"]
    kind = draw(st.sampled_from(["good"] * 4 + ["corrupt", "truncated", "foreign", "other", "random", "missing"]))
    if kind == "good":
        return real
    if kind == "corrupt":
        return _corrupt(draw, real, (0, 256) if draw(st.booleans()) else None)
    if kind == "truncated":
        return real[: draw(st.integers(0, len(real) - 1))]
    if kind == "foreign":
        return _FOREIGN[draw(st.sampled_from(sorted(_FOREIGN)))]
    if kind == "other":
        return good_parts[draw(st.sampled_from(sorted(good_parts)))]
    if kind == "random":
        return draw(st.binary(max_size=512))
    return None


# --- HTTP ---------------------------------------------------------------------------------------------------------------


def _http_finding(findings: list, case, response=None, exc: BaseException | None = None) -> None:
    request = f"{case.method} {case.formatted_path}"
    if exc is not None:
        answer = f"{type(exc).__name__}: {exc}"[:400]
    else:
        answer = f"{response.status_code} {response.text[:400]}"
    body = case.body
    if isinstance(body, dict):
        body = {k: (v[:60] if isinstance(v, (bytes, str)) else v) for k, v in body.items()}
    findings.append({"request": request, "headers": {k: v for k, v in (case.headers or {}).items()},
                     "query": case.query, "body": repr(body)[:600], "answer": answer})


def _is_internal(text: str) -> bool:
    try:
        doc = json.loads(text)
    except ValueError:
        return False
    return isinstance(doc, dict) and doc.get("code") == "internal"


def test_http_fuzz_finds_no_server_error(server, good) -> None:
    import requests
    import schemathesis
    from schemathesis import GenerationMode

    pytest.importorskip("schemathesis")
    schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    labels = sorted(f"{op.method.upper()} {op.path}" for op in operations)
    paths = {op.path for op in operations}
    assert {"/v1/sites/{site_id}/localize", "/v1/sites/{site_id}", "/v1/sites/{site_id}/reload", "/v1/sites",
            "/healthz", "/readyz", "/metrics"} <= paths, labels
    strategies = {(op.method.upper(), op.path, mode): op.as_strategy(generation_mode=mode)
                  for op in operations for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)}
    keys = sorted(strategies, key=lambda k: (k[0], k[1], k[2].value))
    localize_path = "/v1/sites/{site_id}/localize"

    findings: list[dict[str, Any]] = []
    seen: dict[str, int] = {}
    statuses: dict[str, int] = {}
    t_end = time.monotonic() + BUDGET_S
    session = requests.Session()

    @seed(SEED)
    @settings(max_examples=HTTP_CASES, derandomize=True, database=None, deadline=PER_CASE_DEADLINE,
              phases=[Phase.generate], suppress_health_check=list(HealthCheck), print_blob=False)
    @given(data=st.data())
    def run(data) -> None:
        if time.monotonic() > t_end:
            return
        key = data.draw(st.sampled_from(keys), label="operation")
        case = data.draw(strategies[key], label="case")
        if "site_id" in (case.path_parameters or {}) and data.draw(st.integers(0, 9)) < 6:
            case.path_parameters = {**case.path_parameters, "site_id": SITE}
        auth = data.draw(st.sampled_from(["none", "keep", "good", "good", "wrong", "scheme"]), label="auth")
        headers = dict(case.headers or {})
        if auth == "good":
            headers["Authorization"] = f"Bearer {TOKEN}"
        elif auth == "wrong":
            headers["Authorization"] = f"Bearer {TOKEN}x"
        elif auth == "scheme":
            headers["Authorization"] = data.draw(st.sampled_from([TOKEN, f"Basic {TOKEN}", "Bearer", "Bearer  "]))
        elif auth == "none":
            headers.pop("Authorization", None)
        case.headers = headers
        if key[1] == localize_path and key[0] == "POST" and data.draw(st.integers(0, 9)) < 7:
            # a body schemathesis cannot know: real or broken image parts and generated FrameMeta JSON
            body: dict[str, Any] = {}
            if data.draw(st.integers(0, 9)) == 0:  # now and then a good frame with a varied frame id and top_k
                body = {**good["parts"], "meta": json.dumps(_varied_good_meta(data.draw, good["meta"]))}
            for name in codec.PART_NAMES if not body else ():
                value = _part(data.draw, name, good["parts"])
                if value is not None and (name != "labels" or data.draw(st.booleans())):
                    body[name] = value
            if "meta" not in body and data.draw(st.integers(0, 9)):
                body["meta"] = _meta_text(data.draw, good["meta"])
            case.body = body
            case.media_type = "multipart/form-data"
        label = f"{key[0]} {key[1]}"
        seen[label] = seen.get(label, 0) + 1
        try:
            response = case.call(base_url=server.url, session=session, timeout=REQUEST_TIMEOUT_S * 2)
        except Exception as exc:  # a reset or hung connection is a server failure too
            _http_finding(findings, case, exc=exc)
            return
        statuses[f"{label} {response.status_code}"] = statuses.get(f"{label} {response.status_code}", 0) + 1
        if response.status_code >= 500 or _is_internal(response.text):
            _http_finding(findings, case, response)

    t0 = time.monotonic()
    run()
    elapsed = time.monotonic() - t0
    total = sum(seen.values())
    print(f"\nHTTP fuzz: {total} cases in {elapsed:.0f} s; per operation {seen}; statuses {dict(sorted(statuses.items()))}")
    for f in findings:
        print("HTTP FINDING", json.dumps(f, default=str))
    # the service still answers a good frame, and readiness is whole
    _check_good_frame_over_http(server, good)
    server.wait_ready()
    assert not findings, f"{len(findings)} server errors, first: {findings[:5]}"
    assert total >= HTTP_CASES, f"only {total} of {HTTP_CASES} cases ran within the {BUDGET_S:.0f} s budget"
    if HTTP_CASES >= 1000:
        assert set(seen) == set(labels), (sorted(seen), labels)  # every route was fuzzed


# --- zenoh --------------------------------------------------------------------------------------------------------------


def _hand_envelope(header: Any, body: bytes, *, magic: bytes = codec.MAGIC, version: int = codec.ENVELOPE_VERSION,
                   header_len: int | None = None, raw_header: bytes | None = None) -> bytes:
    head = raw_header if raw_header is not None else json.dumps(header, allow_nan=True).encode()
    length = len(head) if header_len is None else header_len
    return magic + bytes([version & 0xFF]) + struct.pack("<I", length & 0xFFFFFFFF) + head + body


@st.composite
def envelopes(draw, good: dict[str, Any]) -> tuple[str, bytes]:
    """(what kind, payload) of a generated zenoh frame envelope."""
    real: bytes = good["envelope"]
    kind = draw(st.sampled_from(["random", "magic_random", "truncated", "corrupt_header", "corrupt_body",
                                 "junk_header", "junk_meta", "bad_spans", "bad_parts", "bad_prefix", "good_meta_var"]))
    if kind == "random":
        return kind, draw(st.binary(max_size=1024))
    if kind == "magic_random":
        return kind, codec.MAGIC + draw(st.binary(max_size=64)) + draw(st.binary(max_size=512))
    if kind == "truncated":
        return kind, real[: draw(st.integers(0, len(real) - 1))]
    header_len = struct.unpack_from("<I", real, 5)[0]
    if kind == "corrupt_header":
        return kind, _corrupt(draw, real, (0, 9 + header_len))
    if kind == "corrupt_body":
        return kind, _corrupt(draw, real, (9 + header_len, len(real)))
    parts = good["parts"]
    if kind == "bad_prefix":
        header = {"meta": good["meta"], "parts": _spans(parts)}
        raw = json.dumps(header).encode()
        return kind, _hand_envelope(
            header, b"".join(parts.values()),
            magic=draw(st.sampled_from([codec.MAGIC, b"CDRg", b"\0\0\0\0"])),
            version=draw(st.sampled_from([0, 1, 2, 255])),
            header_len=draw(st.sampled_from([0, 1, len(raw) - 1, len(raw) + 1, 2**20 + 1, 2**32 - 1])
                            | st.integers(0, 2**32 - 1)))
    if kind == "junk_header":
        raw = draw(st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode),
                             _JUNK_JSON.map(lambda v: json.dumps(v, allow_nan=True).encode())))
        return kind, _hand_envelope(None, b"".join(parts.values()), raw_header=raw)
    if kind in ("junk_meta", "good_meta_var"):
        meta = draw(meta_docs(good["meta"])) if kind == "junk_meta" else _varied_good_meta(draw, good["meta"])
        header = {"meta": meta, "parts": _spans(parts)}
        if draw(st.integers(0, 3)) == 0:
            header[draw(st.text(max_size=8))] = draw(_JUNK_JSON)
        return kind, _hand_envelope(header, b"".join(parts.values()))
    if kind == "bad_spans":
        spans = _spans(parts)
        for _ in range(draw(st.integers(1, 3))):
            name = draw(st.sampled_from(sorted(spans) + ["labels", "extra"]))
            spans[name] = draw(st.one_of(
                st.lists(st.integers(-(2**40), 2**40), max_size=3),
                st.tuples(st.integers(-10, 10**7), st.integers(-10, 10**7)).map(list),
                st.sampled_from([[0, 0], [0, -1], [-1, 10], [2**63, 1], [0.5, 10], [True, False], "0:10", None]),
                _JUNK_JSON))
        return kind, _hand_envelope({"meta": good["meta"], "parts": spans}, b"".join(parts.values()))
    # bad_parts: parts of the wrong size, type or content under a good meta and honest spans
    new_parts: dict[str, bytes] = {}
    for name in codec.PART_NAMES:
        value = _part(draw, name, parts)
        if value is not None and (name != "labels" or draw(st.booleans())):
            new_parts[name] = value
    return kind, _hand_envelope({"meta": good["meta"], "parts": _spans(new_parts)}, b"".join(new_parts.values()))


def _spans(parts: dict[str, bytes]) -> dict[str, list[int]]:
    spans, pos = {}, 0
    for name, data in parts.items():
        spans[name] = [pos, len(data)]
        pos += len(data)
    return spans


_CHUNK_ALPHABET = st.characters(blacklist_characters="/*$#?", blacklist_categories=("Cs",))
_SITE_IDS = st.one_of(st.just(SITE), st.just(SITE), st.just(SITE), st.text(_CHUNK_ALPHABET, min_size=1, max_size=30),
                      st.sampled_from(["*", "atlantis", "..", "SCENE0470", "scene0470 ", "a" * 200, "%2F"]))
_DEVICE_IDS = st.one_of(st.sampled_from(["cam-1", "cam-2", "cam-3"]), st.text(_CHUNK_ALPHABET, min_size=1, max_size=30),
                        st.just("*"))


def _zenoh_query_finding(findings: list, key: str, what: str, payload: bytes, answer: str) -> None:
    findings.append({"request": f"query {key!r} ({what}, {len(payload)} bytes: {payload[:80]!r})",
                     "answer": answer[:400]})


def test_zenoh_fuzz_finds_no_internal_error(server, good) -> None:
    import zenoh

    from service.zenoh_server import zenoh_config

    findings: list[dict[str, Any]] = []
    kinds: dict[str, int] = {}
    replies: dict[str, int] = {}
    poses: list[tuple[str, str, bytes]] = []  # (key, encoding, payload), filled on zenoh's thread, read after
    poses_lock = threading.Lock()

    def on_pose(sample) -> None:  # no zenoh calls in a callback: just keep it
        with poses_lock:
            poses.append((str(sample.key_expr), str(sample.encoding), sample.payload.to_bytes()))

    config = zenoh_config(Settings(zenoh_mode="peer", zenoh_listen=[], zenoh_connect=[server.zenoh_endpoint]))
    session = zenoh.open(config)
    sub = session.declare_subscriber("cadreg/*/poses/*", on_pose)
    time.sleep(0.5)  # let the peers meet
    sent_stream = 0
    t_end = time.monotonic() + BUDGET_S
    try:
        @seed(SEED)
        @settings(max_examples=ZENOH_CASES, derandomize=True, database=None, deadline=PER_CASE_DEADLINE,
                  phases=[Phase.generate], suppress_health_check=list(HealthCheck), print_blob=False)
        @given(item=envelopes(good), site=_SITE_IDS, device=_DEVICE_IDS, stream_site=_SITE_IDS)
        def run(item, site, device, stream_site) -> None:
            nonlocal sent_stream
            if time.monotonic() > t_end:
                return
            what, payload = item
            kinds[what] = kinds.get(what, 0) + 1
            # as a stream sample first (it is answered on the poses key, asynchronously) ...
            try:
                session.put(f"cadreg/{stream_site}/frames/{device}", payload)
                sent_stream += 1
            except zenoh.ZError:
                pass  # a key zenoh itself refuses to build never reaches the service
            # ... then as a query, which must get exactly one answer of ours
            key = f"cadreg/{site}/localize"
            if site.startswith("@"):
                # a verbatim chunk: zenoh matches it against no '*', so no queryable of ours can see this query
                replies["verbatim key, unroutable"] = replies.get("verbatim key, unroutable", 0) + 1
                with pytest.raises(ValueError):
                    zenoh_wire.localize_key(site)  # and the wire module refuses to build it
                return
            try:
                got = list(session.get(key, payload=payload, timeout=REQUEST_TIMEOUT_S * 2))
            except zenoh.ZError as exc:
                replies["key refused by zenoh"] = replies.get("key refused by zenoh", 0) + 1
                if site == SITE:
                    _zenoh_query_finding(findings, key, what, payload, f"zenoh refused: {exc}")
                return
            if len(got) != 1:
                _zenoh_query_finding(findings, key, what, payload, f"{len(got)} replies")
                return
            reply = got[0]
            sample = reply.ok if reply.ok is not None else reply.err
            kind = zenoh_wire.body_kind(sample.encoding)
            data = sample.payload.to_bytes()
            if (reply.ok is not None and kind != "result") or (reply.err is not None and kind != "error"):
                _zenoh_query_finding(findings, key, what, payload,
                                     f"{'ok' if reply.ok is not None else 'err'} reply, encoding "
                                     f"{str(sample.encoding)!r}: {data[:300]!r}")
                return
            try:
                body = json.loads(data)
            except ValueError:
                _zenoh_query_finding(findings, key, what, payload, f"no JSON: {data[:300]!r}")
                return
            code = body.get("status") if kind == "result" else body.get("code")
            replies[f"{kind}:{code}"] = replies.get(f"{kind}:{code}", 0) + 1
            if kind == "error" and code == "internal":
                _zenoh_query_finding(findings, key, what, payload, data.decode("utf-8", "replace"))

        t0 = time.monotonic()
        run()
        elapsed = time.monotonic() - t0
        total = sum(kinds.values())
        # let the streams drain: wait until no pose message came for a few seconds
        last, quiet_since = -1, time.monotonic()
        while time.monotonic() - quiet_since < 5.0 and time.monotonic() - t0 < elapsed + 300:
            with poses_lock:
                n = len(poses)
            if n != last:
                last, quiet_since = n, time.monotonic()
            time.sleep(0.5)
        pose_codes: dict[str, int] = {}
        with poses_lock:
            received = list(poses)
        for key, encoding, data in received:
            kind = zenoh_wire.body_kind(encoding)
            try:
                body = json.loads(data)
            except ValueError:
                body = None
            code = None if not isinstance(body, dict) else (body.get("status") if kind == "result" else body.get("code"))
            pose_codes[f"{kind}:{code}"] = pose_codes.get(f"{kind}:{code}", 0) + 1
            if kind is None or not isinstance(body, dict) or (kind == "error" and code == "internal"):
                findings.append({"request": f"stream sample answered on {key!r}",
                                 "answer": f"encoding {encoding!r}: {data[:400]!r}"})
        print(f"\nzenoh fuzz: {total} envelopes in {elapsed:.0f} s as queries and {sent_stream} as stream samples; "
              f"kinds {kinds}; query replies {replies}; {len(received)} pose messages {pose_codes}")
        for f in findings:
            print("ZENOH FINDING", json.dumps(f, default=str))

        # a good frame still gets an ok answer: a query, a stream sample, and over HTTP
        got = list(session.get(zenoh_wire.localize_key(SITE), payload=good["envelope"], timeout=120.0))
        assert len(got) == 1 and got[0].ok is not None, [str(r.err.payload.to_bytes()) for r in got if r.err]
        assert zenoh_wire.body_kind(got[0].ok.encoding) == "result"
        assert json.loads(got[0].ok.payload.to_bytes())["status"] in OK_STATUSES
        with poses_lock:
            poses.clear()
        session.put(zenoh_wire.frames_key(SITE, "after-fuzz"), good["envelope"],
                    congestion_control=zenoh.CongestionControl.BLOCK)  # not dropped behind the fuzz backlog
        deadline = time.monotonic() + 120
        answer = None
        while answer is None and time.monotonic() < deadline:
            with poses_lock:
                answer = next((p for p in poses if p[0] == zenoh_wire.poses_key(SITE, "after-fuzz")), None)
            time.sleep(0.1)
        assert answer is not None, "no pose message for a good stream frame after the fuzzing"
        assert zenoh_wire.body_kind(answer[1]) == "result" and json.loads(answer[2])["status"] in OK_STATUSES, answer
        _check_good_frame_over_http(server, good)
        assert not findings, f"{len(findings)} bad answers, first: {findings[:5]}"
        assert total >= ZENOH_CASES, f"only {total} of {ZENOH_CASES} envelopes went out within the {BUDGET_S:.0f} s budget"
    finally:
        sub.undeclare()
        session.close()


pytestmark = [pytest.mark.slow, pytest.mark.timeout(PYTEST_TIMEOUT_S)]
