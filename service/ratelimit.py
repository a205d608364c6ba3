"""A request rate per tenant: a token bucket of ``burst`` tokens refilled at ``per_s`` a second.

One bucket per tenant in this process (REST and gRPC share it: both authenticate through
``Service.authenticate``). Several API processes each hold their own, so a deployment's rate is
the sum of its processes'; the limit is there to keep one client from flooding a process, which a
per-process bucket does without a round trip to Redis on every request.
"""

from __future__ import annotations

import math
import threading
import time

from geomatch_core.errors import RateLimited


class RateLimiter:
    def __init__(self, per_s: float, burst: int) -> None:
        self.per_s = per_s  # 0: no limit
        self.burst = float(max(1, burst))
        self._lock = threading.Lock()
        self._buckets: dict[str, tuple[float, float]] = {}  # tenant -> (tokens, when)

    def take(self, tenant_id: str) -> None:
        """One request of ``tenant_id``, or RateLimited with the seconds until it may retry."""
        if self.per_s <= 0:
            return
        now = time.monotonic()
        with self._lock:
            tokens, when = self._buckets.get(tenant_id, (self.burst, now))
            tokens = min(self.burst, tokens + (now - when) * self.per_s)
            if tokens < 1.0:
                self._buckets[tenant_id] = (tokens, now)
                wait = max(1, math.ceil((1.0 - tokens) / self.per_s))
                raise RateLimited(
                    f"too many requests: this key's tenant may make {self.per_s:g} a second "
                    f"(bursts of {self.burst:g}); retry in {wait} s",
                    retry_after_s=wait,
                )
            self._buckets[tenant_id] = (tokens - 1.0, now)
