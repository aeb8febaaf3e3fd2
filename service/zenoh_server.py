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
pool jobs; one moves frames into a bounded deque per device (a device that outruns the pool loses its oldest
frames, counted in cadreg_zenoh_dropped_frames_total); one hands each device's oldest frame to the pool, one frame
in flight per device; one replies and publishes when the jobs are done.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
import zenoh

from cadreg.errors import CadregError, ConfigError, InvalidFrame, Overloaded, UnknownSite

from . import zenoh_wire as wire
from .codec import encode_result, unpack_envelope
from .errors import error_body
from .runtime import Service
from .settings import Settings

log = logging.getLogger("cadreg.service.zenoh")

_OVERLOAD_RETRY_S = 0.02  # a stream frame refused by a full pool waits this long before the next try
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


def _query_site(key: zenoh.KeyExpr) -> str:
    """The site of a query's key; a wildcard query (`cadreg/**`, which our queryable matches too) names none."""
    try:
        return wire.parse_key(key).site_id
    except ValueError:
        raise UnknownSite(f"the query key {str(key)!r} names no single site (ask cadreg/<site_id>/localize)",
                          detail={"key": str(key)}) from None


@dataclass
class _Device:
    site_id: str
    device_id: str
    frames: deque = field(default_factory=deque)
    in_flight: bool = False


