"""The parent's store of tracking sessions (service/sessions.py): bounded by a TTL and a cap whatever the network
sends, dropped per site, never mixing bundle versions or clocks; and its settings validated at start."""

from __future__ import annotations

import pytest

from cadreg.errors import ConfigError
from service.sessions import SessionStore
from service.settings import settings_from


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _state(t_s: float) -> dict:
    return {"t_s": t_s, "confirmed": True, "tracks": []}


def test_a_new_session_has_no_state_and_a_stored_one_comes_back() -> None:
    clock = Clock()
    store = SessionStore(ttl_s=10, max_sessions=4, clock=clock)
    job = store.job(("device", "site", "robot"), "v1")
    assert job.state is None and job.t_s == 100.0 and not job.stamped
    store.store(("device", "site", "robot"), _state(100.0), "v1")
    assert store.job(("device", "site", "robot"), "v1").state == _state(100.0)
    assert len(store) == 1


def test_ttl_forgets_idle_sessions() -> None:
    clock = Clock()
    store = SessionStore(ttl_s=10, max_sessions=100, clock=clock)
    store.store(("device", "s", "a"), _state(1.0), "v1")
    clock.now += 5
    store.store(("device", "s", "b"), _state(1.0), "v1")
    clock.now += 6  # a is 11 s idle, b 6 s
    assert store.job(("device", "s", "a"), "v1").state is None
    assert store.job(("device", "s", "b"), "v1").state is not None
    assert store.expired == 1 and len(store) == 1


def test_the_cap_forgets_the_least_recently_used() -> None:
    clock = Clock()
    store = SessionStore(ttl_s=1000, max_sessions=3, clock=clock)
    for name in "abc":
        clock.now += 1
        store.store(("device", "s", name), _state(clock.now), "v1")
    clock.now += 1
    store.job(("device", "s", "a"), "v1")  # a is used again: b is now the least recently used
    store.store(("device", "s", "d"), _state(clock.now), "v1")
    assert len(store) == 3 and store.evicted == 1
    assert store.job(("device", "s", "b"), "v1").state is None
    assert all(store.job(("device", "s", k), "v1").state is not None for k in "acd")


def test_twenty_thousand_distinct_sessions_stay_within_the_cap() -> None:
    store = SessionStore(ttl_s=60, max_sessions=500, clock=Clock())
    for k in range(20_000):
        key = ("device", "s", f"dev-{k}")
        store.job(key, "v1")
        store.store(key, _state(float(k)), "v1")
    assert len(store) == 500 and store.evicted == 19_500


def test_a_reload_drops_the_sites_sessions_only() -> None:
    store = SessionStore(ttl_s=60, max_sessions=10, clock=Clock())
    store.store(("device", "kitchen", "a"), _state(1.0), "v1")
    store.store(("session", "kitchen", "b"), _state(1.0), "v1")
    store.store(("device", "office", "a"), _state(1.0), "v1")
    assert store.drop_site("kitchen") == 2
    assert len(store) == 1 and store.job(("device", "office", "a"), "v1").state is not None


def test_another_bundle_version_or_clock_starts_afresh() -> None:
    store = SessionStore(ttl_s=60, max_sessions=10, clock=Clock())
    key = ("session", "s", "x")
    store.store(key, _state(1.0), "v1")
    assert store.job(key, "v2").state is None  # a pose in the replaced map means nothing in the new one
    store.store(key, _state(1.0), "v1")
    job = store.job(key, "v1", stamp_s=5.0)  # arrival-timed state, stamped frame: two clocks, no motion
    assert job.state is None and job.t_s == 5.0 and job.stamped


def test_an_older_state_does_not_replace_a_newer_one() -> None:
    store = SessionStore(ttl_s=60, max_sessions=10, clock=Clock())
    key = ("session", "s", "x")
    store.store(key, _state(2.0), "v1", stamped=True)
    store.store(key, _state(1.0), "v1", stamped=True)  # an earlier frame answered later
    assert store.job(key, "v1", stamp_s=3.0).state["t_s"] == 2.0
    store.store(key, None, "v1")  # nothing worth keeping: forgotten
    assert len(store) == 0


