"""The Celery application: Redis as broker and result store, configured for at-least-once steps.

- ``task_acks_late`` + ``task_reject_on_worker_lost``: a step is acknowledged after it ran, so a
  worker killed mid-step (SIGKILL, OOM, a lost node) leaves its message to be delivered again.
  On Redis an unacknowledged message returns after ``visibility_timeout`` (GEOMATCH_VISIBILITY_TIMEOUT),
  which must exceed the longest step (workers sweep for such messages every few seconds); a child
  process dying under a live worker is requeued at once. A whole worker gone is found sooner by
  its lapsed lease (``workers.lifeline``: its steps are back in the queue within
  GEOMATCH_WORKER_LEASE); the visibility timeout is the backstop.
- ``worker_prefetch_multiplier=1``: a worker holds one message beyond the one it runs, so a long
  pair does not starve other workers.
- Every key (queues, unacked sets, results) starts with GEOMATCH_REDIS_PREFIX, so deployments,
  test runs and other tenants of one Redis never see each other's messages.
- A Redis failing over (READONLY, LOADING, MASTERDOWN for a few seconds) is a lost connection to
  the broker, not an unrecoverable error (``workers.celery_transport``), and a step's publish waits
  through about 20 s of it (``CeleryQueue.enqueue``) rather than failing the step.
- Job steps go to GEOMATCH_QUEUE, interactive ones (match pictures) to GEOMATCH_QUEUE.interactive,
  which a worker also consumes: a picture does not wait behind a whole match job.
"""

from __future__ import annotations

from celery import Celery

from geomatch_core.config import Settings
from geomatch_core.queue import RENDER_PAIR

from .celery_transport import TRANSPORT


def interactive_queue(settings: Settings) -> str:
    return f"{settings.queue}.interactive"


def make_app(settings: Settings) -> Celery:
    if not settings.redis_url:
        raise ValueError(
            "REDIS_URL is not set: Celery needs Redis (without it, `geomatch serve` runs jobs itself)"
        )
    app = Celery("geomatch", broker=settings.redis_url, backend=settings.redis_url, set_as_current=False)
    app.conf.update(
        broker_transport=TRANSPORT,
        task_default_queue=settings.queue,
        task_routes={RENDER_PAIR: {"queue": interactive_queue(settings)}},
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        result_expires=3600,
        broker_transport_options={
            "global_keyprefix": settings.redis_prefix,
            "visibility_timeout": settings.visibility_timeout_s,
            # look for expired unacknowledged messages every few seconds (kombu's default sweep is
            # ~100 s), so a dead worker's step returns soon after its visibility timeout
            "unacked_restore_interval": max(1, min(10, settings.visibility_timeout_s // 3)),
            "unacked_restore_throttle": 1,
        },
        result_backend_transport_options={"global_keyprefix": settings.redis_prefix},
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
        worker_redirect_stdouts=False,
        worker_cancel_long_running_tasks_on_connection_loss=True,
    )
    return app
