"""What a hostile client found (issue 14, part 2), each reproduced against a real uvicorn on loopback with a real
worker: meta nested 100,000 deep, a small file declaring a huge image, an unknown label set, a duplicated part,
`top_k: true`, a huge declared Content-Length, and connections that never finish their headers."""

from __future__ import annotations

import io
import json
import socket
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from cadreg.errors import InvalidFrame
from cadreg.frame import Frame
from service import codec
from service.settings import Settings
from test_service_support import LiveServer, free_port, load_frames, multipart, render_frames

SITE = "scene0470"
TOKEN = "strict-token"
UPLOAD_LIMIT = 4 * 1024 * 1024
HEADER_TIMEOUT_S = 1.0
MAX_HEADER_BYTES = 4096
BODY_TIMEOUT_S = 4.0  # the budget test's three sends (about 1.5 s) must fit in it
BUFFERED_LIMIT = 2 * UPLOAD_LIMIT


@pytest.fixture(scope="module")
def frames(scene0470_site_dir: Path, tmp_path_factory) -> list:
    return load_frames(render_frames(scene0470_site_dir, tmp_path_factory.mktemp("sframes"), n=4))


@pytest.fixture(scope="module")
def server(scene0470_site_dir: Path):
    settings = Settings(sites_dir=scene0470_site_dir.parent, port=free_port(), workers=1, queue_depth=2,
                        request_timeout_s=20.0, max_upload_bytes=UPLOAD_LIMIT, admin_token=TOKEN,
                        zenoh_enabled=False, http_header_timeout_s=HEADER_TIMEOUT_S,
                        http_max_header_bytes=MAX_HEADER_BYTES, http_body_timeout_s=BODY_TIMEOUT_S,
                        http_max_buffered_bytes=BUFFERED_LIMIT)
    live = LiveServer(settings, as_served=True)
    yield live
    live.stop()


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=60.0) as c:
        yield c


def _post(client, files, data) -> httpx.Response:
    return client.post(f"/v1/sites/{SITE}/localize", files=files, data=data)


def _error(r: httpx.Response, status: int, code: str) -> dict:
    assert r.status_code == status, r.text
    body = r.json()
    assert body["code"] == code, body
    return body


def _meta_doc(frame) -> dict:
    return codec.encode_frame_parts(frame)[1].model_dump(mode="json")


# --- 1. meta nested 100,000 deep ---------------------------------------------------------------------------------

def test_meta_nested_100000_deep_is_422_naming_the_limit(client, frames) -> None:
    files, _ = multipart(frames[0][0])
    r = _post(client, files, {"meta": '{"frame_id": ' + "[" * 100_000 + "]" * 100_000 + "}"})
    body = _error(r, 422, "invalid_frame")
    assert "65536-byte limit" in body["message"], body
    # under the size cap but deeper than the depth cap: refused by the scan, not by a recursing parser
    deep = json.dumps(_meta_doc(frames[0][0]))[:-1] + ', "gravity": ' + "[" * 40 + "]" * 40 + "}"
    body = _error(_post(client, files, {"meta": deep}), 422, "invalid_frame")
    assert "32-level limit" in body["message"], body
    assert _post(client, *multipart(frames[0][0])).status_code == 200


# --- 2. pixel cap from the headers ---------------------------------------------------------------------------------

def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=9)
    return buf.getvalue()


_BIG = (3100, 4100)  # h, w: 12.71 MP, just over the default cap of 4096 x 3072 = 12.58 MP


@pytest.mark.parametrize("part", ["color", "depth", "labels"])
def test_an_image_over_max_frame_pixels_is_refused_from_its_header(server, client, frames, part) -> None:
    frame = frames[0][0]
    big = {"color": np.zeros((*_BIG, 3), np.uint8), "depth": np.zeros(_BIG, np.uint16),
           "labels": np.zeros(_BIG, np.uint8)}[part]
    data = _png(big)
    assert len(data) < 200_000  # a small request...
    files, form = multipart(frame, parts_override={part: data})
    t0 = time.monotonic()
    body = _error(_post(client, files, form), 422, "invalid_frame")
    assert time.monotonic() - t0 < 5.0
    assert "max_frame_pixels" in body["message"] and str(4096 * 3072) in body["message"], body
    assert body["detail"]["part"] == part and body["detail"]["max_pixels"] == 4096 * 3072
    # the parent refuses it, before a worker sees it: the zenoh front end submits through the same call
    parts, meta = codec.encode_frame_parts(frame)
    with pytest.raises(InvalidFrame, match="max_frame_pixels"):
        server.service.submit(SITE, {**parts, part: data}, meta)


