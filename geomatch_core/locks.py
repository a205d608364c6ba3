"""One writer per project at a time: a Redis lock where workers share Redis (any host), a file
lock in the embedded default (one host, no servers).

A lock held by a process that died is released by the lock itself: the Redis key expires after
``timeout`` seconds, the kernel drops an flock with its holder. Writes under the lock are short
(one pair's transaction), so the timeout only matters after a crash.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from .errors import Unavailable

if TYPE_CHECKING:
    import redis


class LockFactory(Protocol):
    def project(self, project_id: str) -> AbstractContextManager[None]: ...


class FileLocks:
    def __init__(self, path_for: Callable[[str], Path], wait_s: float = 600.0) -> None:
        self._path_for = path_for
        self.wait_s = wait_s

    @contextmanager
    def project(self, project_id: str) -> Iterator[None]:
        path = self._path_for(project_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            deadline = time.monotonic() + self.wait_s
            while True:  # flock conflicts between open file descriptions, i.e. threads too
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise Unavailable(
                            f"project {project_id}: writer lock busy for {self.wait_s:.0f}s"
                        ) from None
                    time.sleep(0.05)
            try:
                yield
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)


class RedisLocks:
    def __init__(self, client: redis.Redis, prefix: str, timeout_s: int, wait_s: float = 600.0) -> None:
        self.client = client
        self.prefix = prefix
        self.timeout_s = timeout_s
        self.wait_s = wait_s

    @contextmanager
    def project(self, project_id: str) -> Iterator[None]:
        lock = self.client.lock(
            f"{self.prefix}lock:project:{project_id}",
            timeout=self.timeout_s,
            blocking_timeout=self.wait_s,
            sleep=0.05,
        )
        if not lock.acquire():
            raise Unavailable(f"project {project_id}: writer lock busy for {self.wait_s:.0f}s")
        try:
            yield
        finally:
            # expired meanwhile (a write longer than the timeout): nothing left to release
            with contextlib.suppress(Exception):
                lock.release()
