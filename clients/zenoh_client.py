"""zenoh client of the cadreg service: request/reply `localize` and a streaming helper for robots.

    with ZenohClient("tcp/127.0.0.1:7447") as z:
        result = z.localize("scene0470", frame)          # query on cadreg/<site>/localize

        with z.stream("scene0470", "robot-1", lost_after_s=5.0) as s:   # DESIGN §6 stream mode
            for r in s.run(frames, rate_hz=5):             # publishes frames, yields StreamResult as poses come back
                if r.lost: ...                             # no pose for r.frame_id within lost_after_s
                elif r.error: ...                          # the service answered with an error body
                elif r.status == "ok": r.T_map_camera, r.mode   # mode: tracked | relocalized | global

Each device is a tracking session on the service: its next frame is refined from its last pose (mode "tracked")
until tracking fails, and is then localized globally ("relocalized").

Keys, encodings and the session config are the service's (`service.zenoh_wire`). The session is a zenoh *client*
connected to the given endpoint(s) (the service's `--zenoh-listen`), with multicast and gossip scouting off
(DESIGN §9), so nothing leaves loopback unless asked. `localize` sends the `service.codec` envelope with
`session.get(key, payload=..., timeout=...)`; a reply in the result encoding is the result JSON, one in the error
encoding the error body, raised as the typed class of `clients.errors`; pose messages are told apart the same way,
never by what their body holds. Frame encoding and retries are `clients.core`'s, as over HTTP (`RetryPolicy`):
`overloaded` / `worker_crashed` and "no queryable answered" (`unreachable`, e.g. the service is still starting) are
retried; everything else, and the query timeout (`client_timeout`), is not.

Callbacks never block and never call zenoh: subscriber samples go to a queue drained by the caller's thread.
"""

from __future__ import annotations

import itertools
import json
import queue
import time
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import zenoh

from cadreg.errors import CadregError
from service import codec, zenoh_wire as wire
from service.zenoh_wire import frames_key, localize_key, poses_key  # noqa: F401 - part of this module's API

from .core import ClientCore
from .errors import BadResponse, ClientError, ClientTimeout, Unreachable, error_from_body
from .frames import FrameLike
from .retry import RetryHook, RetryPolicy

DEFAULT_QUERY_TIMEOUT_S = 120.0


def session_config(connect: Sequence[str] = (), listen: Sequence[str] = (), *, mode: str = "client") -> zenoh.Config:
    """A zenoh Config with scouting off (no multicast, no gossip) and only the given endpoints."""
    return wire.session_config(mode=mode, listen=listen, connect=connect)


def _gist(kind: str, body: dict[str, Any]) -> tuple:
    """What two services' answers to one query must share: the error code, or the status and the pose."""
    if kind == "error":
        return ("error", body.get("code"))
    return ("result", body.get("status"), json.dumps(body.get("T_map_camera")))


def _json_object(data: bytes, what: str) -> dict[str, Any]:
    try:
        return codec.decode_result(data)
    except CadregError as exc:
        raise BadResponse(f"{what}: {exc.message}: {data[:200]!r}") from None