# --- 3. strict meta ------------------------------------------------------------------------------------------------

def test_an_unknown_label_set_is_422_naming_the_known_ones(client, frames) -> None:
    frame = frames[0][0]
    files, data = multipart(frame, meta_override={"label_set": "bogus"}, drop=("labels",))
    assert "labels" not in files
    body = _error(_post(client, files, data), 422, "invalid_frame")
    assert "'bogus'" in body["message"] and "nyu40" in body["message"], body
    assert "nyu40" in body["detail"]["known"]
    if frame.labels is not None:
        files, data = multipart(frame, meta_override={"label_set": "bogus"})
        body = _error(_post(client, files, data), 422, "invalid_frame")
        assert "nyu40" in body["message"]


def test_a_label_set_is_named_in_any_case(client, frames) -> None:
    # DESIGN §2 writes "NYU40", the sites key it "nyu40": a client's capitals name the same set, labels and all.
    frame, T_true = frames[0]
    assert frame.labels is not None
    r = _post(client, *multipart(frame, meta_override={"label_set": "NYU40"}))
    assert r.status_code == 200, r.text
    result = r.json()
    assert result["status"] == "ok" and result["diagnostics"]["scan_objects"], result["diagnostics"]
    assert Frame(**{**frame.__dict__, "label_set": "NYU40"}).label_set == "nyu40"


def test_a_duplicated_part_is_422_naming_it(client, frames) -> None:
    files, data = multipart(frames[0][0])
    twice = {"meta": [data["meta"], json.dumps({**json.loads(data["meta"]), "top_k": 1})]}
    body = _error(_post(client, files, twice), 422, "invalid_frame")
    assert "'meta' given twice" in body["message"] and body["detail"]["part"] == "meta", body
    file_list = list(files.items()) + [("color", files["color"])]
    body = _error(client.post(f"/v1/sites/{SITE}/localize", files=file_list, data=data), 422, "invalid_frame")
    assert "'color' given twice" in body["message"] and body["detail"]["part"] == "color", body


@pytest.mark.parametrize("path, value", [
    (("top_k",), True),
    (("top_k",), False),
    (("depth_scale",), True),
    (("depth_intrinsics", "fx"), True),
    (("gravity",), [True, 0, 0]),
    (("top_k",), "3"),
    (("top_k",), 2.0),
])
def test_booleans_and_strings_are_not_numbers(client, frames, path, value) -> None:
    meta = _meta_doc(frames[0][0])
    target = meta
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    files, _ = multipart(frames[0][0])
    body = _error(_post(client, files, {"meta": json.dumps(meta)}), 422, "invalid_frame")
    assert body["message"].startswith("meta." + ".".join(path)), body


def test_top_k_not_sent_is_none_and_the_service_default_answers(client, frames) -> None:
    meta = _meta_doc(frames[0][0])
    meta.pop("top_k")
    assert codec.parse_meta(json.dumps(meta)).top_k is None
    files, _ = multipart(frames[0][0])
    r = _post(client, files, {"meta": json.dumps(meta)})
    assert r.status_code == 200, r.text
    r1 = _post(client, *multipart(frames[0][0], top_k=1))
    assert r1.status_code == 200 and len(r1.json()["hypotheses"]) <= 1


# --- 4. declared lengths and idle connections ----------------------------------------------------------------------

def _connect(server) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", server.settings.port), timeout=5.0)
    return sock


def _read_until_closed(sock: socket.socket, timeout_s: float) -> tuple[bytes, bool]:
    """What the server sent within `timeout_s`, and whether it closed the connection in that time."""
    sock.settimeout(0.2)
    deadline = time.monotonic() + timeout_s
    data = b""
    while time.monotonic() < deadline:
        try:
            chunk = sock.recv(65536)
        except socket.timeout:
            continue
        except ConnectionResetError:
            return data, True
        if not chunk:
            return data, True
        data += chunk
    return data, False


