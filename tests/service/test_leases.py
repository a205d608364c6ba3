"""The reaper's decisions against a real Redis (workers.leases, workers.liveness): which
unacknowledged messages go back to the queue, and that racing reapers restore each only once.
The broker's side (which tags are unacknowledged, and the restore itself) is passed in, as
workers.lifeline passes kombu's; here it is a dict and a list."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest
import redis

from workers.leases import Leases
from workers.liveness import Registry

pytestmark = pytest.mark.service
LEASE = 30


@pytest.fixture
def r(redis_url: str) -> Iterator[redis.Redis]:
    client = redis.Redis.from_url(redis_url)
    prefix = f"gmtest-lease-{uuid.uuid4().hex[:8]}:"
    client.prefix = prefix  # type: ignore[attr-defined]
    yield client
    for k in client.scan_iter(f"{prefix}*"):
        client.delete(k)


def parts(r: redis.Redis) -> tuple[Registry, Leases]:
    prefix = r.prefix  # type: ignore[attr-defined]
    return Registry(r, prefix, LEASE), Leases(r, prefix, LEASE)


def test_a_dead_workers_steps_are_restored_once_and_a_live_ones_kept(r: redis.Redis) -> None:
    registry, leases = parts(r)
    now = registry.now()
    registry.beat("live/1")
    r.zadd(registry.key, {"dead/2": now - LEASE - 1})  # its last beat, a lease ago
    assert registry.alive() == {"live/1"}
    leases.hold("t-live", "live/1")
    leases.hold("t-dead", "dead/2")
    leases.hold("t-acked", "live/1")  # acknowledged since: not in the unacked index any more
    unacked = {"t-live": now - 500, "t-dead": now - 500, "t-new": now - 1, "t-lost": now - LEASE - 5}
    restored: list[str] = []
    first = leases.reap(registry.alive(), now, lambda: unacked, restored.append)
    # the dead worker's, and one without a lease a lease after delivery (its worker died before
    # writing it); not the live worker's, nor one delivered a second ago (its lease is on its way)
    assert sorted(first) == sorted(restored) == ["t-dead", "t-lost"]
    assert set(leases.held()) == {"t-live"}  # the acknowledged one's lease is gone too


def test_racing_reapers_restore_a_message_once(r: redis.Redis) -> None:
    registry, leases = parts(r)
    _, other = parts(r)
    now = registry.now()
    r.zadd(registry.key, {"dead/2": now - LEASE - 1})
    leases.hold("t", "dead/2")
    broker = {"t": now - 100}  # the unacked index; a restore takes the message out of it
    restored: list[str] = []

    def restore(tag: str) -> None:
        broker.pop(tag)
        restored.append(tag)

    def unacked_then_the_other_reaps() -> dict[str, float]:
        seen = dict(broker)  # this reaper has read the leases and the index ...
        other.reap(registry.alive(), now, lambda: dict(broker), restore)  # ... the other acts first
        return seen

    leases.reap(registry.alive(), now, unacked_then_the_other_reaps, restore)
    assert restored == ["t"]
    # and after it, one more reaper finds nothing to do
    leases.reap(registry.alive(), now, lambda: dict(broker), restore)
    assert restored == ["t"] and leases.held() == {}


def test_a_worker_that_stops_leaves_the_live_set_and_old_ones_age_out(r: redis.Redis) -> None:
    registry, _ = parts(r)
    registry.beat("a/1")
    registry.beat("b/2")
    registry.forget("a/1")
    assert registry.alive() == {"b/2"}
    r.zadd(registry.key, {"b/2": registry.now() - LEASE - 1})
    assert registry.alive() == set()