class ZenohClient(ClientCore):
    """A zenoh session to the cadreg service.

    connect : endpoint or endpoints of the service, e.g. "tcp/127.0.0.1:7447" (ignored when `session` is given).
    timeout_s : query timeout of `localize` (a localization takes seconds on a busy machine).
    session : an already open zenoh Session to use (not closed by `close`).
    retry, on_retry, top_k, deadline_s : as for the HTTP clients (`clients.core.ClientCore`).
    """

    def __init__(
        self,
        connect: str | Sequence[str] = (),
        *,
        timeout_s: float = DEFAULT_QUERY_TIMEOUT_S,
        retry: RetryPolicy | None = None,
        on_retry: RetryHook | None = None,
        top_k: int | None = None,
        session: zenoh.Session | None = None,
        deadline_s: float | None = None,
    ) -> None:
        super().__init__(retry=retry, on_retry=on_retry, deadline_s=deadline_s, top_k=top_k)
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.timeout_s = float(timeout_s)
        if session is not None:
            self.session, self._owns = session, False
        else:
            if not endpoints:
                raise ValueError("give the service's endpoint(s) to connect to, or an open session")
            try:
                self.session = zenoh.open(session_config(endpoints))
            except zenoh.ZError as exc:
                raise Unreachable(f"cannot open a zenoh session to {', '.join(endpoints)}: {exc}") from None
            self._owns = True

    def __enter__(self) -> "ZenohClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._owns and not self.session.is_closed():
            self.session.close()

    def query_once(self, site_id: str, payload: bytes, timeout_s: float | None = None) -> dict[str, Any]:
        """One query, no retries: the result dict, or the typed error. What a reply is comes from its encoding
        (service/zenoh_wire.py), never from its body. Every reply is read (no consolidation): two that disagree
        (status, pose or error code) raise BadResponse. zenoh authenticates nobody here, and with its default
        consolidation the latest reply won: a hostile peer's queryable that answered after the service had its
        forged pose taken (README, "Who may answer on zenoh"). Services that agree (replicas of one site) pass."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        key = localize_key(site_id)
        started = time.monotonic()
        answers: list[tuple[str, dict[str, Any]]] = []  # ("result" | "error", body), in arrival order
        try:
            for reply in self.session.get(key, payload=payload, encoding=wire.ENVELOPE_ENCODING, timeout=timeout_s,
                                          consolidation=zenoh.ConsolidationMode.NONE):
                sample = reply.ok if reply.ok is not None else reply.err
                kind = wire.body_kind(sample.encoding)
                data = sample.payload.to_bytes()
                if reply.ok is not None and kind == "result":
                    answers.append(("result", _json_object(data, "zenoh reply")))
                elif reply.err is not None and kind == "error":
                    answers.append(("error", _json_object(data, "zenoh error reply")))
                elif reply.err is not None and time.monotonic() - started >= 0.9 * timeout_s:
                    break  # zenoh's own error reply (b"Timeout") when the query timed out
                else:
                    raise BadResponse(f"zenoh {'reply' if reply.ok is not None else 'error reply'} on {key} with "
                                      f"encoding {str(sample.encoding)!r} is no cadreg answer: {data[:200]!r}")
        except zenoh.ZError as exc:
            raise Unreachable(f"zenoh query on {key} failed: {exc}") from None
        if answers:
            kind, body = answers[0]
            if any(_gist(k, b) != _gist(kind, body) for k, b in answers[1:]):
                raise BadResponse(f"{len(answers)} queryables on {key} answered, and not alike: another service or a "
                                  "peer that is not one answers there (zenoh authenticates nobody)",
                                  detail={"answers": [_gist(k, b) for k, b in answers[:5]]})
            if kind == "error":
                raise error_from_body(body)
            return body
        elapsed = time.monotonic() - started
        # zenoh ends a query with no reply both when nobody serves the key (at once) and at the timeout
        if elapsed >= 0.9 * timeout_s:
            raise ClientTimeout(f"no answer on {key} within {timeout_s:g} s")
        raise Unreachable(f"no queryable answered on {key} (is the service up and serving site {site_id!r}?)")

    def localize(
        self,
        site_id: str,
        frame: FrameLike,
        *,
        frame_id: str | None = None,
        top_k: int | None = None,
        timeout_s: float | None = None,
    ) -> dict[str, Any]:
        """Localize one frame (a cadreg Frame, an EncodedFrame, or (folder, index)); the result dict.

        Safe to call from several threads at once (each call is its own zenoh query).
        """
        envelope = self.encode(frame, frame_id=frame_id, top_k=top_k).envelope()
        return self.localize_envelope(site_id, envelope, timeout_s=timeout_s)

    def localize_envelope(self, site_id: str, payload: bytes, *, timeout_s: float | None = None) -> dict[str, Any]:
        """`localize` for an already packed envelope (`EncodedFrame.envelope()`), with the retries."""
        return self._retry_loop.call(lambda: self.query_once(site_id, payload, timeout_s))

    def stream(
        self, site_id: str, device_id: str, *, lost_after_s: float = 10.0, drop_when_congested: bool = False
    ) -> "PoseStream":
        """A PoseStream publishing frames of `device_id` to the site and collecting its poses (a context manager)."""
        return PoseStream(self, site_id, device_id, lost_after_s=lost_after_s,
                          drop_when_congested=drop_when_congested)


@dataclass
class StreamResult:
    """What became of one published frame.

    frame_id : the id the frame was published with (the service echoes it).
    result : the result dict (status, T_map_camera, ...) when a pose message came back, else None.
    error : the typed error when the service answered with an error body, else None.
    lost : True when nothing came back within `lost_after_s` of publishing (a late answer is then dropped).
    latency_ms : publish -> answer (or -> declared lost), milliseconds.
    """

    frame_id: str
    result: dict[str, Any] | None = None
    error: ClientError | None = None
    lost: bool = False
    latency_ms: float = 0.0

    @property
    def ok(self) -> bool:
        return self.result is not None

    @property
    def status(self) -> str | None:
        """The result's status (ok, ambiguous, ...), None without a result."""
        return None if self.result is None else self.result.get("status")

    @property
    def mode(self) -> str | None:
        """How the service answered this frame of the device's tracking session: "tracked" (refined from the last
        pose), "relocalized" (tracking failed: localized globally) or "global" (a new session); None without a
        result."""
        if self.result is None:
            return None
        diagnostics = self.result.get("diagnostics")
        return diagnostics.get("mode") if isinstance(diagnostics, dict) else None

    @property
    def T_map_camera(self) -> np.ndarray | None:
        """(4, 4) colour camera -> map when the result holds a pose (ok or ambiguous), else None."""
        T = None if self.result is None else self.result.get("T_map_camera")
        return None if T is None else np.asarray(T, dtype=np.float64)