class ZenohServer:
    def __init__(self, service: Service, settings: Settings) -> None:
        self.service = service
        self.settings = settings
        self.session: zenoh.Session | None = None
        self._queryable: zenoh.Queryable | None = None
        self._subscriber: zenoh.Subscriber | None = None
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()  # callables run on the reply thread; None ends it
        self._devices: dict[tuple[str, str], _Device] = {}
        self._cond = threading.Condition()
        self._stopping = False
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
        log.info("zenoh %s listening on %s, connecting to %s", self.settings.zenoh_mode,
                 self.settings.zenoh_listen, self.settings.zenoh_connect)

    def stop(self) -> None:
        # undeclaring closes zenoh's channels, which ends the query and frame drains' iterations
        for entity in (self._queryable, self._subscriber):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception:  # the session may already be closing; nothing to recover
                    log.debug("undeclare failed", exc_info=True)
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        self._outbox.put(None)
        for t in self._threads:
            t.join(5.0)
        if self.session is not None:
            self.session.close()

    # --- queries ----------------------------------------------------------------------------------------------------

    def _drain_queries(self) -> None:
        for query in self._queryable:  # ends when the queryable is undeclared
            try:
                self._take_query(query, time.perf_counter())
            except Exception:  # a reply to a vanished peer must not stop the thread
                log.exception("zenoh query failed")

    def _take_query(self, query: zenoh.Query, t0: float) -> None:
        request_id = uuid.uuid4().hex
        site_id = str(query.key_expr)  # named in the log as it came until it parses
        try:
            site_id = _query_site(query.key_expr)
            if query.payload is None:
                raise InvalidFrame("the query carries no payload (expected a frame envelope)")
            parts, meta = unpack_envelope(query.payload.to_bytes())
            future = self.service.submit(site_id, parts, meta)
        except Exception as exc:
            self._reply_error(query, exc, request_id, site_id, t0)
            return
        future.add_done_callback(
            lambda f: self._outbox.put(lambda: self._reply_done(query, f, request_id, site_id, t0)))

    def _reply_done(self, query: zenoh.Query, future, request_id: str, site_id: str, t0: float) -> None:
        try:
            job = future.result()
        except Exception as exc:
            self._reply_error(query, exc, request_id, site_id, t0)
            return
        body = self.service.finish(job, site_id, request_id)
        try:
            query.reply(query.key_expr, encode_result(body), encoding=wire.RESULT_ENCODING)
        finally:
            query.drop()
        self._log("query", request_id, site_id, "ok", t0)

    def _reply_error(self, query: zenoh.Query, exc: BaseException, request_id: str, site_id: str, t0: float) -> None:
        if not isinstance(exc, CadregError):
            log.error("zenoh query %s failed", request_id, exc_info=exc)
        body = error_body(exc, request_id)
        try:
            query.reply_err(encode_result(body), encoding=wire.ERROR_ENCODING)
        finally:
            query.drop()
        self._log("query", request_id, site_id, body["code"], t0)

    def _log(self, route: str, request_id: str, site_id: str, code: str, t0: float) -> None:
        elapsed = time.perf_counter() - t0
        self.service.metrics.observe_request("zenoh", route, code, elapsed)
        if self.settings.log_requests:
            log.info("request_id=%s zenoh %s site=%s code=%s ms=%.1f", request_id, route, site_id, code, elapsed * 1e3)

    def _drain_outbox(self) -> None:
        while True:
            task = self._outbox.get()
            if task is None:
                return
            try:
                task()
            except Exception:  # a reply to a vanished peer must not stop the thread
                log.exception("zenoh reply failed")

    # --- streams ----------------------------------------------------------------------------------------------------

    def _drain_frames(self) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            try:
                key = wire.parse_key(sample.key_expr)
            except ValueError:
                continue  # a wildcard put matches cadreg/*/frames/* too, but names no device to answer
            self._enqueue_frame(key.site_id, key.device_id, sample.payload.to_bytes())

    def _enqueue_frame(self, site_id: str, device_id: str, payload: bytes) -> None:
        with self._cond:
            device = self._devices.get((site_id, device_id))
            if device is None:
                device = self._devices[(site_id, device_id)] = _Device(site_id, device_id)
            if len(device.frames) >= self.settings.stream_queue_per_device:
                device.frames.popleft()  # the device outruns the pool: the oldest frame is the least useful
                self.service.metrics.zenoh_dropped.labels(site_id).inc()
            device.frames.append((payload, time.perf_counter()))
            self._cond.notify()

    def _next_frame(self) -> tuple[_Device, bytes, float] | None:
        """The oldest pending frame of a device with nothing in flight (round robin by dict order), or None."""
        for device in self._devices.values():
            if device.frames and not device.in_flight:
                payload, t0 = device.frames.popleft()
                device.in_flight = True
                return device, payload, t0
        return None

    def _drain_streams(self) -> None:
        while True:
            with self._cond:
                item = None
                while not self._stopping and (item := self._next_frame()) is None:
                    self._cond.wait()
                if self._stopping:
                    return
                # rotate so that one busy device cannot starve the others
                device = item[0]
                self._devices.pop((device.site_id, device.device_id))
                self._devices[(device.site_id, device.device_id)] = device
            self._submit_stream(*item)

    def _submit_stream(self, device: _Device, payload: bytes, t0: float) -> None:
        request_id = uuid.uuid4().hex
        frame_id = None
        try:
            parts, meta = unpack_envelope(payload)
            frame_id = meta.frame_id
            future = self.service.submit(device.site_id, parts, meta)
        except Overloaded:
            # the pool is full: put the frame back (newer frames may push it out) and let the pool drain
            with self._cond:
                device.in_flight = False
                if len(device.frames) < self.settings.stream_queue_per_device:
                    device.frames.appendleft((payload, t0))
                else:
                    self.service.metrics.zenoh_dropped.labels(device.site_id).inc()
                self._cond.wait(_OVERLOAD_RETRY_S)
            return
        except Exception as exc:
            # bind exc now: Python unbinds the name when the except block ends, before the outbox thread runs this
            self._outbox.put(lambda exc=exc: self._publish_error(device, exc, request_id, frame_id, t0))
            return
        future.add_done_callback(
            lambda f: self._outbox.put(lambda: self._publish_done(device, f, request_id, frame_id, t0)))

    def _release(self, device: _Device) -> None:
        with self._cond:
            device.in_flight = False
            self._cond.notify()

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
            self._log("stream", request_id, device.site_id, "ok", t0)
        finally:
            self._release(device)

    def _publish_error(self, device: _Device, exc: BaseException, request_id: str, frame_id: str | None,
                       t0: float) -> None:
        try:
            body = error_body(exc, request_id)
            wire.stamp_stream_body(body, "error", frame_id, device.device_id)
            self.session.put(wire.poses_key(device.site_id, device.device_id), encode_result(body),
                             encoding=wire.ERROR_ENCODING)
            self._log("stream", request_id, device.site_id, body["code"], t0)
        finally:
            self._release(device)
