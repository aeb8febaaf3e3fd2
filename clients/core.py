"""What every client of the service does the same whatever carries the bytes: turn the accepted frame forms into an
`EncodedFrame` (with the client's default `top_k` and one cache of opened recorded-frames folders) and retry by one
`RetryLoop`. The transports (`clients.http`, `clients.zenoh_client`) subclass `ClientCore` and only do I/O.
"""

from __future__ import annotations

from .frames import EncodedFrame, FolderCache, FrameLike, to_encoded
from .retry import RetryHook, RetryLoop, RetryPolicy


class ClientCore:
    """retry : RetryPolicy (default: 4 retries, 0.2 s base backoff); on_retry(attempt, error, delay_s) is told of each.
    deadline_s : budget of one call, retries included (None: only the policy limits it).
    top_k : hypotheses asked for when a call gives none (None: the frame's own, 5 for frames encoded here).
    """

    def __init__(
        self,
        *,
        retry: RetryPolicy | None = None,
        on_retry: RetryHook | None = None,
        deadline_s: float | None = None,
        top_k: int | None = None,
    ) -> None:
        self.retry = retry or RetryPolicy()
        self.top_k = top_k
        self._retry_loop = RetryLoop(self.retry, deadline_s=deadline_s, on_retry=on_retry)
        self._folders = FolderCache()

    @property
    def retries(self) -> int:
        """Retries made over this client's life (for load reports)."""
        return self._retry_loop.count

    def encode(self, frame: FrameLike, *, frame_id: str | None = None, top_k: int | None = None) -> EncodedFrame:
        """A frame in any accepted form (cadreg Frame, EncodedFrame, (folder, index)) ready to send; `top_k`
        overrides the client's default, `frame_id` (when given) the frame's own."""
        enc = to_encoded(frame, top_k=top_k if top_k is not None else self.top_k, cache=self._folders)
        return enc if frame_id is None else enc.with_frame_id(frame_id)
