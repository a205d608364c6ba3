"""Which workers are alive: every worker process writes its id and Redis's clock into one sorted
set (``<prefix>workers``) every ``lease / 6`` seconds; one heard from within the lease is alive.

Read by the API (readiness: is any worker there?) and by every worker's reaper (whose steps must
go back to the queue?). Redis's own clock is used for the beats and the reads, so hosts whose
clocks disagree still agree on who is alive. A worker id carries a random part: a container
restarted with the same host name and process id is a new worker, not the dead one revived.
"""

from __future__ import annotations

import socket
import uuid
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import redis

FORGET_AFTER_S = 86_400  # beats older than this are pruned from the set (dead workers' ids)


def new_worker_id(hostname: str) -> str:
    return f"{hostname or socket.gethostname()}/{uuid.uuid4().hex[:8]}"


def beat_period(lease_s: int) -> float:
    """Six beats per lease: a worker must miss all six (30 s by default) to be counted dead, so a
    loaded machine's late beat does not hand its steps to another worker."""
    return lease_s / 6


class Registry:
    def __init__(self, client: redis.Redis, prefix: str, lease_s: int) -> None:
        self.client = client
        self.key = f"{prefix}workers"
        self.lease_s = lease_s

    def now(self) -> float:
        seconds, micros = self.client.time()
        return float(seconds) + micros / 1e6

    def beat(self, worker_id: str) -> None:
        now = self.now()
        pipe = self.client.pipeline()
        pipe.zadd(self.key, {worker_id: now})
        pipe.zremrangebyscore(self.key, "-inf", now - FORGET_AFTER_S)
        pipe.execute()

    def forget(self, worker_id: str) -> None:
        """A worker that stopped cleanly: it leaves readiness at once (it held nothing any more)."""
        self.client.zrem(self.key, worker_id)

    def alive(self) -> set[str]:
        """Ids of the workers heard from within the lease."""
        ids = self.client.zrangebyscore(self.key, self.now() - self.lease_s, "+inf")
        return {i.decode() if isinstance(i, bytes) else str(i) for i in ids}
