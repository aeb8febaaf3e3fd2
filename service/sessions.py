"""Tracking sessions, held in the service's parent process and handed to whichever worker takes a session's frame.

A session is a zenoh stream device (`cadreg/<site>/frames/<device>`) or a client that sends `session_id` in the
frame meta (HTTP, zenoh queries). Its state is the core's `TrackState` in its plain form
(`cadreg.localize.tracking.TrackState.to_dict`: a few hypotheses of 4x4 poses and velocities): the parent stores it
as it came back from the worker and sends it with the session's next job, so any worker can track any session and a
worker that dies loses nothing.

Bounded, whatever the network sends (issue 12): a session unused for `session_ttl_s` is forgotten; at most
`max_sessions` are held, and at the cap the least recently used one is forgotten to make room; a state holds at most
TrackConfig.max_hypotheses hypotheses (the core's bound). A site reload drops the site's sessions: their poses
belong to the map that was replaced. Thread-safe (HTTP's event loop, zenoh's threads and the pool's dispatcher
all call in).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# (front end, site id, session id): a zenoh device and an HTTP session of the same name are different sessions
SessionKey = tuple[str, str, str]


def session_key(site_id: str, session_id: str | None, device_id: str | None) -> SessionKey | None:
    """The session a frame belongs to: its meta's `session_id`, else its zenoh stream device, else none."""
    if session_id is not None:
        return ("session", site_id, session_id)
    if device_id is not None:
        return ("device", site_id, device_id)
    return None


@dataclass(frozen=True)
class SessionJob:
    """What travels with a session's job to the worker: the stored state (None for a new session) and the frame's
    time in seconds, the clock of the stored state's `t_s`: the client's capture stamp (meta `stamp_s`) when the
    frame has one, else its arrival on the parent's monotonic clock."""

    state: dict[str, Any] | None
    t_s: float
    stamped: bool = False
    # The session's search lease: only the job holding it may run a global search (`Localizer.track(may_search=)`);
    # a frame sent while another frame of its session holds it and fails to track is answered at once. None: no
    # lease (`SessionStore.release` is called with it, whatever the job's outcome).
    lease: int | None = None

    @property
    def may_search(self) -> bool:
        return self.lease is not None


@dataclass
class _Entry:
    state: dict[str, Any]
    site_version: str
    used_s: float
    stamped: bool


def _age(state: dict[str, Any]) -> tuple[float, float]:
    """How recent a state is: the time of its last accepted frame, then of its last search that found nothing (a
    failed search keeps the accepted time, and a frame answered beside it must not undo what it learnt)."""
    searched = state.get("searched_s")
    return float(state.get("t_s", 0.0)), float("-inf") if searched is None else float(searched)


class SessionStore:
    """Session states by key, least recently used first; expired on access and on every store."""

    def __init__(self, *, ttl_s: float, max_sessions: int, clock: Callable[[], float] = time.monotonic) -> None:
        if ttl_s <= 0 or max_sessions < 1:
            raise ValueError("sessions need a positive ttl_s and max_sessions >= 1")
        self.ttl_s = float(ttl_s)
        self.max_sessions = int(max_sessions)
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: OrderedDict[SessionKey, _Entry] = OrderedDict()
        self.evicted = 0  # forgotten at the cap (a gauge of pressure, read by tests and metrics)
        self.expired = 0
        # Search leases in flight: key -> (token, expiry). One per session, so a stream's frames in flight never
        # run two global searches at once (each costs 10-50 tracked frames, and the frames behind them would be
        # dropped). Released when the job is done; the expiry (lease_s) frees a lease whose release was lost, and
        # at most max_sessions are held (`_grant_lease`).
        self._leases: dict[SessionKey, tuple[int, float]] = {}
        self._next_lease = 0
        self.lease_s = max(self.ttl_s, 1.0)

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def job(self, key: SessionKey, site_version: str, stamp_s: float | None = None) -> SessionJob:
        """The state to send with this session's next frame (None when new, expired, of another bundle version,
        timed by the other clock, or newer than this frame's stamp) and the frame's time (`stamp_s`, the client's
        capture time, or now)."""
        now = self._clock()
        stamped = stamp_s is not None
        with self._lock:
            self._expire(now)
            entry = self._entries.get(key)
            if entry is not None and (entry.site_version != site_version or entry.stamped != stamped
                                      or (stamped and stamp_s < float(entry.state.get("t_s", 0.0)))):
                # a pose in a map that was replaced means nothing in the new one; times on two clocks, no motion;
                # and a stamp before the state's own time is a device whose clock restarted (a robot rebooted, a
                # replay started over): a device's frames are sent in order, so its state would otherwise refuse
                # every new state as older than itself until the TTL forgot it, and each frame would be a search
                del self._entries[key]
                entry = None
            if entry is not None:
                entry.used_s = now
                self._entries.move_to_end(key)
            return SessionJob(None if entry is None else entry.state, stamp_s if stamped else now, stamped,
                              self._grant_lease(key, now))

    def _grant_lease(self, key: SessionKey, now: float) -> int | None:
        """A new search lease for `key`, or None while another job of the session holds one (lock held)."""
        held = self._leases.pop(key, None)
        if held is not None and held[1] > now:
            self._leases[key] = held
            return None
        # Releases keep this to the jobs in flight; whatever arrives, at most max_sessions leases are held, the
        # oldest granted dropped first (kept in grant order: O(1)). A dropped lease only lets its session's next
        # frame search while an earlier one may still be searching.
        while len(self._leases) >= self.max_sessions:
            del self._leases[next(iter(self._leases))]
        self._next_lease += 1
        self._leases[key] = (self._next_lease, now + self.lease_s)
        return self._next_lease

    def release(self, key: SessionKey, lease: int | None) -> None:
        """The job holding `lease` is done (answered, failed or cancelled): the session's next job may search."""
        if lease is None:
            return
        with self._lock:
            held = self._leases.get(key)
            if held is not None and held[0] == lease:
                del self._leases[key]

    def leases(self) -> int:
        """Search leases held now (one per session with a job that may search in flight)."""
        with self._lock:
            return len(self._leases)

    def store(self, key: SessionKey, state: dict[str, Any] | None, site_version: str, *, stamped: bool = False) -> None:
        """Keep the state the worker returned (None: nothing worth keeping, the session is forgotten). A state
        older than the one stored (frames of one session answered out of order; `_age`) is not kept."""
        now = self._clock()
        with self._lock:
            self._expire(now)
            if state is None:
                self._entries.pop(key, None)
                return
            held = self._entries.get(key)
            if held is not None and held.stamped == stamped and _age(held.state) > _age(state):
                return
            self._entries[key] = _Entry(state, site_version, now, stamped)
            self._entries.move_to_end(key)
            while len(self._entries) > self.max_sessions:
                self._entries.popitem(last=False)
                self.evicted += 1

    def holds(self, key: SessionKey) -> bool:
        """Whether `key` has a stored state (expiry aside): its next frame will likely be tracked, not searched."""
        with self._lock:
            return key in self._entries

    def drop_site(self, site_id: str) -> int:
        """Forget every session of `site_id` (a reload); returns how many."""
        with self._lock:
            keys = [k for k in self._entries if k[1] == site_id]
            for k in keys:
                del self._entries[k]
            return len(keys)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def _expire(self, now: float) -> None:
        """Drop sessions unused for the TTL (lock held). Ordered by last use: O(expired)."""
        horizon = now - self.ttl_s
        while self._entries:
            key, entry = next(iter(self._entries.items()))
            if entry.used_s > horizon:
                return
            del self._entries[key]
            self.expired += 1
