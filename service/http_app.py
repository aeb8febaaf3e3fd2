"""The HTTP front end (FastAPI): `create_app(settings)`.

Routes (DESIGN §6):
    POST /v1/sites/{site_id}/localize   multipart/form-data: color, depth, labels (optional), meta (FrameMeta JSON)
    GET  /v1/sites                      [{site_id, version}]
    GET  /v1/sites/{site_id}            {site_id, version, nodes, edges, points, classes}
    PUT  /v1/sites/{site_id}            admin (Bearer token): upload a bundle as a tar/zip archive, swapped in live
    POST /v1/sites/{site_id}/reload     admin: reload the bundle from the sites directory, swapped in live
    GET  /healthz, /readyz, /metrics    liveness, readiness (sites loaded, pool up), Prometheus
Every error is `{code, message, request_id, detail}` with the status of `service.errors.ERROR_TABLE`. Request ids
come from `X-Request-ID` (when sane) or are made here; they go back in the header, the body and the log line.
Bodies are size-checked before anything is decoded: a declared Content-Length over the route's cap is refused at
once, before a byte of the body is read (and the connection closed when it is far over: nobody waits for it), then
bytes are counted while reading. The event loop never decodes images: parts go to the worker pool as bytes. uvicorn
runs with `uvicorn_options(settings)`: bounded headers, and a deadline for them (`GuardedH11Protocol`).
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import re
import time
import traceback
import uuid
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator

import h11
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.formparsers import MultiPartException, MultiPartParser, parse_options_header
from starlette.requests import ClientDisconnect
from uvicorn.protocols.http.h11_impl import H11Protocol

from cadreg import __version__
from cadreg.errors import CadregError, InputError, InvalidFrame, Overloaded, PayloadTooLarge

from .codec import MAX_LISTED_ERRORS, PART_NAMES, encode_result
from .errors import BodyTimeout, ClientDisconnected, Unauthorized, error_body, http_headers, spec_for
from .logs import log_event
from .registry import check_site_id
from .runtime import Service
from .schemas import ErrorBody, Health, LocalizeResponse, Readiness, SiteInfo, SiteList, SiteSummary
from .settings import Settings

log = logging.getLogger("cadreg.service.http")

_REQUEST_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
_DRAIN_FACTOR = 4  # read (and drop) up to this many times the limit, so the client sees the 413 and not a reset


def _error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorBody, "description": "error body"} for code in codes}


_LOCALIZE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["color", "depth", "meta"],
                    "properties": {
                        "color": {"type": "string", "format": "binary", "description": "PNG or JPEG, 8-bit RGB"},
                        "depth": {"type": "string", "format": "binary",
                                  "description": "PNG, 16-bit grayscale, depth_scale units per metre, 0 = invalid"},
                        "labels": {"type": "string", "format": "binary",
                                   "description": "optional PNG, 8- or 16-bit label ids, colour's size"},
                        "meta": {"type": "string", "description": "JSON text of FrameMeta (schema FrameMeta)"},
                    },
                }
            }
        },
    }
}


class _JSON(JSONResponse):
    """JSON through the wire codec: compact, NaN-free."""

    def render(self, content: Any) -> bytes:
        return encode_result(content)


def _error_response(exc: BaseException, request: Request) -> Response:
    request_id = getattr(request.state, "request_id", None)
    body = error_body(exc, request_id)
    request.state.error_code = body["code"]
    headers = http_headers(exc, request_id)
    if getattr(request.state, "close_connection", False):
        headers = {**headers, "Connection": "close"}
    return _JSON(body, status_code=spec_for(exc).status, headers=headers)


def _refuse_declared_length(request: Request, limit: int, what: str) -> None:
    """413 at once, before any of the body is read, when the declared Content-Length is over `limit`. uvicorn reads
    and drops the rest of a body nobody read, so a client that sends what it declared still sees the 413; one that
    declares far more than the limit (or lies about a slow trickle) has its connection closed after the answer."""
    declared = request.headers.get("content-length")
    if declared is None:
        return
    if not declared.isdigit():
        raise InputError("Content-Length is not a number")
    n = int(declared)
    if n > limit:
        request.state.close_connection = n > _DRAIN_FACTOR * limit
        raise PayloadTooLarge(f"{what} of {n} bytes is over the {limit}-byte limit", detail={"limit_bytes": limit})


class BodyBudget:
    """The bytes of request bodies held in memory at once, over every connection (`http_max_buffered_bytes`). A
    body's bytes are taken as they arrive and given back once its parts are in the pool's queue (whose depth bounds
    what waits there) or it is refused; a chunk that would pass the budget is refused (503 `overloaded`, the
    connection closed). Without it eight connections that each sent 30 MB and then waited held 240 MB, and more
    connections more. One event loop reads every body: no lock."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.held = 0

    def take(self, request: Request, n: int) -> None:
        if self.held + n > self.limit:
            request.state.close_connection = True
            raise Overloaded(f"request bodies in memory would pass the {self.limit}-byte budget "
                             "(http_max_buffered_bytes)", detail={"limit_bytes": self.limit})
        self.held += n
        request.state.body_bytes_held = getattr(request.state, "body_bytes_held", 0) + n

    def give_back(self, request: Request) -> None:
        self.held -= getattr(request.state, "body_bytes_held", 0)
        request.state.body_bytes_held = 0


