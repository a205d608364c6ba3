"""Requeue what a lost queue message would otherwise leave unfinished forever.

A message can be lost with Redis (restarted without the step persisted, a restore that failed
while it was down, a worker terminated mid-step while disconnected): its job then stays queued
or running with nothing in the queue to move it. Every worker, each time its consumer
(re)connects to the broker, requeues the entry step of every unfinished job: steps are
idempotent (``workers.jobs``), so a job that was not lost only sees duplicates that skip, while a
lost one goes on where it stopped (a match job re-dispatches its pending pairs).
"""

from __future__ import annotations

import logging

from sqlalchemy import select

from geomatch_core.models import Job
from geomatch_core.queue import ENTRY_STEP, JobQueue
from geomatch_core.store import MetadataStore

log = logging.getLogger("geomatch.workers")


def unfinished(store: MetadataStore) -> list[tuple[str, str]]:
    """(id, kind) of the running jobs and of the queued jobs not waiting for another one: the jobs
    that must have a step in the queue or in a worker's hands."""
    with store.session() as s:
        rows = s.execute(
            select(Job.id, Job.kind, Job.state, Job.after_job_id).where(Job.state.in_(("queued", "running")))
        ).all()
        after = {r.after_job_id for r in rows if r.after_job_id}
        ended = dict(s.execute(select(Job.id, Job.state).where(Job.id.in_(after))).all()) if after else {}
    return [
        (r.id, r.kind)
        for r in rows
        # a queued job waiting for its predecessor is released, or cancelled, when that one ends
        if not (r.state == "queued" and r.after_job_id and ended.get(r.after_job_id) != "succeeded")
    ]


def requeue_unfinished(store: MetadataStore, queue: JobQueue) -> int:
    """Queue the entry step of every unfinished job (``unfinished``)."""
    n = 0
    for job_id, kind in unfinished(store):
        queue.enqueue(ENTRY_STEP[kind], job_id)
        n += 1
    if n:
        log.info("requeued the entry step of %d unfinished job(s)", n)
    return n
