"""Typed errors of the cadreg clients: one class per wire code of the service, plus the client's own failures.

    ClientError (cadreg.errors.CadregError)   base of everything a client raises
    ├── ServerError                           the service answered with an error body {code, message, request_id, detail}
    │   ├── InputError        invalid_input       422   (also a cadreg.errors.InputError)
    │   ├── InvalidFrame      invalid_frame       422   (also a cadreg.errors.InvalidFrame)
    │   ├── InvalidFileError  invalid_file        422
    │   ├── BundleIntegrityError bundle_integrity 422
    │   ├── ConfigError       invalid_config      422
    │   ├── UnknownSite       unknown_site        404
    │   ├── PayloadTooLarge   payload_too_large   413
    │   ├── Overloaded        overloaded          503 + Retry-After   retried
    │   ├── WorkerCrashed     worker_crashed      503 + Retry-After   retried
    │   ├── RequestTimeout    timeout             504                 never retried (the work may still be running)
    │   ├── Unauthorized      unauthorized        401
    │   ├── BodyTimeout       body_timeout        408   the request body did not arrive in time
    │   ├── ClientDisconnected client_disconnected 499  (logged and counted by the service; no client reads it)
    │   └── InternalError     internal            500
    ├── Unreachable        unreachable   no connection, connection dropped, or no zenoh queryable answered; retried
    ├── ClientTimeout      client_timeout the client's own read/query deadline passed (also a RequestTimeout); not retried
    └── BadResponse        bad_response  an answer outside the wire contract (not JSON, wrong shape)

Each server class also derives from the cadreg core class of the same name (`cadreg.errors`, `service.errors`), so
`except cadreg.errors.Overloaded` catches the client's `Overloaded` too. `ERRORS_BY_CODE` is total over the codes of
`service.errors.ERROR_TABLE` (tests/test_clients_errors.py checks it).
"""

from __future__ import annotations

import math
from typing import Any

from cadreg import errors as core
import service.errors as wire

RETRYABLE_CODES = frozenset({"overloaded", "worker_crashed", "unreachable"})


class ClientError(core.CadregError):
    """Base of the client errors.

    code : stable wire code (the service's, or a client-only one: unreachable, client_timeout, bad_response).
    status : HTTP status of the answer, None over zenoh or when nothing was answered.
    request_id : the service's id for the request, when it sent one.
    retry_after_s : seconds the service asked us to wait (Retry-After), None when it did not say.
    """

    code = "internal"

    # The core classes have differing __init__ signatures (InvalidFileError takes a path); set their attributes
    # here instead of calling them, so every client class shares one constructor.
    def __init__(
        self,
        message: str,
        *,
        status: int | None = None,
        request_id: str | None = None,
        detail: dict[str, Any] | None = None,
        retry_after_s: float | None = None,
    ) -> None:
        Exception.__init__(self, message)
        self.message = message
        self.detail = dict(detail or {})
        self.status = status
        self.request_id = request_id
        self.retry_after_s = retry_after_s
        if isinstance(self, core.InvalidFileError):
            self.path = str(self.detail.get("path", ""))

    @property
    def retryable(self) -> bool:
        return self.code in RETRYABLE_CODES

    def __str__(self) -> str:
        where = f" (HTTP {self.status})" if self.status else ""
        rid = f" [request {self.request_id}]" if self.request_id else ""
        return f"{self.code}{where}: {self.message}{rid}"


class ServerError(ClientError):
    """The service answered with an error body."""


class InputError(ServerError, core.InputError):
    code = "invalid_input"


class InvalidFrame(ServerError, core.InvalidFrame):
    code = "invalid_frame"


class InvalidFileError(ServerError, core.InvalidFileError):
    code = "invalid_file"


class BundleIntegrityError(ServerError, core.BundleIntegrityError):
    code = "bundle_integrity"


class ConfigError(ServerError, core.ConfigError):
    code = "invalid_config"


class UnknownSite(ServerError, core.UnknownSite):
    code = "unknown_site"


class PayloadTooLarge(ServerError, core.PayloadTooLarge):
    code = "payload_too_large"


class Overloaded(ServerError, core.Overloaded):
    code = "overloaded"


class WorkerCrashed(ServerError, core.WorkerCrashed):
    code = "worker_crashed"


class RequestTimeout(ServerError, core.RequestTimeout):
    code = "timeout"


class Unauthorized(ServerError, wire.Unauthorized):
    code = "unauthorized"


class BodyTimeout(ServerError, wire.BodyTimeout):
    code = "body_timeout"


class ClientDisconnected(ServerError, wire.ClientDisconnected):
    code = "client_disconnected"


class InternalError(ServerError, core.ServiceError):
    code = "internal"


class Unreachable(ClientError):
    """No connection to the service (refused, dropped before an answer), or no zenoh queryable answered."""

    code = "unreachable"


class ClientTimeout(ClientError, core.RequestTimeout):
    """The client's own deadline (HTTP read timeout, zenoh query timeout) passed before an answer."""

    code = "client_timeout"


class BadResponse(ClientError):
    """The service (or something in front of it) answered outside the wire contract."""

    code = "bad_response"


ERRORS_BY_CODE: dict[str, type[ServerError]] = {
    cls.code: cls
    for cls in (
        InputError, InvalidFrame, InvalidFileError, BundleIntegrityError, ConfigError, UnknownSite,
        PayloadTooLarge, Overloaded, WorkerCrashed, RequestTimeout, Unauthorized, BodyTimeout, ClientDisconnected,
        InternalError,
    )
}


def error_from_body(
    body: Any, *, status: int | None = None, retry_after_s: float | None = None
) -> ClientError:
    """The typed error for a wire error body `{code, message, request_id, detail}`.

    A body that is not such an object gives BadResponse. An unknown code gives a ServerError that keeps the code
    (a newer service may add codes). The wait comes from `detail.retry_after_s` (the service's own estimate, in
    fractions of a second) or else the argument (the HTTP Retry-After header, whole seconds).
    """
    if not isinstance(body, dict) or not isinstance(body.get("code"), str):
        return BadResponse(f"not an error body: {str(body)[:200]!r}", status=status)
    code = body["code"]
    detail = body.get("detail") if isinstance(body.get("detail"), dict) else {}
    hint_s = _seconds(detail.get("retry_after_s"))
    if hint_s is not None:
        retry_after_s = hint_s
    cls = ERRORS_BY_CODE.get(code)
    kwargs = dict(
        status=status,
        request_id=body.get("request_id") if isinstance(body.get("request_id"), str) else None,
        detail=detail,
        retry_after_s=retry_after_s,
    )
    message = str(body.get("message", code))
    if cls is None:
        exc = ServerError(message, **kwargs)
        exc.code = code
        return exc
    return cls(message, **kwargs)


def _seconds(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v >= 0 else None
