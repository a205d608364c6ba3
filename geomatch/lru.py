"""Least-recently-used caches bounded in bytes, never in entries.

Why bytes: an entry's size spans two orders of magnitude (a 640x480 render is 0.9 MB, a 12 MP
photo 36 MB; a 640 px feature set without dense maps a few MB, with them over a hundred), so a
count bound that is safe for the large entries wastes memory on the small ones, and one that suits
the small ones lets a worker grow by gigabytes on the large ones.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

import numpy as np

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


def trim_lru(cache: OrderedDict[K, V], budget_mb: float, nbytes: Callable[[V], int], keep: int) -> None:
    """Drop the least recently used entries until ``cache`` fits ``budget_mb`` (at least ``keep``
    entries stay, so the entry just added survives a budget smaller than itself)."""
    total = sum(nbytes(v) for v in cache.values())
    while len(cache) > keep and total > budget_mb * 2**20:
        total -= nbytes(cache.popitem(last=False)[1])


class ByteLRU(Generic[K, V]):
    """A mapping that forgets its least recently used entries beyond ``budget_mb``; the newest
    entry always stays (a pair needs both its images even when one alone exceeds the budget)."""

    def __init__(self, budget_mb: float, nbytes: Callable[[V], int] = lambda v: int(np.asarray(v).nbytes)):
        self.budget_mb = budget_mb
        self._nbytes = nbytes
        self._data: OrderedDict[K, V] = OrderedDict()
        self._total = 0

    def get(self, key: K) -> V | None:
        value = self._data.get(key)
        if value is not None:
            self._data.move_to_end(key)
        return value

    def put(self, key: K, value: V) -> None:
        old = self._data.pop(key, None)
        if old is not None:
            self._total -= self._nbytes(old)
        self._data[key] = value
        self._total += self._nbytes(value)
        while len(self._data) > 1 and self._total > self.budget_mb * 2**20:
            self._total -= self._nbytes(self._data.popitem(last=False)[1])

    def nbytes(self) -> int:
        return self._total

    def clear(self) -> None:
        self._data.clear()
        self._total = 0

    def __len__(self) -> int:
        return len(self._data)

    def __contains__(self, key: object) -> bool:
        return key in self._data
