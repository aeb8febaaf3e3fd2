"""The zenoh front end, in the HTTP app's process, on the same worker pool.

Keys, encodings and the session config are the wire contract of service/zenoh_wire.py:
    cadreg/<site_id>/localize              queryable: query payload = frame envelope (service/codec.py);
                                           reply = the result (RESULT_ENCODING), or reply_err with the error body
                                           (ERROR_ENCODING)
    cadreg/<site_id>/frames/<device_id>    stream mode: subscribed (wildcard cadreg/*/frames/*), payload = envelope
    cadreg/<site_id>/poses/<device_id>     stream mode: the result published per frame, frame id echoed; errors are
                                           published as the error body (ERROR_ENCODING) with detail.frame_id

No callbacks of ours run on zenoh's threads (zenoh-python: never block or call zenoh there): the queryable and the
subscriber deliver into zenoh's own FIFO channels, and threads of our own drain them. One thread turns queries into
pool jobs; one moves frames into a bounded deque per device; one hands each ready device's oldest frame to the pool,
at most `stream_in_flight_per_device` frames in flight per device, round robin; one replies and publishes when the
jobs are done. Each device is a tracking session (service/sessions.py): its frames are tracked from its last pose,
and with two in flight a device's frames use both workers (the second is predicted from the same state).

What a client cannot make grow (issue 14):
- a payload over `max_upload_bytes` (the HTTP cap too) is refused as payload_too_large by its length, unread;
- frames for a site that is not loaded are answered unknown_site at once and leave no state;
- per-device state is bounded: a device idle for `stream_device_ttl_s` is forgotten, at most `stream_max_devices`
  are tracked (at the cap the one idle longest is forgotten; when none is idle the new device's frame is refused);
- the frames waiting across all devices hold at most `stream_max_pending_bytes`; a device that outruns the pool loses
  its oldest frame (cadreg_zenoh_dropped_frames_total{site}, loaded sites only); refusals are counted by reason in
  cadreg_zenoh_refused_frames_total{reason};
- stream frames fill at most `stream_pool_share` of the pool's places (workers + queue_depth): they are submitted with
  a reserve, so queries and HTTP requests always find the rest;
- the next frame to submit is the head of a deque of ready devices (pending frames, room in flight): O(1); devices
  whose tracking session has a state go first, so new device ids (a global search each) never starve them.
At shutdown (`stop`) new queries are answered 'shutting down' (overloaded), in-flight queries get their answers (up
to `zenoh_shutdown_timeout_s`, then 'shutting down'), and only then are the entities undeclared and the session
closed. Every log line is one JSON object (service/logs.py).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
import uuid
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import zenoh

from cadreg.errors import CadregError, ConfigError, InvalidFrame, Overloaded, PayloadTooLarge, UnknownSite

from . import zenoh_wire as wire
from .codec import encode_result, unpack_envelope
from .errors import error_body
from .logs import log_event
from .runtime import Service
from .sessions import session_key
from .settings import Settings

log = logging.getLogger("cadreg.service.zenoh")

_OVERLOAD_RETRY_S = 0.02  # ready stream frames and a pool without room for them: look again this much later
_PRUNE_EVERY_S = 1.0  # the stream thread forgets idle devices at least this often when nothing else wakes it
# zenoh's FIFO channels block zenoh's delivery when full, which pushes back on the senders instead of losing
# messages unseen; our drains only move items along (no decoding, no pool wait), so these depths are rarely reached.
# Frames are dropped, and counted, in the per-device deques, not here.
QUERY_CHANNEL_SIZE = 256
FRAME_CHANNEL_SIZE = 256


def zenoh_config(settings: Settings) -> zenoh.Config:
    """The service session's zenoh Config from the settings (zenoh_wire.session_config)."""
    return wire.session_config(
        mode=settings.zenoh_mode,
        listen=settings.zenoh_listen,
        connect=settings.zenoh_connect,
        multicast_scouting=settings.zenoh_multicast_scouting,
        gossip_scouting=settings.zenoh_gossip_scouting,
    )


