"""Jobs: start a match (and the reconstruction it may chain) or a reconstruction, list a project's,
read, cancel and watch a job."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from geomatch.options import PROJECT_OPTIONS, RECONSTRUCT_OPTIONS, fewest_pairs
from geomatch_core import jobstate
from geomatch_core.errors import (
    Conflict,
    InvalidRequest,
    NotFound,
    PlanTooLarge,
    Unavailable,
    WorkQueued,
    too_many_pairs,
    too_much_queued,
)
from geomatch_core.models import JOB_STATES, Image, Job
from geomatch_core.queue import ENTRY_STEP

from ..ids import known_id
from ..paging import JOBS, Page, page_of
from ..validation import check_option, check_pair_list
from .base import DEFAULTS, UseCases, check_config, check_open_jobs, choice
from .gcp import check_checkpoints
from .views import JobView, MatchRequest, job_view


class JobUseCases(UseCases):
    def start_match(
        self, tenant_id: str, project_id: str, req: MatchRequest
    ) -> tuple[JobView, JobView | None]:
        with self._unless_deleted(tenant_id, project_id), self.ctx.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            names = set(s.scalars(select(Image.name).where(Image.project_id == project_id)))
            if len(names) < 2:
                raise InvalidRequest(f"the project has {len(names)} image(s); matching needs at least 2")
            given = {k: getattr(req, k) for k in PROJECT_OPTIONS}
            opts = {**DEFAULTS, **check_config(dict(p.config)), **check_config(given)}
            if isinstance(opts["pairs"], list):
                opts["pairs"] = check_pair_list(opts["pairs"], names)
            self._check_plan_size(opts["pairs"], len(names))
            self._check_queued(s, tenant_id, opts["pairs"], len(names))
            mapper = opts.pop("mapper")
            mapping = {k: opts.pop(k) for k in RECONSTRUCT_OPTIONS if k != "mapper"}
            job = Job(project_id=project_id, tenant_id=tenant_id, kind="match", options=opts)
            s.add(job)
            s.flush()
            follower = None
            if req.reconstruct:
                check_open_jobs(s, self.ctx.settings, tenant_id)
                held_out = check_checkpoints(s, self.ctx.storage, project_id, req.checkpoints)
                follower = _reconstruct_job(
                    s, project_id, tenant_id, mapper, job.id, checkpoints=held_out, mapping=mapping
                )
            views = job_view(job), job_view(follower) if follower else None
        self.enqueue(views[0])
        return views

    def _check_plan_size(self, pairs: str | list[Any], n: int) -> None:
        """``GEOMATCH_MAX_PAIRS_PER_JOB``, on arithmetic alone (nothing planned): a plan sure to
        pass the limit is refused here; one that may (``auto``, ``gps:K``, ``retrieval:K`` over
        GPS and appearance the API does not read) is measured by the job's plan step, which fails
        the job before it writes a pair."""
        limit = self.ctx.settings.max_pairs_per_job
        if not limit:
            return
        if isinstance(pairs, list):
            count, exact, plan = len(pairs), True, "the pair list"
        else:
            (count, exact), plan = fewest_pairs(pairs, n), pairs
        if count > limit:
            raise PlanTooLarge(too_many_pairs(count, n, limit, plan, exact))

    def _check_queued(self, s: Session, tenant_id: str, pairs: str | list[Any], n: int) -> None:
        """``GEOMATCH_MAX_QUEUED_PAIRS``: what the tenant's unfinished match jobs hold (planned
        ones by their rows, the others by the fewest pairs their plan can have) plus the fewest
        this one can add. A plan only its step can size is measured again there."""
        limit = self.ctx.settings.max_queued_pairs
        if not limit:
            return
        queued, jobs, unplanned = jobstate.queued_pairs(self.ctx.store, tenant_id)
        for j in unplanned:
            images = s.scalar(select(func.count()).select_from(Image).where(Image.project_id == j.project_id))
            spec = j.options.get("pairs", DEFAULTS["pairs"])
            queued += len(spec) if isinstance(spec, list) else fewest_pairs(spec, images or 0)[0]
        jobs += len(unplanned)
        adding, exact = (len(pairs), True) if isinstance(pairs, list) else fewest_pairs(pairs, n)
        if queued + adding > limit:
            raise WorkQueued(too_much_queued(queued, jobs, adding, limit, exact), retry_after_s=60)

    def start_reconstruct(
        self,
        tenant_id: str,
        project_id: str,
        mapper: str | None = None,
        checkpoints: list[str] | int | None = None,
        mapping: dict[str, Any] | None = None,
    ) -> JobView:
        """``checkpoints``: ground control points held out of the fit to judge it (names, or how
        many, spread over the points' sorted names), checked against the project's GCP file;
        ``mapping``: the reconstruct options but the mapper (``min_pose_inliers``, ``ortho``,
        ``ortho_gsd``) for this job (else the project's)."""
        with self._unless_deleted(tenant_id, project_id), self.ctx.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            mapper = check_option("mapper", mapper or p.config.get("mapper") or DEFAULTS["mapper"])
            # the values before the project's state: a bad one is refused as REST's schema refuses it
            config = {**DEFAULTS, **check_config(dict(p.config)), **check_config(dict(mapping or {}))}
            matched = s.scalar(
                select(func.count())
                .select_from(Job)
                .where(Job.project_id == project_id, Job.kind == "match", Job.state == "succeeded")
            )
            if not matched:
                raise Conflict(
                    "nothing to reconstruct yet: no match job of this project has succeeded "
                    '(POST .../match first, or with "reconstruct": true to chain both)'
                )
            check_open_jobs(s, self.ctx.settings, tenant_id)
            held_out = check_checkpoints(s, self.ctx.storage, project_id, checkpoints)
            mapping = {k: config[k] for k in RECONSTRUCT_OPTIONS if k != "mapper"}
            job = _reconstruct_job(s, project_id, tenant_id, mapper, checkpoints=held_out, mapping=mapping)
            view = job_view(job)
        self.enqueue(view)
        return view

    def enqueue(self, job: JobView) -> None:
        """The job handed to the queue; a queue that cannot take it fails the job (Unavailable)."""
        try:
            self.ctx.queue.enqueue(ENTRY_STEP[job.kind], job.id)
        except Exception as e:
            jobstate.fail(self.ctx.store, job.id, f"could not queue the job: {e}")
            raise Unavailable(f"the job queue is not reachable ({e}); the job was not started") from None

    def get_job(self, tenant_id: str, job_id: str) -> JobView:
        """Every use case that takes a job id (cancel, watch) looks it up here."""
        with self.ctx.store.session() as s:
            job = s.get(Job, known_id("job", job_id))
            if job is None or job.tenant_id != tenant_id:
                raise NotFound(f"job {job_id} not found")
            return job_view(job)

    def list_jobs(
        self,
        tenant_id: str,
        project_id: str,
        offset: int = 0,
        limit: int | None = None,
        state: str | None = None,
    ) -> Page[JobView]:
        """One page of the project's jobs, newest first (``paging.JOBS``: its sizes), of one state
        when ``state`` is given. The jobs live in the store, not in a client: any tab, device or
        program that holds a key of the tenant finds the running and past ones here."""
        limit = JOBS.clamp(limit)
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
            query = select(Job).where(Job.project_id == project_id, Job.tenant_id == tenant_id)
            if state is not None:
                query = query.where(Job.state == choice("state", state, JOB_STATES))
            rows = s.scalars(
                query.order_by(Job.created_at.desc(), Job.id.desc()).offset(offset).limit(limit + 1)
            ).all()
            return page_of([job_view(j) for j in rows], offset, limit)

    def cancel_job(self, tenant_id: str, job_id: str) -> JobView:
        """Idempotent: a finished job is returned as it is."""
        self.get_job(tenant_id, job_id)
        if jobstate.cancel(self.ctx.store, job_id, "cancelled by the client"):
            jobstate.release_followers(self.ctx.store, self.ctx.queue, job_id)
        return self.get_job(tenant_id, job_id)

    def watch_job(
        self, tenant_id: str, job_id: str, interval_s: float = 0.5, heartbeat_s: float = 15.0
    ) -> Iterator[JobView | None]:
        """The job each time its state or progress changes, until it ends; None as a keep-alive."""
        watch = JobWatch(self, tenant_id, job_id, heartbeat_s)
        while not watch.finished:
            emit, job = watch.poll()
            if emit:
                yield job
            if not watch.finished:
                time.sleep(interval_s)


class JobWatch:
    """Change detection over a job, one poll at a time, so that a caller may wait between polls
    however it likes (a thread sleeping in ``watch_job``, an event loop in the SSE route)."""

    def __init__(self, jobs: JobUseCases, tenant_id: str, job_id: str, heartbeat_s: float = 15.0) -> None:
        self.jobs, self.tenant_id, self.job_id, self.heartbeat_s = jobs, tenant_id, job_id, heartbeat_s
        self.finished = False
        self._last: tuple[Any, ...] | None = None
        self._quiet_since = time.monotonic()

    def poll(self) -> tuple[bool, JobView | None]:
        """(True, job) when it changed, (True, None) when a keep-alive is due, else (False, None)."""
        job = self.jobs.get_job(self.tenant_id, self.job_id)
        key = (job.state, job.done, job.total, job.error)
        now = time.monotonic()
        if key != self._last:
            self._last, self._quiet_since = key, now
            self.finished = job.terminal
            return True, job
        if now - self._quiet_since > self.heartbeat_s:
            self._quiet_since = now
            return True, None
        return False, None


def _reconstruct_job(
    s: Session,
    project_id: str,
    tenant_id: str,
    mapper: str,
    after: str | None = None,
    checkpoints: list[str] | int = 0,
    mapping: dict[str, Any] | None = None,
) -> Job:
    """``checkpoints`` go into the options only when asked for (the job's GCP step reads them), and
    so do the PnP minimum (``mapping``'s ``min_pose_inliers`` other than 0, auto) and the map
    (``ortho`` on, with its ``ortho_gsd``): a job's options read as what was asked of it, and a
    job stored without them maps with the defaults."""
    options: dict[str, Any] = {"mapper": mapper}
    if checkpoints:
        options["checkpoints"] = checkpoints
    if mapping and mapping.get("min_pose_inliers"):
        options["min_pose_inliers"] = int(mapping["min_pose_inliers"])
    if mapping and mapping.get("ortho") == "on":
        options |= {"ortho": "on", "ortho_gsd": float(mapping.get("ortho_gsd") or 0.0)}
    job = Job(
        project_id=project_id,
        tenant_id=tenant_id,
        kind="reconstruct",
        options=options,
        total=1,
        after_job_id=after,
    )
    s.add(job)
    s.flush()
    return job
