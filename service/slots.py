"""Fair slots: at most ``total`` calls of one kind at once, at most ``per_tenant`` of one tenant,
and a reserve that a tenant holding many cannot take.

A cap per tenant alone is not fair: with 48 slots and 16 per tenant, three tenants holding idle
calls took every slot and a fourth got nothing. So the last ``reserve`` free slots go only to
tenants holding fewer than ``share`` calls: a tenant at or over its share may take a slot only
while more than ``reserve`` are free. A newcomer then finds a slot unless the server is full of
tenants holding their share each, which is a full server, not one tenant's doing.

Refusal is immediate (``Overloaded``: 429 / RESOURCE_EXHAUSTED): a caller waiting for a slot would
hold the very thread or connection the limit protects.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from geomatch_core.errors import Overloaded


class FairSlots:
    def __init__(self, what: str, total: int, per_tenant: int) -> None:
        self.what = what  # named in the refusal: "streaming calls", "heavy calls"
        self.total = total
        self.per_tenant = min(per_tenant, total)
        self.share = max(1, self.per_tenant // 4)
        self.reserve = total // 4 if self.per_tenant > self.share else 0
        self._lock = threading.Lock()
        self._open = 0
        self._by_tenant: dict[str, int] = {}

    @contextmanager
    def open(self, tenant_id: str) -> Iterator[None]:
        self.acquire(tenant_id)
        try:
            yield
        finally:
            self.release(tenant_id)

    def acquire(self, tenant_id: str) -> None:
        with self._lock:
            mine = self._by_tenant.get(tenant_id, 0)
            if mine >= self.per_tenant:
                raise Overloaded(
                    f"this key's tenant has {mine} {self.what} open, the most one tenant may hold "
                    "at once; retry when one has ended"
                )
            free = self.total - self._open
            if free <= 0 or (mine >= self.share and free <= self.reserve):
                raise Overloaded(
                    f"the server has {self._open} {self.what} open and keeps the rest for tenants "
                    f"holding fewer than {self.share}; retry shortly"
                )
            self._open += 1
            self._by_tenant[tenant_id] = mine + 1

    def release(self, tenant_id: str) -> None:
        with self._lock:
            self._open -= 1
            left = self._by_tenant[tenant_id] - 1
            if left:
                self._by_tenant[tenant_id] = left
            else:
                del self._by_tenant[tenant_id]

    def counts(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            return self._open, dict(self._by_tenant)