def stream_reserve(settings: Settings) -> int:
    """Pool places a stream frame must leave free: capacity minus the stream share (at least one place for streams)."""
    capacity = settings.workers + settings.queue_depth
    stream_places = max(1, int(capacity * settings.stream_pool_share))
    return max(0, capacity - stream_places)


def _query_site(key: zenoh.KeyExpr) -> str:
    """The site of a query's key; a wildcard query (`cadreg/**`, which our queryable matches too) names none."""
    try:
        return wire.parse_key(key).site_id
    except ValueError:
        raise UnknownSite(f"the query key {str(key)!r} names no single site (ask cadreg/<site_id>/localize)",
                          detail={"key": str(key)}) from None


def _too_large(size: int, limit: int) -> PayloadTooLarge:
    return PayloadTooLarge(f"payload of {size} bytes is over the {limit}-byte limit", detail={"limit_bytes": limit})


def _shutting_down() -> Overloaded:
    return Overloaded("the service is shutting down", retry_after_s=1.0)


@dataclass(eq=False)
class _Device:
    """One streaming device (site, device). Idle = no frame pending and none in flight; only idle devices are
    forgotten (TTL, cap)."""

    site_id: str
    device_id: str
    frames: deque = field(default_factory=deque)  # (payload bytes, t0 perf_counter)
    in_flight: int = 0  # frames of this device in the pool (at most stream_in_flight_per_device)
    ready: bool = False  # in ZenohServer._ready
    idle_since: float = 0.0  # time.monotonic()

    @property
    def key(self) -> tuple[str, str]:
        return (self.site_id, self.device_id)

    @property
    def idle(self) -> bool:
        return not self.frames and not self.in_flight


class _ReadyDevices:
    """Devices with a frame to submit, round robin, in two classes: those with a tracking state first (their
    frames cost a refinement and a robot waits on them), then new or lost ones (a global search each). A flood of
    new device ids then cannot push a tracked robot's next pose behind a thousand searches."""

    def __init__(self) -> None:
        self._tracked: deque[_Device] = deque()
        self._new: deque[_Device] = deque()

    def __bool__(self) -> bool:
        return bool(self._tracked) or bool(self._new)

    def append(self, device: _Device, tracked: bool) -> None:
        (self._tracked if tracked else self._new).append(device)

    def appendleft(self, device: _Device, tracked: bool) -> None:
        (self._tracked if tracked else self._new).appendleft(device)

    def popleft(self) -> _Device:
        return self._tracked.popleft() if self._tracked else self._new.popleft()

    def pop_waiting_new(self) -> _Device | None:
        """The new device ready longest, when none of its frames is in flight (it can be forgotten whole)."""
        if self._new and self._new[0].in_flight == 0:
            return self._new.popleft()
        return None

    def clear(self) -> None:
        self._tracked.clear()
        self._new.clear()


@dataclass(eq=False)
class _PendingQuery:
    query: zenoh.Query
    request_id: str
    key: str
    site_id: str | None
    t0: float