class PoseStream:
    """Stream mode for robots: publish frames on `cadreg/<site>/frames/<device>`, get poses on
    `cadreg/<site>/poses/<device>`, matched by frame id.

    Lost frames: a frame with no answer `lost_after_s` after it was published is yielded once as
    `StreamResult(frame_id, lost=True)`; an answer arriving later is counted in `late` and not yielded.
    Messages whose frame id was never published by this stream (another client on the same device key) are
    counted in `foreign` and skipped.
    """

    def __init__(
        self, client: ZenohClient, site_id: str, device_id: str, *, lost_after_s: float = 10.0,
        drop_when_congested: bool = False,
    ) -> None:
        if lost_after_s <= 0:
            raise ValueError("lost_after_s must be positive")
        self.client = client
        self.site_id, self.device_id = site_id, device_id
        self.lost_after_s = float(lost_after_s)
        self.late = 0
        self.foreign = 0
        self._pending: dict[str, float] = {}  # frame id -> monotonic publish time
        self._resolved: set[str] = set()
        self._inbox: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
        self._ids = itertools.count()
        session = client.session
        # the callback is the enqueue itself: it runs on a zenoh thread that must not block; the caller's thread
        # reads the samples in `poll` (a queue with a timed get, which zenoh's channels do not offer)
        self._sub = session.declare_subscriber(poses_key(site_id, device_id), self._inbox.put)
        cc = zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
        self._pub = session.declare_publisher(frames_key(site_id, device_id), congestion_control=cc,
                                              encoding=wire.ENVELOPE_ENCODING)

    def __enter__(self) -> "PoseStream":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for entity in (self._pub, self._sub):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass  # already gone with its session

    @property
    def pending(self) -> int:
        return len(self._pending)

    def wait_ready(self, timeout_s: float = 5.0) -> bool:
        """Wait until the service's frame subscriber is known to us (frames published before are lost)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._pub.matching_status.matching:
                return True
            time.sleep(0.02)
        return bool(self._pub.matching_status.matching)

    def send(self, frame: FrameLike, *, frame_id: str | None = None) -> str:
        """Publish a frame; returns its frame id (the given one, the frame's own, or `<device>-<n>`)."""
        enc = self.client.encode(frame)  # the same encoding rules as localize
        fid = frame_id or enc.frame_id or f"{self.device_id}-{next(self._ids)}"
        if fid in self._pending:
            raise ValueError(f"frame id {fid!r} is already in flight")
        self._resolved.discard(fid)
        payload = enc.with_frame_id(fid).envelope()
        self._pending[fid] = time.monotonic()
        self._pub.put(payload)
        return fid

    def poll(self, timeout_s: float = 0.0) -> list[StreamResult]:
        """Answers that arrived (waiting up to `timeout_s` for the first), then frames now lost."""
        out: list[StreamResult] = []
        try:
            sample = self._inbox.get(timeout=timeout_s) if timeout_s > 0 else self._inbox.get_nowait()
            while True:
                r = self._match(sample)
                if r is not None:
                    out.append(r)
                sample = self._inbox.get_nowait()
        except queue.Empty:
            pass
        now = time.monotonic()
        for fid, sent in list(self._pending.items()):
            if now - sent >= self.lost_after_s:
                del self._pending[fid]
                self._resolved.add(fid)
                out.append(StreamResult(fid, lost=True, latency_ms=(now - sent) * 1e3))
        return out

    def _match(self, sample: zenoh.Sample) -> StreamResult | None:
        # a result or an error body by the sample's encoding: either may hold any key (a result may well carry a
        # "code"), so the body is no guide
        kind = wire.body_kind(sample.encoding)
        try:
            body = None if kind is None else _json_object(sample.payload.to_bytes(), "pose message")
        except BadResponse:
            body = None
        if body is None:
            self.foreign += 1
            return None
        fid = wire.stream_frame_id(body, kind)
        if fid not in self._pending:
            if fid in self._resolved:
                self.late += 1
            else:
                self.foreign += 1
            return None
        sent = self._pending.pop(fid)
        self._resolved.add(fid)
        latency_ms = (time.monotonic() - sent) * 1e3
        if kind == "error":
            return StreamResult(fid, error=error_from_body(body), latency_ms=latency_ms)
        return StreamResult(fid, result=body, latency_ms=latency_ms)

    def results(self, *, idle_timeout_s: float | None = None) -> Iterator[StreamResult]:
        """Yield answers until no frame is pending (every frame answered or lost).

        idle_timeout_s : stop early when nothing at all arrives for this long (None: rely on lost_after_s).
        """
        last = time.monotonic()
        while self._pending:
            got = self.poll(timeout_s=0.05)
            if got:
                last = time.monotonic()
            yield from got
            if idle_timeout_s is not None and time.monotonic() - last > idle_timeout_s:
                return

    def run(self, frames: Iterable[FrameLike], *, rate_hz: float | None = None,
            max_in_flight: int = 8) -> Iterator[StreamResult]:
        """Publish `frames` (at `rate_hz`, or as fast as answers allow with at most `max_in_flight` pending) and
        yield one StreamResult per frame, in arrival order; returns when every frame is answered or lost."""
        if rate_hz is not None and rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        period = None if rate_hz is None else 1.0 / rate_hz
        next_at = time.monotonic()
        for frame in frames:
            while True:
                now = time.monotonic()
                if period is not None and now >= next_at:
                    break
                if period is None and len(self._pending) < max_in_flight:
                    break
                wait = 0.05 if period is None else min(0.05, max(0.0, next_at - now))
                yield from self.poll(timeout_s=wait)
            self.send(frame)
            if period is not None:
                next_at += period
            yield from self.poll()
        yield from self.results()