def _head(method: str, path: str, length: int, extra: str = "") -> bytes:
    return (f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {length}\r\n"
            f"Content-Type: multipart/form-data; boundary=xyz\r\n{extra}\r\n").encode()


@pytest.mark.parametrize("declared, closed", [(UPLOAD_LIMIT + 1, False), (10**12, True)])
def test_an_oversized_content_length_is_413_before_the_body(server, declared, closed) -> None:
    with _connect(server) as sock:
        sock.sendall(_head("POST", f"/v1/sites/{SITE}/localize", declared))  # headers only: no body is coming
        t0 = time.monotonic()
        data, was_closed = _read_until_closed(sock, 3.0 if closed else 0.8)
        assert data.startswith(b"HTTP/1.1 413"), data[:200]
        assert b'"code":"payload_too_large"' in data and str(UPLOAD_LIMIT).encode() in data
        if closed:  # far over the limit: nobody waits for that body
            assert was_closed and time.monotonic() - t0 < 3.0
            assert b"connection: close" in data.lower()


def test_an_oversized_archive_length_is_413_before_the_body(server) -> None:
    with _connect(server) as sock:
        sock.sendall(_head("PUT", f"/v1/sites/{SITE}", 10**12, f"Authorization: Bearer {TOKEN}\r\n"))
        data, was_closed = _read_until_closed(sock, 3.0)
    assert data.startswith(b"HTTP/1.1 413") and b'"code":"payload_too_large"' in data, data[:200]
    assert was_closed


def test_a_connection_that_sends_nothing_is_closed_after_the_header_timeout(server) -> None:
    with _connect(server) as sock:
        t0 = time.monotonic()
        data, was_closed = _read_until_closed(sock, HEADER_TIMEOUT_S + 3.0)
    assert was_closed and data == b"", data
    assert HEADER_TIMEOUT_S - 0.2 <= time.monotonic() - t0 < HEADER_TIMEOUT_S + 3.0


def test_headers_sent_a_byte_at_a_time_are_cut_off(server) -> None:
    with _connect(server) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        t0 = time.monotonic()
        closed = False
        while time.monotonic() - t0 < HEADER_TIMEOUT_S + 3.0 and not closed:
            try:
                sock.sendall(b"X-Slow: a\r\n")
            except (BrokenPipeError, ConnectionResetError):
                closed = True
                break
            _, closed = _read_until_closed(sock, 0.2)
    assert closed and time.monotonic() - t0 < HEADER_TIMEOUT_S + 3.0


def test_headers_over_the_limit_are_400(server) -> None:
    # h11 bounds what it buffers of an incomplete request head (headers still coming), so the end comes later
    with _connect(server) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (2 * MAX_HEADER_BYTES) + b"\r\n")
        data, closed = _read_until_closed(sock, 0.5)
        if not closed:
            sock.sendall(b"\r\n")
            more, _ = _read_until_closed(sock, 3.0)
            data += more
    assert data.startswith(b"HTTP/1.1 400"), data[:200]