class ZenohServer:
    def __init__(self, service: Service, settings: Settings) -> None:
        self.service = service
        self.settings = settings
        self.session: zenoh.Session | None = None
        self._queryable: zenoh.Queryable | None = None
        self._subscriber: zenoh.Subscriber | None = None
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()  # callables run on the reply thread; None ends it
        self._reserve = stream_reserve(settings)
        # stream state, all under _cond
        self._cond = threading.Condition()
        self._devices: dict[tuple[str, str], _Device] = {}
        self._idle: OrderedDict[tuple[str, str], _Device] = OrderedDict()  # idle devices, longest idle first
        self._ready = _ReadyDevices()  # pending frames and room in flight, round robin, tracked sessions first
        self._pending_bytes = 0
        self._streams_in_flight = 0
        self._stopping = False
        # queries taken and not yet answered, under _queries_cond
        self._queries_cond = threading.Condition()
        self._queries: dict[str, _PendingQuery] = {}
        self._closing = False  # no new queries: they are answered 'shutting down'
        self._threads: list[threading.Thread] = []

    # --- life cycle -------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the session and declare the queryable and the subscriber; a session that cannot open (an endpoint
        in use, a bad locator) raises ConfigError naming the endpoints."""
        try:
            self.session = zenoh.open(zenoh_config(self.settings))
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh could not open a {self.settings.zenoh_mode} session listening on "
                              f"{self.settings.zenoh_listen}, connecting to {self.settings.zenoh_connect}: {exc}") from None
        self._queryable = self.session.declare_queryable(wire.QUERY_KEYS, zenoh.handlers.FifoChannel(QUERY_CHANNEL_SIZE))
        self._subscriber = self.session.declare_subscriber(wire.FRAMES_KEYS,
                                                           zenoh.handlers.FifoChannel(FRAME_CHANNEL_SIZE))
        for target, name in ((self._drain_queries, "queries"), (self._drain_frames, "frames"),
                             (self._drain_streams, "streams"), (self._drain_outbox, "replies")):
            t = threading.Thread(target=target, name=f"cadreg-zenoh-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        log_event(log, "zenoh_started", mode=self.settings.zenoh_mode, listen=self.settings.zenoh_listen,
                  connect=self.settings.zenoh_connect)

    def stop(self) -> None:
        """Graceful: refuse new queries and frames, answer the queries in flight (waiting for their jobs up to
        `zenoh_shutdown_timeout_s`, then 'shutting down'), publish the stream answers that come in that time, then
        undeclare, end our threads and close the session. Call before the pool stops."""
        deadline = time.monotonic() + self.settings.zenoh_shutdown_timeout_s
        with self._queries_cond:
            self._closing = True
        with self._cond:
            self._stopping = True  # the stream thread submits nothing more; pending frames are let go
            for device in self._devices.values():
                device.frames.clear()
            self._ready.clear()
            self._pending_bytes = 0
            self._cond.notify_all()
        with self._queries_cond:
            while self._queries and (left := deadline - time.monotonic()) > 0:
                self._queries_cond.wait(left)
            late = list(self._queries.values())
            self._queries.clear()
        for pending in late:  # their jobs outlived the bound: answered all the same
            self._send_error(pending, _shutting_down())
        with self._cond:
            while self._streams_in_flight and (left := deadline - time.monotonic()) > 0:
                self._cond.wait(left)
        # undeclaring closes zenoh's channels, which ends the query and frame drains' iterations
        for entity in (self._queryable, self._subscriber):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception:  # the session may already be closing; nothing to recover
                    log.debug("undeclare failed", exc_info=True)
        self._outbox.put(None)
        for t in self._threads:
            t.join(5.0)
        if self.session is not None:
            self.session.close()
        log_event(log, "zenoh_stopped", unanswered_in_time=len(late))

    # --- queries ----------------------------------------------------------------------------------------------------

    def _drain_queries(self) -> None:
        for query in self._queryable:  # ends when the queryable is undeclared
            try:
                self._take_query(query, time.perf_counter())
            except Exception as exc:  # a reply to a vanished peer must not stop the thread
                self._log_failure("zenoh_query_failed", exc)

    def _take_query(self, query: zenoh.Query, t0: float) -> None:
        key = str(query.key_expr)
        pending = _PendingQuery(query, uuid.uuid4().hex, key, None, t0)
        with self._queries_cond:
            closing = self._closing
            if not closing:
                self._queries[pending.request_id] = pending
        if closing:
            self._send_error(pending, _shutting_down())
            return
        try:
            pending.site_id = _query_site(query.key_expr)
            payload = query.payload
            if payload is None:
                raise InvalidFrame("the query carries no payload (expected a frame envelope)")
            size, limit = len(payload), self.settings.max_upload_bytes
            if size > limit:  # by its length: nothing of it is copied or decoded
                raise _too_large(size, limit)
            parts, meta = unpack_envelope(payload.to_bytes())
            future = self.service.submit(pending.site_id, parts, meta)
        except Exception as exc:
            self._answer_error(pending, exc)
            return
        future.add_done_callback(lambda f: self._outbox.put(lambda: self._answer_done(pending, f)))

    def _claim(self, pending: _PendingQuery) -> bool:
        """Take `pending` off the in-flight table; False when shutdown answered it already."""
        with self._queries_cond:
            if self._queries.pop(pending.request_id, None) is None:
                return False
            self._queries_cond.notify_all()
            return True

    def _answer_done(self, pending: _PendingQuery, future) -> None:
        try:
            job = future.result()
        except Exception as exc:
            self._answer_error(pending, exc)
            return
        if not self._claim(pending):
            return
        try:
            body = self.service.finish(job, pending.site_id, pending.request_id)
            pending.query.reply(pending.query.key_expr, encode_result(body), encoding=wire.RESULT_ENCODING)
        finally:
            pending.query.drop()
        self._log("query", pending.request_id, "ok", pending.t0, key=pending.key, site_id=pending.site_id)

    def _answer_error(self, pending: _PendingQuery, exc: BaseException) -> None:
        if self._claim(pending):
            self._send_error(pending, exc)

    def _send_error(self, pending: _PendingQuery, exc: BaseException) -> None:
        if not isinstance(exc, CadregError):
            self._log_failure("zenoh_query_failed", exc, request_id=pending.request_id, key=pending.key)
        body = error_body(exc, pending.request_id)
        try:
            pending.query.reply_err(encode_result(body), encoding=wire.ERROR_ENCODING)
        finally:
            pending.query.drop()
        self._log("query", pending.request_id, body["code"], pending.t0, key=pending.key, site_id=pending.site_id)

    def _log(self, route: str, request_id: str, code: str, t0: float, **fields: Any) -> None:
        elapsed = time.perf_counter() - t0
        self.service.metrics.observe_request("zenoh", route, code, elapsed)
        if self.settings.log_requests:
            log_event(log, "zenoh_request", request_id=request_id, route=route, **fields, code=code,
                      ms=round(elapsed * 1e3, 1))

    def _log_failure(self, event: str, exc: BaseException, **fields: Any) -> None:
        log_event(log, event, logging.ERROR, **fields, error=f"{type(exc).__name__}: {exc}",
                  traceback="".join(traceback.format_exception(exc)))

    def _drain_outbox(self) -> None:
        while True:
            task = self._outbox.get()
            if task is None:
                return
            try:
                task()
            except Exception as exc:  # a reply to a vanished peer must not stop the thread
                self._log_failure("zenoh_reply_failed", exc)

    # --- streams: arrival -------------------------------------------------------------------------------------------

    def _drain_frames(self) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            try:
                self._take_frame(sample)
            except Exception as exc:  # a put to a vanished peer must not stop the thread
                self._log_failure("zenoh_frame_failed", exc)

    def _take_frame(self, sample: zenoh.Sample) -> None:
        try:
            key = wire.parse_key(sample.key_expr)
        except ValueError:
            return  # a wildcard put matches cadreg/*/frames/* too, but names no device to answer
        t0 = time.perf_counter()
        size, limit = len(sample.payload), self.settings.max_upload_bytes
        if size > limit:  # by its length: nothing of it is copied or decoded
            self.service.metrics.zenoh_refused.labels("payload_too_large").inc()
            self._publish_refusal(key.site_id, key.device_id, _too_large(size, limit), t0)
            return
        if not self.service.serves(key.site_id):  # no device state, no metric series for a site nobody serves
            self.service.metrics.zenoh_refused.labels("unknown_site").inc()
            exc = UnknownSite(f"unknown site {key.site_id!r}", detail={"site_id": key.site_id})
            self._publish_refusal(key.site_id, key.device_id, exc, t0)
            return
        refusal = self._enqueue_frame(key.site_id, key.device_id, sample.payload.to_bytes(), t0)
        if refusal is not None:  # answered, so that the device backs off rather than waits for a pose
            self._publish_refusal(key.site_id, key.device_id, refusal, t0)

    def _publish_refusal(self, site_id: str, device_id: str, exc: CadregError, t0: float) -> None:
        """Answer a frame refused on arrival on its poses key, from this thread (no state, nothing queued)."""
        request_id = uuid.uuid4().hex
        body = wire.stamp_stream_body(error_body(exc, request_id), "error", None, device_id)
        self.session.put(wire.poses_key(site_id, device_id), encode_result(body), encoding=wire.ERROR_ENCODING)
        self._log("stream", request_id, body["code"], t0, site_id=site_id, device_id=device_id, frame_id=None)

    def _enqueue_frame(self, site_id: str, device_id: str, payload: bytes, t0: float) -> Overloaded | None:
        """Queue a stream frame for the pool; the error to answer it with when it is refused for want of room (the
        device cap, the pending bytes' budget: before the forty-first session such a frame got no answer at all, and
        a device waited for a pose that never came), None otherwise (a frame refused at shutdown is not answered)."""
        metrics = self.service.metrics
        now = time.monotonic()
        retry_after_s = self.settings.retry_after_s
        with self._cond:
            if self._stopping:
                metrics.zenoh_refused.labels("shutting_down").inc()
                return None
            self._prune(now)
            device = self._devices.get((site_id, device_id))
            if device is None:
                if len(self._devices) >= self.settings.stream_max_devices:
                    if self._idle:
                        self._forget(next(iter(self._idle.values())))  # the one idle longest
                    elif not self._make_room_for(site_id, device_id):
                        # every device has work: the new one waits its turn outside
                        metrics.zenoh_refused.labels("device_cap").inc()
                        cap = self.settings.stream_max_devices
                        return Overloaded(f"every one of the {cap} stream devices the service tracks "
                                          "(stream_max_devices) has work", retry_after_s=retry_after_s)
                device = self._devices[(site_id, device_id)] = _Device(site_id, device_id)
            full = len(device.frames) >= self.settings.stream_queue_per_device
            freed = len(device.frames[0][0]) if full else 0
            if self._pending_bytes - freed + len(payload) > self.settings.stream_max_pending_bytes:
                metrics.zenoh_refused.labels("stream_budget").inc()
                if device.idle:
                    self._set_idle(device, now)
                budget = self.settings.stream_max_pending_bytes
                return Overloaded(f"stream frames waiting for the pool would pass {budget} bytes "
                                  "(stream_max_pending_bytes)", retry_after_s=retry_after_s)
            if full:
                device.frames.popleft()  # the device outruns the pool: the oldest frame is the least useful
                self._pending_bytes -= freed
                metrics.zenoh_dropped.labels(site_id).inc()
            device.frames.append((payload, t0))
            self._pending_bytes += len(payload)
            self._idle.pop(device.key, None)
            self._mark_ready(device)
            self._cond.notify_all()
        return None

    # --- streams: state (all under _cond) ---------------------------------------------------------------------------

    def _set_idle(self, device: _Device, now: float) -> None:
        device.idle_since = now
        self._idle[device.key] = device
        self._idle.move_to_end(device.key)

    def _forget(self, device: _Device) -> None:
        self._idle.pop(device.key, None)
        self._devices.pop(device.key, None)

    def _prune(self, now: float) -> None:
        """Forget the devices idle for longer than the TTL (the idle table is ordered by idle time: O(forgotten))."""
        horizon = now - self.settings.stream_device_ttl_s
        while self._idle:
            device = next(iter(self._idle.values()))
            if device.idle_since > horizon:
                return
            self._forget(device)

    def _mark_ready(self, device: _Device) -> None:
        if device.frames and device.in_flight < self.settings.stream_in_flight_per_device and not device.ready:
            device.ready = True
            self._ready.append(device, self._tracked(device))

    def _make_room_for(self, site_id: str, device_id: str) -> bool:
        """At the device cap with no idle device: a device with a tracking session takes the place of the new
        device waiting longest for its first search (its frames are dropped, counted); False when there is none."""
        if not self._has_session(site_id, device_id):
            return False
        victim = self._ready.pop_waiting_new()
        if victim is None:
            return False
        for payload, _ in victim.frames:
            self._pending_bytes -= len(payload)
            self.service.metrics.zenoh_dropped.labels(victim.site_id).inc()
        victim.frames.clear()
        victim.ready = False
        self._forget(victim)
        return True

    def _tracked(self, device: _Device) -> bool:
        return self._has_session(device.site_id, device.device_id)

    def _has_session(self, site_id: str, device_id: str) -> bool:
        return self.service.sessions.holds(session_key(site_id, None, device_id))

    def _take_next(self) -> tuple[_Device, bytes, float]:
        """The oldest frame of the first ready device (O(1)); it is then in flight."""
        device = self._ready.popleft()
        device.ready = False
        payload, t0 = device.frames.popleft()
        self._pending_bytes -= len(payload)
        device.in_flight += 1
        self._streams_in_flight += 1
        self._mark_ready(device)  # room for another of its frames: back in the round robin, behind the others
        return device, payload, t0

    def _pool_has_room(self) -> bool:
        pool = self.service.pool
        return pool is not None and pool.free_slots() > self._reserve

    # --- streams: to the pool and back ------------------------------------------------------------------------------

    def _drain_streams(self) -> None:
        while True:
            with self._cond:
                while not self._stopping and not (self._ready and self._pool_has_room()):
                    self._prune(time.monotonic())
                    self._cond.wait(_OVERLOAD_RETRY_S if self._ready else _PRUNE_EVERY_S)
                if self._stopping:
                    return
                item = self._take_next()
            self._submit_stream(*item)

    def _submit_stream(self, device: _Device, payload: bytes, t0: float) -> None:
        request_id = uuid.uuid4().hex
        frame_id = None
        try:
            parts, meta = unpack_envelope(payload)
            frame_id = meta.frame_id
            future = self.service.submit(device.site_id, parts, meta, reserve=self._reserve, device_id=device.device_id)
        except Overloaded:
            self._put_back(device, payload, t0)
            return
        except Exception as exc:
            # bind exc now: Python unbinds the name when the except block ends, before the outbox thread runs this
            self._outbox.put(lambda exc=exc: self._publish_error(device, exc, request_id, frame_id, t0))
            return
        future.add_done_callback(
            lambda f: self._outbox.put(lambda: self._publish_done(device, f, request_id, frame_id, t0)))

    def _put_back(self, device: _Device, payload: bytes, t0: float) -> None:
        """The pool had no room after all (HTTP took it first): the frame goes back to the head of its device and
        the device to the head of the ready deque, unless newer frames filled its queue meanwhile."""
        with self._cond:
            device.in_flight -= 1
            self._streams_in_flight -= 1
            if not self._stopping and len(device.frames) < self.settings.stream_queue_per_device:
                device.frames.appendleft((payload, t0))
                self._pending_bytes += len(payload)
            else:
                self.service.metrics.zenoh_dropped.labels(device.site_id).inc()
            if device.frames and not device.ready:
                device.ready = True
                self._ready.appendleft(device, self._tracked(device))
            elif device.idle:
                self._set_idle(device, time.monotonic())
            self._cond.notify_all()
            self._cond.wait(_OVERLOAD_RETRY_S)

    def _release(self, device: _Device) -> None:
        with self._cond:
            device.in_flight -= 1
            self._streams_in_flight -= 1
            if device.idle:
                self._set_idle(device, time.monotonic())
            else:
                self._mark_ready(device)
            self._cond.notify_all()

    def _publish_done(self, device: _Device, future, request_id: str, frame_id: str | None, t0: float) -> None:
        try:
            job = future.result()
        except Exception as exc:
            self._publish_error(device, exc, request_id, frame_id, t0)
            return
        try:
            body = self.service.finish(job, device.site_id, request_id)
            wire.stamp_stream_body(body, "result", frame_id, device.device_id)  # echoed, whatever the result says
            self.session.put(wire.poses_key(device.site_id, device.device_id), encode_result(body),
                             encoding=wire.RESULT_ENCODING)
            self._log("stream", request_id, "ok", t0, site_id=device.site_id, device_id=device.device_id,
                      frame_id=frame_id)
        finally:
            self._release(device)

    def _publish_error(self, device: _Device, exc: BaseException, request_id: str, frame_id: str | None,
                       t0: float) -> None:
        try:
            if not isinstance(exc, CadregError):
                self._log_failure("zenoh_stream_failed", exc, request_id=request_id, site_id=device.site_id,
                                  device_id=device.device_id)
            body = error_body(exc, request_id)
            wire.stamp_stream_body(body, "error", frame_id, device.device_id)
            self.session.put(wire.poses_key(device.site_id, device.device_id), encode_result(body),
                             encoding=wire.ERROR_ENCODING)
            self._log("stream", request_id, body["code"], t0, site_id=device.site_id, device_id=device.device_id,
                      frame_id=frame_id)
        finally:
            self._release(device)