def _refuse_long_headers(request: Request, limit: int) -> None:
    """413, and the connection closed, when the request line and headers pass `limit` bytes. uvicorn's h11 checks
    its limit only while the head is still incomplete (400 then): a head of 17-100 KB that arrived in one read went
    through (`http_max_header_bytes`). Here, and not in `GuardedH11Protocol`, since the app is the first to see a
    whole head; the query string counts (uvicorn's raw_path leaves it out)."""
    scope = request.scope
    line = len(scope["method"]) + len(scope.get("raw_path") or b"") + 1 + len(scope.get("query_string") or b"") + 11
    size = line + sum(len(k) + len(v) + 4 for k, v in scope["headers"])  # "name: value\r\n" each
    if size > limit:
        request.state.close_connection = True
        raise PayloadTooLarge(f"request headers of {size} bytes are over the {limit}-byte limit "
                              "(http_max_header_bytes)", detail={"limit_bytes": limit})


async def _read_body(request: Request, limit: int, budget: BodyBudget, timeout_s: float) -> bytes:
    """The request body, refusing (413) anything over `limit` bytes before it is decoded, one that has not arrived
    whole `timeout_s` after its headers (408 `body_timeout`: a stalled or trickled upload held its connection and
    its bytes for as long as the client liked), and any chunk past the shared `budget`. A client that disconnects
    mid-body is `client_disconnected` (`create_app`'s handler). The caller gives the budget back (`give_back`)."""
    _refuse_declared_length(request, limit, "request body")
    too_large: int | None = None
    chunks: list[bytes] = []
    total = 0
    try:
        async with asyncio.timeout(timeout_s):
            async for chunk in request.stream():
                total += len(chunk)
                if too_large is None and total > limit:
                    too_large = total
                    budget.give_back(request)  # what it held is dropped: the rest is drained, not kept
                if too_large is not None:
                    chunks.clear()
                    if total > _DRAIN_FACTOR * limit:
                        break
                    continue
                budget.take(request, len(chunk))
                chunks.append(chunk)
    except TimeoutError:
        request.state.close_connection = True
        raise BodyTimeout(f"the request body was not whole {timeout_s:g} s after its headers ({total} bytes "
                          "arrived; http_body_timeout_s)", detail={"timeout_s": timeout_s, "bytes": total}) from None
    if too_large is not None:
        raise PayloadTooLarge(f"request body of {too_large}+ bytes is over the {limit}-byte limit",
                              detail={"limit_bytes": limit})
    return b"".join(chunks)


async def _parse_multipart(request: Request, body: bytes) -> tuple[dict[str, bytes], str]:
    content_type = request.headers.get("content-type", "")
    if not content_type.startswith("multipart/form-data"):
        raise InvalidFrame(f"expected multipart/form-data, got {content_type or 'no content type'!r}")

    boundary = parse_options_header(content_type)[1].get(b"boundary")
    if boundary and b"--" + boundary + b"--" not in body:
        # The parser takes a body cut short for one whose last parts are missing ("missing part: meta").
        raise InvalidFrame("malformed multipart body: it has no closing boundary (cut short?)")

    async def once() -> AsyncIterator[bytes]:
        yield body

    parser = MultiPartParser(request.headers, once(), max_files=len(PART_NAMES) + 1, max_fields=2,
                             max_part_size=1024 * 1024)
    try:
        form = await parser.parse()
    except MultiPartException as exc:
        raise InvalidFrame(f"malformed multipart body: {exc.message}") from None
    parts: dict[str, bytes] = {}
    meta: str | None = None
    try:
        for name, value in form.multi_items():
            if name == "meta":
                if meta is not None:
                    raise InvalidFrame("part 'meta' given twice", detail={"part": "meta"})
                meta = (await value.read()).decode("utf-8") if isinstance(value, UploadFile) else value
            elif name in PART_NAMES:
                if not isinstance(value, UploadFile):
                    raise InvalidFrame(f"part {name!r} must be a file part (binary), not a text field")
                if name in parts:
                    raise InvalidFrame(f"part {name!r} given twice", detail={"part": name})
                parts[name] = await value.read()
            else:
                raise InvalidFrame(f"unknown part {name!r} (expected {', '.join(PART_NAMES)}, meta)")
    except UnicodeDecodeError:
        raise InvalidFrame("meta is not UTF-8 text") from None
    finally:
        await form.close()
    if meta is None:
        raise InvalidFrame("missing part: meta", detail={"part": "meta"})
    return parts, meta