def test_headers_over_the_limit_in_one_read_are_413_and_the_connection_closes(server) -> None:
    # h11 checks its limit only while the head is incomplete: a whole head in one read went through (200)
    with _connect(server) as sock:
        sock.sendall(b"GET /healthz?q=" + b"a" * MAX_HEADER_BYTES + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        data, closed = _read_until_closed(sock, 3.0)
    assert data.startswith(b"HTTP/1.1 413") and b'"code":"payload_too_large"' in data, data[:300]
    assert b"http_max_header_bytes" in data and closed


# --- a body that never comes, bodies held at once, a client that leaves (a second hostile client) ---------------

def test_a_body_that_stalls_is_408_after_the_body_timeout(server) -> None:
    with _connect(server) as sock:
        sock.sendall(_head("POST", f"/v1/sites/{SITE}/localize", 1_000_000) + b"x" * 1000)
        t0 = time.monotonic()
        data, closed = _read_until_closed(sock, BODY_TIMEOUT_S + 4.0)
    assert data.startswith(b"HTTP/1.1 408") and b'"code":"body_timeout"' in data, data[:300]
    assert closed and BODY_TIMEOUT_S - 0.2 <= time.monotonic() - t0 < BODY_TIMEOUT_S + 4.0


def test_bodies_held_at_once_are_bounded_and_given_back(server, client, frames) -> None:
    """Three connections that each send 3 MiB of a 3.5 MiB body and wait: the first two fit the 8 MiB budget, the
    third is refused (503 `overloaded`, its connection closed: a reset may lose the answer it was sent, so the
    metrics count it); the first two end at the body timeout; the budget is whole again."""
    part = 3 * 1024 * 1024
    overloaded_before = _localize_count(client, "overloaded")
    socks = []
    try:
        for _ in range(2):  # each connected when it sends: the header timeout (1 s here) runs from the connection
            socks.append(_connect(server))
            socks[-1].sendall(_head("POST", f"/v1/sites/{SITE}/localize", part + part // 6) + b"x" * part)
            assert _read_until_closed(socks[-1], 0.5) == (b"", False)
        socks.append(_connect(server))
        try:
            socks[2].sendall(_head("POST", f"/v1/sites/{SITE}/localize", part + part // 6) + b"x" * part)
        except (BrokenPipeError, ConnectionResetError):
            pass  # closed while we still sent
        third, closed = _read_until_closed(socks[2], 3.0)
        assert closed and (third == b"" or third.startswith(b"HTTP/1.1 503")), third[:300]
        assert _localize_count(client, "overloaded") == overloaded_before + 1
        for sock in socks[:2]:
            data, _ = _read_until_closed(sock, BODY_TIMEOUT_S + 4.0)
            assert data.startswith(b"HTTP/1.1 408"), data[:200]
    finally:
        for sock in socks:
            sock.close()
    assert _post(client, *multipart(frames[0][0])).status_code == 200


def _localize_count(client, code: str) -> float:
    """cadreg_requests_total of the localize route with this code, over HTTP."""
    return sum(float(line.rsplit(" ", 1)[1]) for line in client.get("/metrics").text.splitlines()
               if line.startswith("cadreg_requests_total{") and f'code="{code}"' in line and "localize" in line)


def test_a_client_that_leaves_mid_body_is_counted_as_such_not_as_a_server_error(server, client) -> None:
    left, internal = _localize_count(client, "client_disconnected"), _localize_count(client, "internal")
    with _connect(server) as sock:
        sock.sendall(_head("POST", f"/v1/sites/{SITE}/localize", 1_000_000) + b"x" * 1000)
        time.sleep(0.3)
    deadline = time.monotonic() + 10.0
    while _localize_count(client, "client_disconnected") == left and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _localize_count(client, "client_disconnected") == left + 1
    assert _localize_count(client, "internal") == internal


def test_the_site_routes_422_is_the_error_body_in_the_openapi_document(client) -> None:
    responses = client.get("/openapi.json").json()["paths"]["/v1/sites/{site_id}"]["get"]["responses"]
    assert responses["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    body = _error(client.get("/v1/sites/bad%20id"), 422, "invalid_input")
    assert set(body) == {"code", "message", "request_id", "detail"}


def test_a_body_cut_short_is_named_so_not_as_a_missing_part(client, frames) -> None:
    files, data = multipart(frames[0][0])
    whole = client.build_request("POST", f"/v1/sites/{SITE}/localize", files=files, data=data)
    body = whole.read()
    r = client.post(f"/v1/sites/{SITE}/localize", content=body[: body.rindex(b"--\r\n")],  # the closing "--" gone
                    headers={"content-type": whole.headers["content-type"]})
    assert "no closing boundary" in _error(r, 422, "invalid_frame")["message"]


def test_an_empty_part_is_named_empty_not_missing(client, frames) -> None:
    files, data = multipart(frames[0][0])
    files = {**files, "color": ("color.png", b"", "image/png")}
    body = _error(_post(client, files, data), 422, "invalid_frame")
    assert body["message"] == "part color is empty" and body["detail"] == {"part": "color"}, body


def test_a_client_answered_keeps_a_usable_server(client, frames) -> None:
    assert client.get("/healthz").status_code == 200
    assert _post(client, *multipart(frames[0][0])).status_code == 200
