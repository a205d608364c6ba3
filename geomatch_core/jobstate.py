"""Job state transitions, shared by the API (submit, cancel) and the workers (run, finish).

Every transition is one conditional UPDATE, so concurrent workers, redelivered steps and a
cancel racing a finish all settle on one answer: a terminal state is never left, a pair is
counted once, and exactly one caller sees a job complete.
"""

from __future__ import annotations

from typing import Any, cast

from sqlalchemy import CursorResult, Update, func, select, update
from sqlalchemy.orm import Session

from geomatch.pipeline.outputs import finite

from .models import TERMINAL_STATES, Job, JobPair, JobPhoto, now
from .queue import ENTRY_STEP, JobQueue
from .store import MetadataStore


def _changed(s: Session, statement: Update) -> int:
    """Run an UPDATE; how many rows it changed (Session.execute is typed as returning a Result,
    which for an UPDATE is a CursorResult, the one with the count)."""
    return cast(CursorResult[Any], s.execute(statement)).rowcount


def get(store: MetadataStore, job_id: str) -> Job | None:
    with store.session() as s:
        return s.get(Job, job_id)


def claim(store: MetadataStore, job_id: str) -> Job | None:
    """Mark a job running (again, after a redelivery); None when it is gone or finished."""
    with store.session() as s:
        s.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == "queued")
            .values(state="running", started_at=now())
        )
        job = s.get(Job, job_id)
        if job is None or job.state != "running":
            return None
        return job


def running_for(job: Job) -> float:
    """Seconds since ``job`` started running (0 before it did)."""
    return (now() - job.started_at).total_seconds() if job.started_at is not None else 0.0


def is_active(store: MetadataStore, job_id: str) -> bool:
    with store.session() as s:
        return s.scalar(select(Job.state).where(Job.id == job_id)) == "running"


def mark_pair_done(store: MetadataStore, job_id: str, idx: int, matches: int, inliers: int) -> bool:
    """True the first time only: the pair's row flips and the job's counter moves in one transaction."""
    with store.session() as s:
        flipped = _changed(
            s,
            update(JobPair)
            .where(JobPair.job_id == job_id, JobPair.idx == idx, JobPair.done.is_(False))
            .values(done=True, matches=matches, inliers=inliers),
        )
        if flipped:
            s.execute(update(Job).where(Job.id == job_id).values(done=Job.done + 1))
        return bool(flipped)


def mark_photos_done(store: MetadataStore, job_id: str, chunk: int) -> int | None:
    """How many of a match job's plan photos are left once ``chunk``'s are done; None when they were
    done before (a redelivered step). The job's row is locked first, so that steps ending together
    count one after the other and exactly one of them sees none left."""
    with store.session() as s:
        if s.get(Job, job_id, with_for_update=True) is None:
            return None
        flipped = _changed(
            s,
            update(JobPhoto)
            .where(JobPhoto.job_id == job_id, JobPhoto.chunk == chunk, JobPhoto.done.is_(False))
            .values(done=True),
        )
        if not flipped:
            return None
        left = s.scalar(select(func.count()).where(JobPhoto.job_id == job_id, JobPhoto.done.is_(False)))
        return int(left or 0)


def claim_pairs(store: MetadataStore, job_id: str, window: int) -> list[int]:
    """The pairs a running match job may hand to the queue now: the next ones by index while
    fewer than ``window`` are queued or running (``dispatched - done``). One conditional UPDATE per
    pair, so steps ending together never hand out the same pair twice."""
    claimed: list[int] = []
    while True:
        with store.session() as s:
            row = s.execute(
                update(Job)
                .where(
                    Job.id == job_id,
                    Job.state == "running",
                    Job.planned.is_(True),
                    Job.dispatched < Job.total,
                    Job.dispatched - Job.done < window,
                )
                .values(dispatched=Job.dispatched + 1)
                .returning(Job.dispatched)
            ).first()
        if row is None:
            return claimed
        claimed.append(int(row[0]) - 1)


def queued_pairs(
    store: MetadataStore, tenant_id: str, other_than: str | None = None
) -> tuple[int, int, list[Job]]:
    """What a tenant's unfinished match jobs hold: pairs planned and not done, how many planned
    jobs hold them, and the jobs not planned yet (whose counts only their plan step knows)."""
    with store.session() as s:
        rows = s.scalars(
            select(Job).where(
                Job.tenant_id == tenant_id,
                Job.kind == "match",
                Job.state.in_(("queued", "running")),
                Job.id != (other_than or ""),
            )
        ).all()
        planned = [j for j in rows if j.planned]
        return (
            sum(max(0, j.total - j.done) for j in planned),
            len(planned),
            [j for j in rows if not j.planned],
        )


def set_progress(store: MetadataStore, job_id: str, done: int) -> bool:
    """A one-step job's own count of what it has done (a localize job's photos): moves only up,
    and only while the job runs, so a late report never rewinds or revives a finished job."""
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state == "running", Job.done < done)
                .values(done=done),
            )
        )


def finish_if_complete(store: MetadataStore, job_id: str, result: dict[str, Any] | None = None) -> bool:
    result = finite(result)
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state == "running", Job.planned.is_(True), Job.done >= Job.total)
                .values(state="succeeded", finished_at=now(), result=result),
            )
        )


def store_result(store: MetadataStore, job_id: str, result: dict[str, Any]) -> bool:
    """Store a running job's result without ending it; False when it no longer runs. A step whose
    outputs replace earlier ones (a reconstruct's model) stores first and swaps after, so a result
    the store refuses leaves the earlier outputs in place, and succeeds last, so that no client
    reads the job succeeded before its outputs are there."""
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job).where(Job.id == job_id, Job.state == "running").values(result=finite(result)),
            )
        )


def succeed(store: MetadataStore, job_id: str, result: dict[str, Any] | None = None) -> bool:
    result = finite(result)
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state == "running")
                .values(state="succeeded", finished_at=now(), result=result, done=Job.total),
            )
        )


def fail(store: MetadataStore, job_id: str, error: str) -> bool:
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state.not_in(TERMINAL_STATES))
                .values(state="failed", finished_at=now(), error=error[:4000]),
            )
        )


def cancel(store: MetadataStore, job_id: str, reason: str | None = None) -> bool:
    with store.session() as s:
        return bool(
            _changed(
                s,
                update(Job)
                .where(Job.id == job_id, Job.state.not_in(TERMINAL_STATES))
                .values(state="cancelled", finished_at=now(), error=reason),
            )
        )


def release_followers(store: MetadataStore, queue: JobQueue, job_id: str) -> None:
    """Start the jobs queued behind a finished job, or cancel them if it did not succeed.

    Called at least once per finish (possibly more after a redelivery): starting a queued job
    twice is harmless since every step is idempotent.
    """
    with store.session() as s:
        state = s.scalar(select(Job.state).where(Job.id == job_id))
        waiting = s.scalars(select(Job).where(Job.after_job_id == job_id, Job.state == "queued")).all()
        followers = [(f.id, f.kind) for f in waiting]
    for fid, kind in followers:
        if state == "succeeded":
            queue.enqueue(ENTRY_STEP[kind], fid)
        elif state in TERMINAL_STATES:
            cancel(store, fid, f"the job it waited for ({job_id}) ended {state}")
            release_followers(store, queue, fid)