def create_app(settings: Settings, service: Service | None = None, zenoh_server: Any = None) -> FastAPI:
    """The HTTP app. Its lifespan starts the service (registry, worker pool) and the zenoh front end unless the
    caller started them already (`cadreg serve` does, to fail with a clear message), and stops both at shutdown."""
    service = service or Service(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        nonlocal zenoh_server
        try:
            if not service.started.is_set():
                await asyncio.to_thread(service.start)
            if settings.zenoh_enabled and zenoh_server is None:
                from .zenoh_server import ZenohServer

                zenoh_server = ZenohServer(service, settings)
                await asyncio.to_thread(zenoh_server.start)
            app.state.zenoh = zenoh_server
            yield
        finally:
            if zenoh_server is not None:
                await asyncio.to_thread(zenoh_server.stop)
            await asyncio.to_thread(service.stop)

    app = FastAPI(
        title="cadreg",
        version=__version__,
        description="Localize an RGB-D frame inside a pre-built site map (CAD-aided coarse-to-fine registration).",
        lifespan=lifespan,
    )
    app.state.service = service
    app.state.zenoh = None
    bodies = BodyBudget(settings.http_max_buffered_bytes)

    @app.middleware("http")
    async def request_context(request: Request, call_next):
        given = request.headers.get("x-request-id", "")
        request_id = given if _REQUEST_ID.match(given) else uuid.uuid4().hex
        request.state.request_id = request_id
        request.state.error_code = None
        t0 = time.perf_counter()
        try:
            _refuse_long_headers(request, settings.http_max_header_bytes)
            response = await call_next(request)
        except CadregError as exc:  # refused here, before any route ran
            response = _error_response(exc, request)
        except Exception as exc:  # anything not handled below: one 500 body, no traceback to the client
            # one JSON line, traceback included: the exception's text may carry request input
            log_event(log, "http_request_failed", logging.ERROR, request_id=request_id, path=request.url.path,
                      error=repr(exc)[:500], traceback=traceback.format_exc())
            response = _error_response(exc, request)
        response.headers["X-Request-ID"] = request_id
        elapsed = time.perf_counter() - t0
        route = request.scope.get("route")
        template = getattr(route, "path", "unmatched")
        code = request.state.error_code or ("ok" if response.status_code < 400 else str(response.status_code))
        service.metrics.observe_request("http", template, code, elapsed)
        if settings.log_requests and template not in ("/metrics", "/healthz", "/readyz"):
            site = request.path_params.get("site_id") if route is not None else None
            # the path and site id are the client's: JSON escapes a CR/LF that would forge a line of its own
            log_event(log, "http_request", request_id=request_id, method=request.method, path=request.url.path,
                      site=site[:200] if site else None, status=response.status_code, code=code,
                      ms=round(elapsed * 1e3, 1))
        return response

    @app.exception_handler(CadregError)
    async def cadreg_error(request: Request, exc: CadregError) -> Response:
        return _error_response(exc, request)

    @app.exception_handler(ClientDisconnect)
    async def client_left(request: Request, exc: ClientDisconnect) -> Response:
        # Any route that reads a body (a frame, an admin's archive): the client is gone, nobody reads the answer,
        # and it is no server error (it was a 500 with a traceback in the log).
        return _error_response(ClientDisconnected("the client closed the connection before its body was whole"),
                               request)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> Response:
        errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg"))} for e in exc.errors()]
        return _error_response(InputError("invalid request", detail={"errors": errors[:MAX_LISTED_ERRORS],
                                                                     "error_count": len(errors)}), request)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        request.state.error_code = code
        body = {"code": code, "message": str(exc.detail), "request_id": request.state.request_id, "detail": {}}
        return _JSON(body, status_code=exc.status_code, headers=dict(exc.headers or {}))

    def require_admin(request: Request) -> None:
        token = settings.admin_token.get_secret_value() if settings.admin_token is not None else None
        if not token:
            raise Unauthorized("admin routes are disabled: set CADREG_ADMIN_TOKEN")
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), token.encode()):
            raise Unauthorized("missing or wrong bearer token")

    # --- localize -----------------------------------------------------------------------------------------------

    @app.post(
        "/v1/sites/{site_id}/localize",
        response_model=LocalizeResponse,
        summary="Localize one RGB-D frame in a site",
        openapi_extra=_LOCALIZE_BODY,
        responses=_error_responses(404, 413, 422, 500, 503, 504),
    )
    async def localize(site_id: str, request: Request) -> Response:
        service.registry.get(site_id)  # 404 before reading a body for nothing
        try:
            body = await _read_body(request, settings.max_upload_bytes, bodies, settings.http_body_timeout_s)
            parts, meta = await _parse_multipart(request, body)
            del body  # the parts are what stays
            future = service.submit(site_id, parts, meta)
        finally:
            bodies.give_back(request)
        job = await asyncio.wrap_future(future)
        return _JSON(service.finish(job, site_id, request.state.request_id))

    # --- sites --------------------------------------------------------------------------------------------------

    @app.get("/v1/sites", response_model=SiteList, summary="Sites served and their bundle versions")
    async def list_sites() -> dict[str, Any]:
        return {"sites": [e.summary() for e in service.registry.entries()]}

    @app.get("/v1/sites/{site_id}", response_model=SiteInfo, responses=_error_responses(404, 422),
             summary="One site: version, graph and map sizes, classes")
    async def site_info(site_id: str) -> dict[str, Any]:
        return service.registry.get(site_id).info()

    @app.put("/v1/sites/{site_id}", response_model=SiteSummary, responses=_error_responses(401, 413, 422, 503),
             summary="Admin: upload a site bundle (tar or zip archive) and swap it in",
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
    async def upload_site(site_id: str, request: Request) -> dict[str, Any]:
        require_admin(request)
        check_site_id(site_id)
        incoming = service.registry.root / ".incoming"
        await asyncio.to_thread(incoming.mkdir, parents=True, exist_ok=True)
        archive = incoming / f"upload-{uuid.uuid4().hex}"
        try:
            await _stream_to_file(request, archive, settings.max_bundle_bytes)
            entry = await asyncio.to_thread(service.install_archive, site_id, archive)
        finally:
            await asyncio.to_thread(archive.unlink, missing_ok=True)
        return entry.summary()

    @app.post("/v1/sites/{site_id}/reload", response_model=SiteSummary, responses=_error_responses(401, 404, 422, 503),
              summary="Admin: reload a site from the sites directory and swap it in")
    async def reload_site(site_id: str, request: Request) -> dict[str, Any]:
        require_admin(request)
        check_site_id(site_id)
        entry = await asyncio.to_thread(service.reload_site, site_id)
        return entry.summary()

    # --- operations ---------------------------------------------------------------------------------------------

    @app.get("/healthz", response_model=Health, summary="Liveness")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}},
             summary="Ready when every site is loaded by the workers")
    async def readyz() -> Response:
        pool = service.pool
        body = {
            "ready": service.ready,
            "sites": [e.summary() for e in service.registry.entries()],
            "workers_alive": pool.alive() if pool else 0,
            "workers": settings.workers,
        }
        return _JSON(body, status_code=200 if body["ready"] else 503)

    @app.get("/metrics", summary="Prometheus metrics", response_class=Response)
    async def metrics() -> Response:
        return Response(service.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    if settings.test_hooks:
        @app.get("/debug/workers", include_in_schema=False)
        async def debug_workers() -> list[dict[str, Any]]:
            return service.pool.workers_info() if service.pool else []

    return app


async def _stream_to_file(request: Request, path: Path, limit: int) -> None:
    _refuse_declared_length(request, limit, "archive")
    total = 0
    with open(path, "wb") as out:
        async for chunk in request.stream():
            total += len(chunk)
            if total > limit:
                raise PayloadTooLarge(f"archive over the {limit}-byte limit", detail={"limit_bytes": limit})
            await asyncio.to_thread(out.write, chunk)
    if total == 0:
        raise InputError("empty upload: send the bundle archive as the request body")


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for request headers, which uvicorn lacks: a connection that sends
    nothing, or its headers a byte at a time, is closed `header_timeout_s` after it opened or after its last
    answer. (uvicorn's keep-alive timer stops at the first byte received and never runs on a fresh connection.)"""

    header_timeout_s = 10.0

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_deadline = self.loop.call_later(self.header_timeout_s, self._headers_overdue)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._rearm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._header_deadline.cancel()
        super().connection_lost(exc)

    def _rearm_header_deadline(self) -> None:
        self._header_deadline.cancel()
        if not self.transport.is_closing():
            self._header_deadline = self.loop.call_later(self.header_timeout_s, self._headers_overdue)

    def _headers_overdue(self) -> None:
        # IDLE: no complete request line + headers yet on this cycle (the app is not running for it)
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.close()


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """The keyword arguments of `uvicorn.run` / `uvicorn.Config` that bound what a client can hold: header size
    (h11's incomplete-event limit), header deadline, idle keep-alive."""
    protocol = type("GuardedH11Protocol", (GuardedH11Protocol,), {"header_timeout_s": settings.http_header_timeout_s})
    return {
        "host": settings.host,
        "port": settings.port,
        "http": protocol,
        "timeout_keep_alive": settings.http_keep_alive_s,
        "h11_max_incomplete_event_size": settings.http_max_header_bytes,
    }
