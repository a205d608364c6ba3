"""Handing memory that a finished stage freed back to the operating system.

Why: glibc keeps the heap it has grown (the matcher's caches are many small and mid-sized
allocations), so a process that emptied gigabytes of caches before mapping still holds them, and
the mapper's own peak lands on top. ``malloc_trim`` returns the free heap pages; on a libc without
it (musl, macOS) this is a no-op and the caches are merely reusable by the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
from collections.abc import Callable
from functools import cache


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
