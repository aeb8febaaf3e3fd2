"""HTTP clients of the cadreg service (httpx): `Client` (sync) and `AsyncClient`.

    with Client("http://127.0.0.1:8080") as c:
        result = c.localize("scene0470", frame)            # a cadreg Frame
        result = c.localize("scene0470", ("frames/", 3))   # frame 3 of a recorded-frames folder, files sent as they are
        c.sites(); c.site("scene0470"); c.health(); c.ready()

`localize` returns the result JSON as a dict (`LocalizationResult.to_dict()` + `request_id`, `site_version`);
`pose_of(result)` gives its 4×4 `T_map_camera` or None. Errors raise the typed classes of `clients.errors`, one per
wire code; 503 answers and connection failures are retried by `RetryPolicy` (exponential backoff with jitter, at
least the service's Retry-After), 4xx and 504 never. A Retry-After holds the whole client (`ClientPause`): fresh
requests wait out the pause too instead of overtaking the ones being retried. Timeouts: `connect_timeout_s` to open a connection,
`read_timeout_s` for the answer (a localization takes seconds on a busy machine), `deadline_s` for a whole call
including its retries.
"""

from __future__ import annotations

import asyncio
import email.utils
import math
import time
from dataclasses import replace
from datetime import timezone
from typing import Any, Callable
from urllib.parse import quote

import httpx
import numpy as np

from .core import ClientCore
from .errors import BadResponse, ClientError, ClientTimeout, Unreachable, error_from_body
from .frames import EncodedFrame, FrameLike
from .retry import RetryHook, RetryPolicy

DEFAULT_CONNECT_TIMEOUT_S = 5.0
DEFAULT_READ_TIMEOUT_S = 120.0

# Transport failures after which the request surely did not complete on the server or is safe to repeat
# (localization has no side effects). Read/write timeouts are not here: the server may still be working on it.
_RETRYABLE_TRANSPORT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError, httpx.ReadError,
                        httpx.WriteError, httpx.PoolTimeout)


def pose_of(result: dict[str, Any]) -> np.ndarray | None:
    """The (4, 4) float64 T_map_camera of a result dict, None when the localization gave no pose."""
    T = result.get("T_map_camera")
    return None if T is None else np.asarray(T, dtype=float)


