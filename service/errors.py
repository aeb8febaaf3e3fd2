"""One table from error type to HTTP status and wire code, shared by HTTP, zenoh and the clients.

The error classes are cadreg's (`cadreg/errors.py`) plus `Unauthorized` (admin routes only, a service matter).
Every body is `{"code", "message", "request_id", "detail"}` (`service.schemas.ErrorBody`); HTTP adds `Retry-After`
for the codes marked retryable. Clients turn a body back into the class of the same code with `error_from_body`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from cadreg.errors import (
    BundleIntegrityError,
    CadregError,
    ConfigError,
    InputError,
    InvalidFileError,
    InvalidFrame,
    Overloaded,
    PayloadTooLarge,
    RequestTimeout,
    ServiceError,
    UnknownSite,
    WorkerCrashed,
)


class Unauthorized(ServiceError):
    """An admin route was called without the right bearer token."""

    code = "unauthorized"


class BodyTimeout(InputError):
    """A request body did not arrive whole within `http_body_timeout_s` of its headers (a slow or stalled upload)."""

    code = "body_timeout"


class ClientDisconnected(InputError):
    """The client closed its connection before its request body was whole. Nobody receives the answer: the code is
    what the request log and the metrics count it as (not a server error)."""

    code = "client_disconnected"


@dataclass(frozen=True)
class ErrorSpec:
    status: int
    code: str
    retry_after: bool = False  # send Retry-After: the client should try again later


# Most specific first: the lookup walks the MRO of the raised class, so a subclass needs its own row only when its
# status differs from its parent's.
ERROR_TABLE: dict[type[CadregError], ErrorSpec] = {
    InvalidFrame: ErrorSpec(422, "invalid_frame"),
    BundleIntegrityError: ErrorSpec(422, "bundle_integrity"),
    InvalidFileError: ErrorSpec(422, "invalid_file"),
    ConfigError: ErrorSpec(422, "invalid_config"),
    InputError: ErrorSpec(422, "invalid_input"),
    UnknownSite: ErrorSpec(404, "unknown_site"),
    PayloadTooLarge: ErrorSpec(413, "payload_too_large"),
    Overloaded: ErrorSpec(503, "overloaded", retry_after=True),
    WorkerCrashed: ErrorSpec(503, "worker_crashed", retry_after=True),
    RequestTimeout: ErrorSpec(504, "timeout"),
    Unauthorized: ErrorSpec(401, "unauthorized"),
    BodyTimeout: ErrorSpec(408, "body_timeout"),
    ClientDisconnected: ErrorSpec(499, "client_disconnected"),  # nginx's status for it; no client reads it
    ServiceError: ErrorSpec(500, "internal"),
    CadregError: ErrorSpec(500, "internal"),
}

INTERNAL = ErrorSpec(500, "internal")
DEFAULT_RETRY_AFTER_S = 1.0

# code -> the class clients raise for it (the most specific class carrying that code)
CODE_TO_ERROR: dict[str, type[CadregError]] = {}
for _cls, _spec in ERROR_TABLE.items():
    CODE_TO_ERROR.setdefault(_spec.code, _cls)


def spec_for(exc: BaseException | type[BaseException]) -> ErrorSpec:
    """The status/code row for an exception (instance or class); anything not ours is `internal` 500."""
    cls = exc if isinstance(exc, type) else type(exc)
    for base in cls.__mro__:
        if base in ERROR_TABLE:
            return ERROR_TABLE[base]
    return INTERNAL


def retry_after_s(exc: BaseException) -> float:
    """Seconds to put in Retry-After for a retryable error."""
    value = getattr(exc, "retry_after_s", None)
    if value is None and isinstance(exc, CadregError):
        value = exc.detail.get("retry_after_s")
    try:
        value = float(value) if value is not None else DEFAULT_RETRY_AFTER_S
    except (TypeError, ValueError):
        value = DEFAULT_RETRY_AFTER_S
    return value if math.isfinite(value) and value > 0 else DEFAULT_RETRY_AFTER_S


def error_body(exc: BaseException, request_id: str | None = None) -> dict[str, Any]:
    """The wire body for `exc`. Errors not ours never leak their text (it may hold paths or internals)."""
    spec = spec_for(exc)
    if isinstance(exc, CadregError):
        message, detail = exc.message, dict(exc.detail)
    else:
        message, detail = "internal error", {}
    if spec.retry_after:
        detail.setdefault("retry_after_s", retry_after_s(exc))
    return {"code": spec.code, "message": message, "request_id": request_id, "detail": _jsonable(detail)}


def http_headers(exc: BaseException, request_id: str | None = None) -> dict[str, str]:
    """Response headers for an error: Retry-After (whole seconds, rounded up) for retryable codes, X-Request-ID."""
    headers: dict[str, str] = {}
    if spec_for(exc).retry_after:
        headers["Retry-After"] = str(max(1, math.ceil(retry_after_s(exc))))
    if request_id:
        headers["X-Request-ID"] = request_id
    return headers


def error_from_body(body: dict[str, Any]) -> CadregError:
    """The typed error a client raises for an error body; unknown codes become a plain `CadregError`."""
    code = str(body.get("code", "internal"))
    message = str(body.get("message", code))
    detail = body.get("detail") or {}
    if not isinstance(detail, dict):
        detail = {"detail": detail}
    if body.get("request_id"):
        detail = {**detail, "request_id": body["request_id"]}
    cls = CODE_TO_ERROR.get(code, CadregError)
    if issubclass(cls, InvalidFileError):
        exc: CadregError = cls.__new__(cls)
        CadregError.__init__(exc, message, detail=detail)
        exc.path = str(detail.get("path", ""))
    elif cls is Overloaded:
        exc = Overloaded(message, retry_after_s=float(detail.get("retry_after_s", DEFAULT_RETRY_AFTER_S)), detail=detail)
    else:
        exc = cls(message, detail=detail)
    if cls is CadregError and code != "internal":
        exc.code = code  # keep an unknown code visible rather than folding it into "internal"
    return exc


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return str(value)