@pytest.mark.parametrize("field,value", [("session_ttl_s", 0), ("max_sessions", 0), ("session_ttl_s", -1.0)])
def test_bad_session_settings_fail_at_start(field: str, value: float) -> None:
    with pytest.raises(ConfigError, match=field):
        settings_from(**{field: value})


def test_localize_config_takes_a_track_section(tmp_path) -> None:
    path = tmp_path / "loc.toml"
    path.write_text("[track]\nmax_gap_s = 0.5\nmax_hypotheses = 2\n")
    settings = settings_from(localize_config=str(path))
    assert settings.localize_config.track.max_gap_s == 0.5 and settings.localize_config.track.max_hypotheses == 2
    path.write_text("[track]\nmin_fitness = 2\n")
    with pytest.raises(ConfigError, match="track.min_fitness"):
        settings_from(localize_config=str(path))


def test_a_device_whose_stamps_start_over_gets_a_fresh_session() -> None:
    """A robot that reboots (or a replay that starts again) stamps its frames from 0 again: the state it left, newer
    than every new stamp, would refuse every new state as older than itself until the TTL; it is dropped instead."""
    store = SessionStore(ttl_s=1000, max_sessions=4, clock=Clock())
    key = ("device", "site", "robot")
    store.store(key, _state(50.0), "v1", stamped=True)
    assert store.job(key, "v1", stamp_s=50.1).state == _state(50.0)  # in order: tracked from the state
    job = store.job(key, "v1", stamp_s=0.5)  # the clock went back
    assert job.state is None and job.t_s == 0.5
    store.store(key, _state(0.5), "v1", stamped=True)
    assert store.job(key, "v1", stamp_s=0.6).state == _state(0.5)


def test_one_search_lease_per_session_until_its_job_is_done() -> None:
    """Only the job holding a session's lease may search: a second job of the session in flight gets none, the
    lease comes back when the holder is done (whatever its outcome), and a lease whose release was lost expires."""
    clock = Clock()
    store = SessionStore(ttl_s=30, max_sessions=4, clock=clock)
    key, other = ("device", "site", "robot"), ("device", "site", "other")
    first = store.job(key, "v1")
    second = store.job(key, "v1")
    assert first.may_search and not second.may_search
    assert store.job(other, "v1").may_search  # per session
    store.release(key, second.lease)  # no lease: nothing happens
    assert not store.job(key, "v1").may_search
    store.release(key, first.lease)
    third = store.job(key, "v1")
    assert third.may_search and third.lease != first.lease
    store.release(key, first.lease)  # a stale release does not free the new holder's lease
    assert not store.job(key, "v1").may_search
    clock.now += store.lease_s + 1  # the holder's release never came
    assert store.job(key, "v1").may_search


def test_a_failed_search_is_not_undone_by_a_frame_answered_beside_it() -> None:
    """A search that found nothing keeps the last accepted time and adds its own (`searched_s`): a frame of the
    same session that was answered beside it, from the state before, must not overwrite that, or the next frame
    would search again at once."""
    store = SessionStore(ttl_s=1000, max_sessions=4, clock=Clock())
    key = ("device", "site", "robot")
    before = {"t_s": 10.0, "confirmed": True, "tracks": [], "searched_s": None}
    searched = {**before, "confirmed": False, "searched_s": 10.2}
    store.store(key, before, "v1", stamped=True)
    store.store(key, searched, "v1", stamped=True)
    store.store(key, before, "v1", stamped=True)  # the frame answered beside the search, finishing later
    assert store.job(key, "v1", stamp_s=10.3).state == searched


def test_leases_never_released_stay_within_the_cap() -> None:
    clock = Clock()
    store = SessionStore(ttl_s=10, max_sessions=3, clock=clock)
    for name in "abcdef":
        assert store.job(("device", "s", name), "v1").may_search  # granted, never released (lost releases)
    assert store.leases() == 3  # the oldest granted went first
    assert not store.job(("device", "s", "f"), "v1").may_search  # a held lease stands
    assert store.job(("device", "s", "a"), "v1").may_search  # a dropped one is granted again
