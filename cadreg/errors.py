"""The one error tree of cadreg.

    CadregError                      base of everything cadreg raises on purpose
    ├── InputError                   something handed to cadreg is wrong; fix the input and retry
    │   ├── InvalidArgument          a value handed to a core function outside its domain (an array's shape, an
    │   │                            unknown method name); also a ValueError, as Python callers expect
    │   ├── InvalidFrame             an RGB-D frame that cannot be registered (sizes, dtypes, intrinsics, empty depth,
    │   │                            a label set the site has no map for)
    │   ├── InvalidFileError         a file that is missing, unreadable or malformed (names the file)
    │   │   └── BundleIntegrityError a site bundle whose files do not match the sha256 in its site.json
    │   └── ConfigError              parameters outside their bounds
    ├── UnknownSite                  a site id nobody loaded
    └── ServiceError                 raised by runners around the core (the service), never by the algorithm
        ├── PayloadTooLarge          an upload over the configured limit
        ├── Overloaded               the bounded queue is full; retry after `retry_after_s`
        ├── RequestTimeout           the request ran past its deadline
        └── WorkerCrashed            the worker process holding the request died

A localization that runs but finds no pose is not an error: it is a result whose `status` says why
(`no_objects`, `no_match`, `low_overlap`, `failed`). The core never returns an identity pose to mean failure.

The service maps each class to one HTTP status and one stable wire `code` (see `service/errors.py`); the clients
raise the class of the same name for each code.
"""

from __future__ import annotations

from typing import Any


class CadregError(Exception):
    """Base class; `code` is the stable wire code, `detail` extra JSON-able facts."""

    code = "internal"

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.detail = dict(detail or {})


class InputError(CadregError):
    code = "invalid_input"


class InvalidArgument(InputError, ValueError):
    code = "invalid_input"


class InvalidFrame(InputError):
    code = "invalid_frame"


class InvalidFileError(InputError):
    """A file cadreg was asked to read is missing or malformed; the message names the file."""

    code = "invalid_file"

    def __init__(self, path: Any, reason: str, *, detail: dict[str, Any] | None = None) -> None:
        self.path = str(path)
        super().__init__(f"{self.path}: {reason}", detail={"path": self.path, **(detail or {})})


class BundleIntegrityError(InvalidFileError):
    code = "bundle_integrity"


class ConfigError(InputError):
    code = "invalid_config"


class UnknownSite(CadregError):
    code = "unknown_site"


class ServiceError(CadregError):
    code = "internal"


class PayloadTooLarge(ServiceError):
    code = "payload_too_large"


class Overloaded(ServiceError):
    code = "overloaded"

    def __init__(self, message: str, *, retry_after_s: float = 1.0, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message, detail={"retry_after_s": retry_after_s, **(detail or {})})
        self.retry_after_s = retry_after_s


class RequestTimeout(ServiceError):
    code = "timeout"


class WorkerCrashed(ServiceError):
    code = "worker_crashed"
