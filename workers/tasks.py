"""The Celery tasks: one per job step, thin wrappers around ``workers.jobs``.

Retry policy: a step that raises a transient error is retried (exponential backoff, 3 times),
a permanent one (``jobs.is_permanent``) fails its job at once; a step that gave up fails its job
through ``on_failure``. Each worker process builds its own context (database engine, Redis
client) on first use, after the prefork pool has forked it.
"""

from __future__ import annotations

import os
from typing import Any

import redis
from celery import Celery, Task, bootsteps
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from geomatch_core.config import Settings
from geomatch_core.locks import RedisLocks
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore

from . import jobs, lifeline, recovery
from .celery_queue import CeleryQueue
from .celery_transport import FAILOVER_ERRORS
from .context import PermanentError, StepContext, is_permanent
from .steps import ANSWERED, ONE_SHOT, STEPS

_context: tuple[int, StepContext] | None = None


def context(app: Celery) -> StepContext:
    global _context
    if _context is None or _context[0] != os.getpid():
        settings = Settings.from_env()
        assert settings.redis_url is not None
        store = MetadataStore(settings.database_url)
        client = redis.Redis.from_url(
            settings.redis_url,
            socket_timeout=10,
            socket_connect_timeout=5,
            # a Redis restart or failover of a few seconds: lock calls wait for it rather than fail
            # the step (a replica answers writes READONLY, a starting Redis LOADING)
            retry=Retry(ExponentialBackoff(cap=2.0, base=0.1), 10),
            retry_on_error=[redis.ConnectionError, redis.TimeoutError, *FAILOVER_ERRORS],
        )
        locks = RedisLocks(client, settings.redis_prefix, settings.lock_timeout_s)
        _context = (
            os.getpid(),
            StepContext(settings, store, Storage(settings.home), locks, CeleryQueue(settings, app)),
        )
    return _context[1]


def register(app: Celery) -> None:
    class StepTask(Task[Any, Any]):
        autoretry_for = (Exception,)
        dont_autoretry_for = (PermanentError, ValueError, TypeError, LookupError, NotImplementedError)
        max_retries = 3
        retry_backoff = 2
        retry_backoff_max = 60
        retry_jitter = True
        acks_late = True
        reject_on_worker_lost = True

        def on_failure(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
            jobs.on_failure(context(app), self.name, tuple(args), exc)

    for name, fn in STEPS.items():
        if name in ONE_SHOT:

            def once(*args: Any, _fn: Any = fn) -> Any:
                return _fn(context(app), *args)

            app.task(name=name, ignore_result=False, acks_late=False, max_retries=0)(once)
            continue

        def run(self: Task[Any, Any], *args: Any, _fn: Any = fn) -> Any:
            try:
                return _fn(context(app), *args)
            except Exception as e:  # e.g. missing weights (an OSError): fail now, not after 3 retries
                if is_permanent(e) and not isinstance(e, StepTask.dont_autoretry_for):
                    raise PermanentError(f"{type(e).__name__}: {e}") from e
                raise

        app.task(name=name, base=StepTask, bind=True, ignore_result=name not in ANSWERED)(run)

    app.steps["consumer"].add(_recovery_step(app))
    lifeline.install(app, Settings.from_env(), lambda: context(app))


def _recovery_step(app: Celery) -> type:
    class Recover(bootsteps.StartStopStep):
        """Runs each time the consumer (re)connects to the broker: see ``workers.recovery``."""

        requires = ("celery.worker.consumer.tasks:Tasks",)

        def start(self, c: Any) -> None:
            try:
                ctx = context(app)
                recovery.requeue_unfinished(ctx.store, ctx.queue)
            except Exception as e:  # the store or Redis down again: the next (re)connect retries
                jobs.log.warning("could not requeue unfinished jobs: %s", e)

    return Recover
