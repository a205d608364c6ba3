"""JobQueue over Celery: what the API (and steps that queue further steps) use with REDIS_URL set.

Steps are sent by name, so the API process never imports the step code (nor torch)."""

from __future__ import annotations

from typing import Any

import redis
from celery import Celery
from celery.exceptions import TimeoutError as CeleryTimeout

from geomatch_core.config import Settings
from geomatch_core.queue import RENDER_PAIR

from .celery_app import interactive_queue, make_app
from .celery_transport import publish_through_failover
from .liveness import Registry


class CeleryQueue:
    def __init__(self, settings: Settings, app: Celery | None = None) -> None:
        self.settings = settings
        self.app = app or make_app(settings)
        assert settings.redis_url is not None
        self._redis = redis.Redis.from_url(settings.redis_url, socket_timeout=5, socket_connect_timeout=5)
        self._workers = Registry(self._redis, settings.redis_prefix, settings.worker_lease_s)

    def enqueue(self, step: str, *args: Any) -> None:
        """Queue a step; through a Redis failover of a few seconds (READONLY) it waits, rather than
        failing the step that queues the next one or the request that starts a job."""
        queue = interactive_queue(self.settings) if step == RENDER_PAIR else self.settings.queue
        publish_through_failover(lambda: self.app.send_task(step, args=list(args), queue=queue, retry=False))

    def call(self, step: str, *args: Any, timeout: float) -> Any:
        r = self.app.send_task(step, args=list(args), queue=interactive_queue(self.settings), expires=timeout)
        try:
            return r.get(timeout=timeout, propagate=True)
        except CeleryTimeout:
            raise TimeoutError(f"{step} did not finish within {timeout}s") from None
        finally:
            r.forget()

    def ping(self) -> None:
        self._redis.ping()

    def slots(self) -> int:
        """Two per live worker: the step it runs and the one it prefetched."""
        return 2 * max(1, len(self._workers.alive()))

    def workers_alive(self) -> int:
        return len(self._workers.alive())

    def close(self) -> None:
        self._redis.close()
