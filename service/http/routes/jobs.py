"""Jobs: /v1/projects/{id}/match and /reconstruct start them, /v1/projects/{id}/jobs lists them;
/v1/jobs/{id} reads, cancels and (/events) streams one."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from geomatch.options import RECONSTRUCT_OPTIONS
from geomatch_core.errors import NotFound

from ...paging import JOBS
from ...usecases.jobs import JobWatch
from ...usecases.views import JobView, MatchRequest
from ..schemas import JobAccepted, JobOut, JobsOut, MatchIn, Progress, ReconstructIn
from .deps import MAX_OFFSET, Svc, Tenant, link_next

router = APIRouter(tags=["jobs"])
EVENTS_POLL_S = 0.5
# the reconstruct body's mapping options; its mapper is start_reconstruct's own argument
MAPPING = tuple(k for k in RECONSTRUCT_OPTIONS if k != "mapper")


def job_out(j: JobView) -> JobOut:
    fields = {k: getattr(j, k) for k in JobOut.model_fields if k != "progress"}
    return JobOut(progress=Progress(done=j.done, total=j.total), **fields)


@router.post("/projects/{project_id}/match", status_code=202, response_model=JobAccepted)
def match(project_id: str, body: MatchIn, svc: Svc, tenant_id: Tenant) -> JobAccepted:
    req = MatchRequest(**body.model_dump())
    job, follower = svc.jobs.start_match(tenant_id, project_id, req)
    return JobAccepted(job_id=job.id, reconstruct_job_id=follower.id if follower else None)


@router.post("/projects/{project_id}/reconstruct", status_code=202, response_model=JobAccepted)
def reconstruct(
    project_id: str, svc: Svc, tenant_id: Tenant, body: ReconstructIn | None = None
) -> JobAccepted:
    mapper, checkpoints = (body.mapper, body.checkpoints) if body else (None, None)
    mapping = {k: getattr(body, k) for k in MAPPING if body and getattr(body, k) is not None}
    job = svc.jobs.start_reconstruct(tenant_id, project_id, mapper, checkpoints, mapping)
    return JobAccepted(job_id=job.id)


@router.get("/projects/{project_id}/jobs", response_model=JobsOut)
def list_jobs(
    project_id: str,
    request: Request,
    response: Response,
    svc: Svc,
    tenant_id: Tenant,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="jobs to skip")] = 0,
    limit: Annotated[
        int,
        Query(
            ge=1,
            le=JOBS.max,
            description=f"page size (default {JOBS.default}); the next page is in the `Link` header",
        ),
    ] = JOBS.default,
    state: Annotated[
        Literal["queued", "running", "succeeded", "failed", "cancelled"] | None,
        Query(description="only the jobs in this state"),
    ] = None,
) -> JobsOut:
    """The project's jobs, newest first, one page at a time: running and past ones, whoever
    started them."""
    page = svc.jobs.list_jobs(tenant_id, project_id, offset, limit, state)
    link_next(request, response, page.next_offset, limit)
    return JobsOut(jobs=[job_out(j) for j in page.items])


@router.get("/jobs/{job_id}", response_model=JobOut)
def get_job(job_id: str, svc: Svc, tenant_id: Tenant) -> JobOut:
    return job_out(svc.jobs.get_job(tenant_id, job_id))


@router.delete("/jobs/{job_id}", response_model=JobOut)
def cancel_job(job_id: str, svc: Svc, tenant_id: Tenant) -> JobOut:
    return job_out(svc.jobs.cancel_job(tenant_id, job_id))


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/event-stream": {}}, "description": "`event: job` per change, until it ends"}
    },
)
async def job_events(job_id: str, svc: Svc, tenant_id: Tenant) -> StreamingResponse:
    """Async on purpose: a watcher holds no worker thread while it waits, only for each poll."""
    await run_in_threadpool(svc.jobs.get_job, tenant_id, job_id)  # 404 before the stream starts
    watch = JobWatch(svc.jobs, tenant_id, job_id)

    async def stream() -> AsyncIterator[str]:
        yield "retry: 2000\n\n"
        n = 0
        while not watch.finished:
            try:
                emit, job = await run_in_threadpool(watch.poll)
            except NotFound as e:  # deleted while watched
                yield f"event: error\ndata: {json.dumps({'detail': e.message})}\n\n"
                return
            if emit and job is None:
                yield ": keep-alive\n\n"
            elif emit and job is not None:
                yield f"id: {n}\nevent: job\ndata: {job_out(job).model_dump_json()}\n\n"
                n += 1
            if not watch.finished:
                await asyncio.sleep(EVENTS_POLL_S)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"X-Accel-Buffering": "no"},  # Cache-Control: no-store, as all of /v1 (headers.py)
    )
