"""Leases: which worker holds which delivered step, so that a dead worker's steps go back to the
queue within a lease instead of the broker's visibility timeout (an hour by default, which must
exceed the longest step).

A worker writes ``tag -> "<worker id> <nonce>"`` into ``<prefix>leases`` when it receives a
message (the step it will run and the one it prefetched alike). The lease lasts as long as its
worker beats (``workers.liveness``): there is no per-step renewal to forget inside a long mapping
call. Every worker reaps: a message still unacknowledged whose holder is no longer alive is put
back at the head of its queue (kombu's own restore, the one the visibility timeout uses: same
message, same task id, same retry count), and its lease deleted.

Every decision is safe to race with another reaper and with a worker taking the message again:
a lease is deleted only if it still holds the value read (the nonce makes each receipt's value
unique), and only the reaper that deleted it restores the message. The worst case, a message
that never got its lease (its worker died between the broker's delivery and the lease write, or
Redis failed that write), is restored once it is a lease old: its step may then run twice, which
steps are written for (``workers.jobs``: idempotent, each pair written once).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import redis

log = logging.getLogger("geomatch.workers")

# delete a lease only if it still says what the reaper read: a worker may have taken the message again
_DELETE_IF = """
if redis.call('HGET', KEYS[1], ARGV[1]) == ARGV[2] then
  return redis.call('HDEL', KEYS[1], ARGV[1])
end
return 0
"""


def _text(v: bytes | str) -> str:
    return v.decode() if isinstance(v, bytes) else v


class Leases:
    def __init__(self, client: redis.Redis, prefix: str, lease_s: int) -> None:
        self.client = client
        self.key = f"{prefix}leases"
        self.lease_s = lease_s
        self._delete_if = client.register_script(_DELETE_IF)

    def hold(self, tag: str, worker_id: str) -> None:
        self.client.hset(self.key, tag, f"{worker_id} {uuid.uuid4().hex[:8]}")

    def held(self) -> dict[str, str]:
        """tag -> lease value."""
        return {_text(k): _text(v) for k, v in self.client.hgetall(self.key).items()}

    def _release(self, tag: str, value: str) -> bool:
        return bool(self._delete_if(keys=[self.key], args=[tag, value]))

    def reap(
        self,
        alive: set[str],
        now: float,
        unacked: Callable[[], Mapping[str, float]],
        restore: Callable[[str], None],
    ) -> list[str]:
        """Restore the unacknowledged messages whose holder is dead; drop leases of messages
        acknowledged since. ``unacked()``: tag -> delivery time (kombu's index, the receiving
        worker's clock; ``now`` is Redis's, hosts are assumed within seconds); read after the
        leases, so a lease whose tag it lacks belongs to a message acknowledged (or restored)
        since the lease was written. Returns the tags restored."""
        leases = self.held()
        delivered = unacked()
        restored = []
        for tag, at in delivered.items():
            value = leases.get(tag)
            if value is not None:
                if value.split(" ", 1)[0] in alive or not self._release(tag, value):
                    continue
            elif now - at < self.lease_s or self.client.hexists(self.key, tag):
                continue  # just delivered: its lease is being written
            restore(tag)
            restored.append(tag)
        for tag, value in leases.items():
            if tag not in delivered:
                self._release(tag, value)
        return restored

    def orphans(self, worker_id: str, held: set[str]) -> dict[str, str]:
        """Leases of ``worker_id`` on messages it no longer holds (``held``: the delivery tags its
        consumer has reserved, running or scheduled), tag -> lease value. Such a message stays in
        the broker's unacknowledged set with a live holder, so the reaper leaves it there for the
        visibility timeout (an hour): a step whose reject or ack failed in a Redis failover (the
        reject itself answered READONLY), or whose consumer lost its connection."""
        return {
            tag: value
            for tag, value in self.held().items()
            if value.split(" ", 1)[0] == worker_id and tag not in held
        }

    def restore(self, tag: str, value: str, restore: Callable[[str], None]) -> bool:
        """Restore ``tag``'s message if its lease still says ``value`` (deleted first, so that a
        racing reaper restores it once)."""
        if not self._release(tag, value):
            return False
        restore(tag)
        return True
