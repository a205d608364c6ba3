"""Pages of the list calls: an offset and a page size, the same for REST (``?offset=&limit=``,
``Link: <...>; rel="next"``) and gRPC (``page_size``, ``page_token``: the offset as text).

A page holds at most ``max`` items (``default`` when the client names no size), so a tenant's
list costs one page's work however long it grows. An offset is enough here: lists are ordered
by what does not change (creation time, then id; an image's name), so a page boundary moves only
when items before it are deleted, and then a client sees an item twice or misses one it could not
have relied on anyway. A project's jobs come newest first, what a person looks for: a job started
between two pages moves the boundary by one, and the next page repeats one job.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

from geomatch_core.errors import InvalidRequest

T = TypeVar("T")


@dataclass(frozen=True)
class PageSize:
    default: int
    max: int

    def clamp(self, requested: int | None) -> int:
        """The size of a page: the default for none (or 0, gRPC's unset), at most ``max``."""
        if not requested or requested < 0:
            return self.default
        return min(requested, self.max)


PROJECTS = PageSize(default=100, max=1000)
IMAGES = PageSize(default=1000, max=1000)  # one page holds a usual project: the console reads one
JOBS = PageSize(default=100, max=1000)


@dataclass(frozen=True)
class Page(Generic[T]):
    items: list[T]
    next_offset: int | None  # None: this is the last page


def page_of(rows: list[T], offset: int, limit: int) -> Page[T]:
    """``rows`` read with ``LIMIT limit + 1``: the extra row only tells that another page exists."""
    more = len(rows) > limit
    return Page(rows[:limit], offset + limit if more else None)


def offset_of(token: str) -> int:
    """A gRPC page token back to its offset ('' is the first page)."""
    if not token:
        return 0
    if not token.isdigit() or len(token) > 12:
        raise InvalidRequest(f"page_token {token[:40]!r} is not one this server gave")
    return int(token)
