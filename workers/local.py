"""The embedded runner: job steps on threads of the API process, so ``geomatch serve`` works
with no Redis and no worker processes.

Same steps, same retry policy as the Celery workers; FIFO like a queue. What a crash loses is
the in-memory queue only: on start, jobs the metadata store still shows as queued or running are
queued again (their steps are idempotent, so a half-done job resumes).
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from sqlalchemy import select

from geomatch_core import jobstate
from geomatch_core.config import Settings
from geomatch_core.locks import LockFactory
from geomatch_core.models import Job
from geomatch_core.queue import ENTRY_STEP
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore

from . import jobs
from .context import StepContext, is_permanent
from .steps import STEPS

log = logging.getLogger("geomatch.workers")
MAX_RETRIES = 3


class LocalQueue:
    def __init__(
        self, settings: Settings, store: MetadataStore, storage: Storage, locks: LockFactory
    ) -> None:
        self.ctx = StepContext(settings, store, storage, locks, self)
        self._pool = ThreadPoolExecutor(settings.embedded_threads, thread_name_prefix="geomatch-job")
        self._interactive = ThreadPoolExecutor(1, thread_name_prefix="geomatch-render")
        self._closed = threading.Event()

    def enqueue(self, step: str, *args: Any) -> None:
        if self._closed.is_set():
            raise RuntimeError("the embedded job runner is shut down")
        self._pool.submit(self._run, step, args, 0)

    def _run(self, step: str, args: tuple[Any, ...], attempt: int) -> None:
        try:
            STEPS[step](self.ctx, *args)
        except Exception as e:
            if not is_permanent(e) and attempt < MAX_RETRIES and not self._closed.is_set():
                delay = 2.0**attempt
                log.warning("%s%r failed (%s); retry %d in %.0fs", step, args, e, attempt + 1, delay)
                timer = threading.Timer(delay, self._retry, (step, args, attempt + 1))
                timer.daemon = True
                timer.start()
                return
            log.exception("%s%r failed", step, args)
            jobs.on_failure(self.ctx, step, args, e)

    def _retry(self, step: str, args: tuple[Any, ...], attempt: int) -> None:
        if not self._closed.is_set():
            self._pool.submit(self._run, step, args, attempt)

    def call(self, step: str, *args: Any, timeout: float) -> Any:
        return self._interactive.submit(STEPS[step], self.ctx, *args).result(timeout)

    def ping(self) -> None:
        if self._closed.is_set():
            raise RuntimeError("the embedded job runner is shut down")

    def slots(self) -> int:
        return self.ctx.settings.embedded_threads

    def workers_alive(self) -> int | None:
        return None  # the API process runs the steps: no worker to miss

    def resume(self) -> int:
        """Queue again the jobs a previous run of this process left unfinished."""
        store = self.ctx.store
        with store.session() as s:
            rows = s.execute(
                select(Job.id, Job.kind, Job.after_job_id).where(Job.state.in_(("queued", "running")))
            ).all()
        n = 0
        for job_id, kind, after in rows:
            if after is not None:
                before = jobstate.get(store, after)
                if before is not None and before.state in ("queued", "running"):
                    continue  # started when the job it waits for finishes
                if before is None or before.state != "succeeded":
                    jobstate.cancel(store, job_id, f"the job it waited for ({after}) did not succeed")
                    continue
            self.enqueue(ENTRY_STEP[kind], job_id)
            n += 1
        return n

    def close(self) -> None:
        self._closed.set()
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._interactive.shutdown(wait=False, cancel_futures=True)
