"""When and how long to retry: exponential backoff with jitter, honouring the service's Retry-After.

Retried: `overloaded` and `worker_crashed` (503, the service says "later") and `unreachable` (no connection, or the
connection dropped before an answer). Never retried: 4xx answers (the same request fails the same way), `timeout`
(504: the service ran out of time; the work may have run), and the client's own read timeout (the same).
"""

from __future__ import annotations

import asyncio
import random
import threading
import time
from dataclasses import dataclass, field
from typing import Awaitable, Callable, TypeVar

from .errors import ClientError

RetryHook = Callable[[int, ClientError, float], None]  # (attempt number from 1, the error, delay_s before the retry)
T = TypeVar("T")


@dataclass(frozen=True)
class RetryPolicy:
    """max_retries : retries after the first attempt (0 = never retry).
    backoff_base_s, backoff_max_s : the n-th retry waits up to min(max, base * 2**n) (full jitter) ...
    max_retry_after_s : ... or, when the service sent Retry-After r, r plus a jitter (`jitter_s`) so that clients
        turned away together do not come back together; an r above this is not waited for (the error is raised).
    """

    max_retries: int = 4
    backoff_base_s: float = 0.2
    backoff_max_s: float = 5.0
    max_retry_after_s: float = 30.0
    rng: random.Random = field(default_factory=random.Random, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.max_retries < 0 or self.backoff_base_s < 0 or self.backoff_max_s < 0 or self.max_retry_after_s < 0:
            raise ValueError("retry settings must be non-negative")

    def delay_s(self, retry: int, error: ClientError) -> float | None:
        """Seconds to wait before retry number `retry` (from 0) after `error`, or None to give up."""
        if not error.retryable or retry >= self.max_retries:
            return None
        step = min(self.backoff_max_s, self.backoff_base_s * (2**retry))
        if error.retry_after_s is not None:
            if error.retry_after_s > self.max_retry_after_s:
                return None
            return error.retry_after_s + self.jitter_s(error.retry_after_s)
        return self.rng.uniform(0.0, step)

    def jitter_s(self, retry_after_s: float) -> float:
        """Jitter added to a Retry-After wait: uniform over [0, min(r, backoff_max_s)], the same window for a
        retried request and for fresh ones held by `ClientPause`, so that after a pause neither kind is favoured
        (a request turned away many times must not fall ever further behind fresh ones)."""
        return self.rng.uniform(0.0, min(max(retry_after_s, self.backoff_base_s), self.backoff_max_s))


class ClientPause:
    """Retry-After applies to the client, not only to the request that got it: while a pause is on, fresh requests
    of the same client wait too (they would be turned away as well), then go in the same jittered window as the
    retried ones. Shared by threads (sync client, zenoh) or tasks (async client); a float store is atomic enough.
    """

    def __init__(self, policy: RetryPolicy) -> None:
        self.policy = policy
        self._until = 0.0
        self._retry_after_s = 0.0

    def note(self, error: ClientError, now: float) -> None:
        if error.retryable and error.retry_after_s is not None and error.retry_after_s <= self.policy.max_retry_after_s:
            if now + error.retry_after_s > self._until:
                self._until, self._retry_after_s = now + error.retry_after_s, error.retry_after_s

    def wait_s(self, now: float) -> float:
        """Seconds a fresh request should wait before it is sent (0 when no pause is on)."""
        if now >= self._until:
            return 0.0
        return self._until - now + self.policy.jitter_s(self._retry_after_s)


class RetryLoop:
    """One client's retry bookkeeping, the same for HTTP and zenoh: its pause, the deadline of a call (retries
    included), the retry count over its life (for load reports) and the `on_retry` hook. Thread-safe."""

    def __init__(self, policy: RetryPolicy, *, deadline_s: float | None = None, on_retry: RetryHook | None = None) -> None:
        self.policy = policy
        self.deadline_s = deadline_s
        self.on_retry = on_retry
        self.pause = ClientPause(policy)
        self.count = 0
        self._lock = threading.Lock()

    def next_delay(self, attempt: int, error: ClientError, started: float) -> float | None:
        """Seconds to wait before retrying a call begun at `started` (time.monotonic) that failed with `error` on
        attempt `attempt` (from 0), or None to raise it: not retryable, retries spent, or past the deadline."""
        self.pause.note(error, time.monotonic())
        delay = self.policy.delay_s(attempt, error)
        if delay is None:
            return None
        if self.deadline_s is not None and time.monotonic() - started + delay > self.deadline_s:
            return None
        with self._lock:
            self.count += 1
        if self.on_retry is not None:
            self.on_retry(attempt + 1, error, delay)
        return delay

    def call(self, send: Callable[[], T], sleep: Callable[[float], None] = time.sleep) -> T:
        """`send()` until it returns, retrying the ClientErrors the policy allows; the last error is raised.
        A fresh call first waits out the client's pause. `sleep` waits (tests record instead of sleeping)."""
        attempts = _Attempts(self)
        while True:
            if attempts.wait_s is not None:
                sleep(attempts.wait_s)
            try:
                return send()
            except ClientError as error:
                attempts.failed(error)

    async def acall(self, send: Callable[[], Awaitable[T]], sleep: Callable[[float], Awaitable[None]] = asyncio.sleep) -> T:
        """`call` for a coroutine function `send` and an awaitable `sleep`."""
        attempts = _Attempts(self)
        while True:
            if attempts.wait_s is not None:
                await sleep(attempts.wait_s)
            try:
                return await send()
            except ClientError as error:
                attempts.failed(error)


class _Attempts:
    """One call's place in its RetryLoop: when it began, how many retries it made, what to wait before the next
    send (None: send at once). Shared by `call` and `acall` so that sync and async retry the same way."""

    def __init__(self, loop: RetryLoop) -> None:
        self.loop = loop
        self.started = time.monotonic()
        self.retry = 0
        pause = loop.pause.wait_s(self.started)
        self.wait_s: float | None = pause if pause > 0 else None

    def failed(self, error: ClientError) -> None:
        """Set the wait before the next send, or raise `error` when it is not to be retried."""
        delay = self.loop.next_delay(self.retry, error, self.started)
        if delay is None:
            raise error
        self.wait_s = delay
        self.retry += 1


NO_RETRY = RetryPolicy(max_retries=0)
