"""A worker's beat and its reaper, wired into Celery: ``workers.liveness`` and ``workers.leases``.

Everything runs in the worker's main process (the consumer), not in its pool processes: the main
process receives every message, so it writes each lease, and its thread keeps beating while a
pool process spends minutes in one mapping call. A pool process that dies under a live main
process is Celery's own case (``task_reject_on_worker_lost``: its step is requeued at once); this
is for the whole worker gone (SIGKILL, out of memory, a lost host), whose unacknowledged steps
Redis would otherwise hand out again only after the visibility timeout.

The beat starts once the consumer is ready (so a worker counts for readiness when it takes work)
and stops, leaving the set of live workers, after a warm shutdown has finished its steps.

The same thread keeps a worker's own steps from being stranded by Redis: a message leased to it
that its consumer no longer holds (not reserved, running or scheduled: a step whose reject or ack
failed with READONLY in a failover, the steps of a connection it lost) for two beats in a row is
restored to the queue (``Leases.orphans``; retried each beat until Redis takes the write), and
every period one worker of the deployment sweeps for jobs that no message names
(``workers.sweep``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import redis
from celery import Celery, signals
from kombu import Connection

from geomatch_core.config import Settings

from .context import StepContext
from .leases import Leases
from .liveness import Registry, beat_period, new_worker_id
from .sweep import Sweep

log = logging.getLogger("geomatch.workers")


class Lifeline:
    def __init__(
        self, app: Celery, settings: Settings, hostname: str, context: Callable[[], StepContext] | None = None
    ) -> None:
        assert settings.redis_url is not None
        self.app = app
        self.worker_id = new_worker_id(hostname)
        self.client = redis.Redis.from_url(settings.redis_url, socket_timeout=5, socket_connect_timeout=5)
        self.registry = Registry(self.client, settings.redis_prefix, settings.worker_lease_s)
        self.leases = Leases(self.client, settings.redis_prefix, settings.worker_lease_s)
        self.period = beat_period(settings.worker_lease_s)
        self.sweep = (
            Sweep(context, settings.redis_prefix, [settings.queue], settings.worker_lease_s, self.worker_id)
            if context is not None
            else None
        )
        self._swept = time.monotonic()  # the first sweep a period after the start
        self._suspects: set[str] = set()  # leased tags not held at the last beat
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
                self._restore_orphans(conn.default_channel)
                if self.sweep is not None and time.monotonic() - self._swept >= self.sweep.period_s:
                    self.sweep.run(conn.default_channel, self.client)
                    self._swept = time.monotonic()
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

    def _restore_orphans(self, channel: Any) -> None:
        """Restore the messages leased to this worker that its consumer has not held for two beats
        (one beat may fall between a message's lease and its reservation, or its end and its ack)."""
        held = held_tags()
        if held is None:
            return
        orphans = self.leases.orphans(self.worker_id, held)
        confirmed = {t: v for t, v in orphans.items() if t in self._suspects}
        self._suspects = set(orphans) - set(confirmed)
        restored = [
            t
            for t, v in confirmed.items()
            if self.leases.restore(t, v, lambda tag: channel.qos.restore_by_tag(tag))
        ]
        if restored:
            log.warning("returned %d step(s) it no longer held to the queue: %s", len(restored), restored)


def held_tags() -> set[str] | None:
    """Delivery tags of the messages this worker's consumer holds (reserved, running, or scheduled
    for a retry's countdown), read from Celery's worker state in this process; None when that
    state changed while it was read (the next beat reads it again)."""
    from celery.worker import state

    try:
        # scheduled_requests: Celery 5.3's, not in celery-types' stubs
        scheduled = getattr(state, "scheduled_requests", ())
        requests = [*state.reserved_requests, *state.active_requests, *scheduled]
    except RuntimeError:  # a set changed size during iteration: the consumer thread moved a request
        return None
    tags = set()
    for r in requests:
        tag = getattr(getattr(r, "message", None), "delivery_tag", None)
        if tag is not None:
            tags.add(str(tag))
    return tags


def install(app: Celery, settings: Settings, context: Callable[[], StepContext] | None = None) -> None:
    """Connect the lifeline to this app's worker signals (a no-op outside ``celery worker``)."""
    line: list[Lifeline] = []

    @signals.worker_init.connect(weak=False)
    def init(sender: Any = None, **_: Any) -> None:
        if getattr(sender, "app", None) is app and not line:  # before any message can arrive
            line.append(Lifeline(app, settings, str(getattr(sender, "hostname", "")), context))

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
