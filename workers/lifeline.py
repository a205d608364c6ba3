"""A worker's beat and its reaper, wired into Celery: ``workers.liveness`` and ``workers.leases``.

Everything runs in the worker's main process (the consumer), not in its pool processes: the main
process receives every message, so it writes each lease, and its thread keeps beating while a
pool process spends minutes in one mapping call. A pool process that dies under a live main
process is Celery's own case (``task_reject_on_worker_lost``: its step is requeued at once); this
is for the whole worker gone (SIGKILL, out of memory, a lost host), whose unacknowledged steps
Redis would otherwise hand out again only after the visibility timeout.

The beat starts once the consumer is ready (so a worker counts for readiness when it takes work)
and stops, leaving the set of live workers, after a warm shutdown has finished its steps.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from typing import Any

import redis
from celery import Celery, signals
from kombu import Connection

from geomatch_core.config import Settings

from .leases import Leases
from .liveness import Registry, beat_period, new_worker_id

log = logging.getLogger("geomatch.workers")


class Lifeline:
    def __init__(self, app: Celery, settings: Settings, hostname: str) -> None:
        assert settings.redis_url is not None
        self.app = app
        self.worker_id = new_worker_id(hostname)
        client = redis.Redis.from_url(settings.redis_url, socket_timeout=5, socket_connect_timeout=5)
        self.registry = Registry(client, settings.redis_prefix, settings.worker_lease_s)
        self.leases = Leases(client, settings.redis_prefix, settings.worker_lease_s)
        self.period = beat_period(settings.worker_lease_s)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="geomatch-lifeline", daemon=True)

    def start(self) -> None:
        self._beat_and_reap(None)  # counted before the first message, not a period later
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        try:
            self.registry.forget(self.worker_id)
        except redis.RedisError as e:  # it ages out of the set within a lease anyway
            log.warning("could not leave the set of live workers: %s", e)

    def hold(self, tag: str) -> None:
        try:
            self.leases.hold(tag, self.worker_id)
        except redis.RedisError as e:  # reaped a lease after delivery instead: may run twice
            log.warning("no lease for message %s: %s", tag, e)

    def _run(self) -> None:
        conn: Connection | None = None
        while not self._stop.wait(self.period):
            if conn is None:
                conn = self.app.connection_for_write()
            if not self._beat_and_reap(conn):
                conn.release()  # a broken connection: a fresh one next time
                conn = None
        if conn is not None:
            conn.release()

    def _beat_and_reap(self, conn: Connection | None) -> bool:
        try:
            self.registry.beat(self.worker_id)
            if conn is not None:
                self._reap(conn.default_channel)
            return True
        except Exception as e:  # Redis away: the next period tries again
            log.warning("worker beat / reap failed: %s", e)
            return False

    def _reap(self, channel: Any) -> None:
        def unacked() -> Mapping[str, float]:
            rows = channel.client.zrange(channel.unacked_index_key, 0, -1, withscores=True)
            return {(t.decode() if isinstance(t, bytes) else str(t)): float(s) for t, s in rows}

        restored = self.leases.reap(
            self.registry.alive(), self.registry.now(), unacked, lambda tag: channel.qos.restore_by_tag(tag)
        )
        if restored:
            log.warning(
                "returned %d step(s) held by dead worker(s) to the queue: %s", len(restored), restored
            )


def install(app: Celery, settings: Settings) -> None:
    """Connect the lifeline to this app's worker signals (a no-op outside ``celery worker``)."""
    line: list[Lifeline] = []

    @signals.worker_init.connect(weak=False)
    def init(sender: Any = None, **_: Any) -> None:
        if getattr(sender, "app", None) is app and not line:  # before any message can arrive
            line.append(Lifeline(app, settings, str(getattr(sender, "hostname", ""))))

    @signals.worker_ready.connect(weak=False)
    def ready(sender: Any = None, **_: Any) -> None:
        if line and getattr(sender, "app", None) is app:
            line[0].start()
            log.info(
                "worker %s: beats every %.1fs, lease %ds",
                line[0].worker_id,
                line[0].period,
                settings.worker_lease_s,
            )

    @signals.task_received.connect(weak=False)
    def received(sender: Any = None, request: Any = None, **_: Any) -> None:
        if line and getattr(sender, "app", None) is app and request is not None:
            tag = getattr(request.message, "delivery_tag", None)
            if tag is not None:
                line[0].hold(str(tag))

    @signals.worker_shutdown.connect(weak=False)
    def shutdown(sender: Any = None, **_: Any) -> None:
        if line and getattr(sender, "app", None) is app:
            line.pop().stop()