def parse_retry_after(value: str | None, *, now: float | None = None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds or an HTTP date), None when absent or malformed."""
    if value is None:
        return None
    value = value.strip()
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError):
            return None
        if when.tzinfo is None:
            when = when.replace(tzinfo=timezone.utc)
        seconds = when.timestamp() - (time.time() if now is None else now)
    if not math.isfinite(seconds):
        return None
    return max(0.0, seconds)


def _error_from_response(response: httpx.Response) -> ClientError:
    retry_after = parse_retry_after(response.headers.get("Retry-After"))
    try:
        body = response.json()
    except ValueError:
        body = None
    exc = error_from_body(body, status=response.status_code, retry_after_s=retry_after)
    if isinstance(exc, BadResponse) and response.status_code == 503:
        # a proxy or a server still starting says 503 without our body: the same "come back later"
        exc = Unreachable(f"HTTP 503 without an error body: {response.text[:200]!r}", status=503,
                          retry_after_s=retry_after)
    return exc


def _transport_error(exc: httpx.HTTPError, url: str) -> ClientError:
    if isinstance(exc, _RETRYABLE_TRANSPORT):
        return Unreachable(f"{type(exc).__name__} on {url}: {exc}")
    if isinstance(exc, httpx.TimeoutException):
        return ClientTimeout(f"{type(exc).__name__} on {url}: no answer in time")
    return Unreachable(f"{type(exc).__name__} on {url}: {exc}")


def _result(response: httpx.Response) -> Any:
    if response.status_code >= 400:
        raise _error_from_response(response)
    try:
        return response.json()
    except ValueError:
        raise BadResponse(f"answer is not JSON: {response.text[:200]!r}", status=response.status_code) from None


class _Base(ClientCore):
    def __init__(
        self,
        base_url: str,
        *,
        connect_timeout_s: float,
        read_timeout_s: float,
        deadline_s: float | None,
        retry: RetryPolicy | None,
        on_retry: RetryHook | None,
        top_k: int | None,
    ) -> None:
        super().__init__(retry=retry, on_retry=on_retry, deadline_s=deadline_s, top_k=top_k)
        self.base_url = base_url.rstrip("/")
        self.timeout = httpx.Timeout(read_timeout_s, connect=connect_timeout_s)

    @staticmethod
    def _localize_path(site_id: str) -> str:
        return f"/v1/sites/{quote(site_id, safe='')}/localize"


class Client(_Base):
    """Synchronous client; thread-safe like httpx.Client (one connection pool shared by threads).

    base_url : e.g. "http://127.0.0.1:8080".
    retry : RetryPolicy (default: 4 retries, 0.2 s base backoff); on_retry(attempt, error, delay_s) is told of each.
    transport : an httpx transport (tests pass httpx.MockTransport).
    sleep : the function used to wait between retries (tests record instead of sleeping).
    """

    def __init__(
        self,
        base_url: str,
        *,
        connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        deadline_s: float | None = None,
        retry: RetryPolicy | None = None,
        on_retry: RetryHook | None = None,
        top_k: int | None = None,
        transport: httpx.BaseTransport | None = None,
        headers: dict[str, str] | None = None,
        sleep: Callable[[float], None] = time.sleep,
        max_connections: int = 100,
    ) -> None:
        super().__init__(base_url, connect_timeout_s=connect_timeout_s, read_timeout_s=read_timeout_s,
                         deadline_s=deadline_s, retry=retry, on_retry=on_retry, top_k=top_k)
        self._sleep = sleep
        limits = httpx.Limits(max_connections=max_connections, max_keepalive_connections=max_connections)
        self._http = httpx.Client(base_url=self.base_url, timeout=self.timeout, transport=transport,
                                  headers=headers, limits=limits)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> Any:
        def send() -> Any:
            try:
                return _result(self._http.request(method, path, **kwargs))
            except httpx.HTTPError as exc:
                raise _transport_error(exc, self.base_url + path) from None

        return self._retry_loop.call(send, self._sleep)

    def localize(
        self, site_id: str, frame: FrameLike, *, frame_id: str | None = None, top_k: int | None = None,
        session_id: str | None = None,
    ) -> dict[str, Any]:
        """Localize one frame in a site; returns the result dict (raises a clients.errors class on failure).

        frame : cadreg Frame (encoded as PNG), EncodedFrame (sent as is), or (folder, index) of a recorded-frames
            folder (its files sent as they are).
        session_id : a tracking session: its frames are tracked from the last pose (`diagnostics.mode`); send a
            session's frames one at a time, in order.
        """
        enc = with_session(self.encode(frame, frame_id=frame_id, top_k=top_k), session_id)
        files, data = enc.multipart()
        return self._request("POST", self._localize_path(site_id), files=files, data=data)

    def sites(self) -> list[dict[str, Any]]:
        """[{site_id, version}, ...] of the loaded sites."""
        return self._request("GET", "/v1/sites")["sites"]

    def site(self, site_id: str) -> dict[str, Any]:
        """{site_id, version, nodes, edges, points, classes} of one site (UnknownSite when not loaded)."""
        return self._request("GET", f"/v1/sites/{quote(site_id, safe='')}")

    def health(self) -> dict[str, Any]:
        return self._request("GET", "/healthz")

    def ready(self) -> dict[str, Any]:
        return self._request("GET", "/readyz")

    def metrics_text(self) -> str:
        """The Prometheus exposition text of /metrics."""
        response = self._http.get("/metrics")
        if response.status_code >= 400:
            raise _error_from_response(response)
        return response.text


class AsyncClient(_Base):
    """The same client for asyncio (httpx.AsyncClient); arguments as `Client`, `sleep` is a coroutine function."""

    def __init__(
        self,
        base_url: str,
        *,
        connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        deadline_s: float | None = None,
        retry: RetryPolicy | None = None,
        on_retry: RetryHook | None = None,
        top_k: int | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
        headers: dict[str, str] | None = None,
        sleep: Callable[[float], Any] = asyncio.sleep,
        max_connections: int = 100,
    ) -> None:
        super().__init__(base_url, connect_timeout_s=connect_timeout_s, read_timeout_s=read_timeout_s,
                         deadline_s=deadline_s, retry=retry, on_retry=on_retry, top_k=top_k)
        self._sleep = sleep
        limits = httpx.Limits(max_connections=max_connections, max_keepalive_connections=max_connections)
        self._http = httpx.AsyncClient(base_url=self.base_url, timeout=self.timeout, transport=transport,
                                       headers=headers, limits=limits)

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, **kwargs: Any) -> Any:
        async def send() -> Any:
            try:
                return _result(await self._http.request(method, path, **kwargs))
            except httpx.HTTPError as exc:
                raise _transport_error(exc, self.base_url + path) from None

        return await self._retry_loop.acall(send, self._sleep)

    async def localize(
        self, site_id: str, frame: FrameLike, *, frame_id: str | None = None, top_k: int | None = None,
        session_id: str | None = None,
    ) -> dict[str, Any]:
        """As `Client.localize`. Encoding a Frame or a folder entry runs here, on the event loop's thread; encode
        up front (`clients.frames.encode_*`) and pass EncodedFrame in hot loops."""
        enc = with_session(self.encode(frame, frame_id=frame_id, top_k=top_k), session_id)
        files, data = enc.multipart()
        return await self._request("POST", self._localize_path(site_id), files=files, data=data)

    async def sites(self) -> list[dict[str, Any]]:
        return (await self._request("GET", "/v1/sites"))["sites"]

    async def site(self, site_id: str) -> dict[str, Any]:
        return await self._request("GET", f"/v1/sites/{quote(site_id, safe='')}")

    async def health(self) -> dict[str, Any]:
        return await self._request("GET", "/healthz")

    async def ready(self) -> dict[str, Any]:
        return await self._request("GET", "/readyz")

    async def metrics_text(self) -> str:
        response = await self._http.get("/metrics")
        if response.status_code >= 400:
            raise _error_from_response(response)
        return response.text


def with_session(enc: EncodedFrame, session_id: str | None) -> EncodedFrame:
    """The frame with `session_id` in its meta (unchanged when None)."""
    if session_id is None:
        return enc
    return replace(enc, meta=enc.meta.model_copy(update={"session_id": session_id}))


__all__ = ["Client", "AsyncClient", "pose_of", "parse_retry_after", "with_session"]
