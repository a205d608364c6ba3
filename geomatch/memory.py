"""The memory of a run or a worker: least-recently-used caches bounded in bytes, never in
entries (:class:`ByteLRU`), and the heap a finished stage freed handed back to the operating
system (:func:`return_freed_memory`).

Why bytes: an entry's size spans two orders of magnitude (a 640x480 render is 0.9 MB, a 12 MP
photo 36 MB; a 640 px feature set without dense maps a few MB, with them over a hundred), so a
count bound that is safe for the large entries wastes memory on the small ones, and one that suits
the small ones lets a worker grow by gigabytes on the large ones.

Why hand it back: glibc keeps the heap it has grown (the matcher's caches are many small and
mid-sized allocations), so a process that emptied gigabytes of caches before mapping still holds
them, and the mapper's own peak lands on top. ``malloc_trim`` returns the free heap pages; on a libc
without it (musl, macOS) this is a no-op and the caches are merely reusable by the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from functools import cache
from typing import Generic, TypeVar

import numpy as np

from .options import OptionError

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


@cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim: Callable[[int], int] = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    return trim


def return_freed_memory() -> bool:
    """Collect garbage and trim the heap; True when the heap was trimmed (glibc)."""
    gc.collect()
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


# GEOMATCH_CACHE_MB: the in-memory caches of one job (a worker's job thread, or `geomatch run`), in
# MiB, all together. One number because an operator sizes a process, not its caches.
CACHE_MB = 1536


# GEOMATCH_RUN_FEATURES_MB: the on-disk feature store of a run's folder (``OUT/features``), in MiB;
# 0 turns it off (the service's store is GEOMATCH_FEATURE_CACHE_MB, in its storage). A run keeps
# its features so that ``geomatch localize OUT`` and a resumed run read them instead of running the
# networks again: a new photo is then matched against the model without re-extracting the model's
# images, which is most of a cold localization's time.
RUN_FEATURES_MB = 4096


def env_mib(name: str, default: float) -> float:
    """A MiB setting from the environment (``default`` when unset); a clear error when not a number."""
    raw = os.environ.get(name, "").strip()
    try:
        return float(raw) if raw else default
    except ValueError:
        raise OptionError(f"{name} must be a number of MiB, got {raw!r}") from None


def run_feature_store_bytes() -> int:
    return max(0, int(env_mib("GEOMATCH_RUN_FEATURES_MB", RUN_FEATURES_MB) * 1024 * 1024))


@dataclass(frozen=True)
class CacheBudget:
    """How one GEOMATCH_CACHE_MB is shared by a job's in-memory caches, in MiB: decoded images
    (1/6: a pair needs two, a tiled pair reuses its aerial image), then per matcher the per-image
    features (4/5 of the rest, dense maps included) and recent pairs' LightGlue outputs (1/5).
    The default 1536 gives 256 / 1024 / 256, :class:`~geomatch.matching.matcher.MatcherConfig`'s own."""

    images_mb: float
    features_mb: float
    anchors_mb: float


def cache_budget(total_mb: float | None = None, matchers: int = 1) -> CacheBudget:
    """The split of ``total_mb`` (default: GEOMATCH_CACHE_MB, else :data:`CACHE_MB`) for a job
    that keeps up to ``matchers`` matchers (distinct option sets), each with its own caches."""
    if total_mb is None:
        total_mb = env_mib("GEOMATCH_CACHE_MB", CACHE_MB)
    total_mb = max(64.0, total_mb)
    per_matcher = 5 / 6 * total_mb / max(1, matchers)
    return CacheBudget(total_mb / 6, 0.8 * per_matcher, 0.2 * per_matcher)
