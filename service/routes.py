"""HTTP routes (prefix /v1): request shapes in, use case calls, response shapes out.

Handlers are plain ``def`` where they block (uploads, snapshots, waiting for a picture): FastAPI
runs those on its thread pool, so the event loop keeps serving other requests.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Query, Request, Response, UploadFile
from fastapi.responses import FileResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool

from geomatch_core.errors import NotFound

from .schemas import (
    Error,
    ImageOut,
    ImagesOut,
    JobAccepted,
    JobOut,
    MatchIn,
    PairOut,
    PairsOut,
    Progress,
    ProjectCreate,
    ProjectOut,
    ReconstructIn,
    SceneOut,
)
from .usecases import (
    IMAGE_MEDIA,
    JobView,
    JobWatch,
    MatchRequest,
    Service,
    Upload,
    export_formats,
    model_files,
    remove_quietly,
)

_bearer = HTTPBearer(auto_error=False, description="an API key from `geomatch keys create TENANT`")
ERRORS: dict[int | str, dict[str, object]] = {
    code: {"model": Error} for code in (400, 401, 404, 409, 413, 415, 422, 503)
}
router = APIRouter(prefix="/v1", responses=ERRORS)
EVENTS_POLL_S = 0.5


def service(request: Request) -> Service:
    return request.app.state.service  # type: ignore[no-any-return]


def tenant(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    key = credentials.credentials if credentials and credentials.scheme.lower() == "bearer" else None
    return service(request).authenticate(key)


Svc = Annotated[Service, Depends(service)]
Tenant = Annotated[str, Depends(tenant)]


def job_out(j: JobView) -> JobOut:
    fields = {k: getattr(j, k) for k in JobOut.model_fields if k != "progress"}
    return JobOut(progress=Progress(done=j.done, total=j.total), **fields)


# -- projects ------------------------------------------------------------------------------------
@router.post("/projects", status_code=201, response_model=ProjectOut, tags=["projects"])
def create_project(body: ProjectCreate, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    config = body.config.model_dump(exclude_none=True) if body.config else {}
    return ProjectOut.model_validate(svc.create_project(tenant_id, body.name, config), from_attributes=True)


@router.get("/projects", response_model=list[ProjectOut], tags=["projects"])
def list_projects(svc: Svc, tenant_id: Tenant) -> list[ProjectOut]:
    return [ProjectOut.model_validate(p, from_attributes=True) for p in svc.list_projects(tenant_id)]


@router.get("/projects/{project_id}", response_model=ProjectOut, tags=["projects"])
def get_project(project_id: str, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    return ProjectOut.model_validate(svc.get_project(tenant_id, project_id), from_attributes=True)


@router.delete("/projects/{project_id}", status_code=204, tags=["projects"])
def delete_project(project_id: str, svc: Svc, tenant_id: Tenant) -> Response:
    svc.delete_project(tenant_id, project_id)
    return Response(status_code=204)


# -- images --------------------------------------------------------------------------------------
@router.post("/projects/{project_id}/images", status_code=201, response_model=ImagesOut, tags=["images"])
def upload_images(
    project_id: str,
    files: Annotated[
        list[UploadFile], File(description="one or more images (repeat the field)", min_length=1)
    ],
    svc: Svc,
    tenant_id: Tenant,
    capture: Annotated[
        Literal["aerial", "ground", "auto"], Form(description="auto: EXIF/XMP decides")
    ] = "auto",
) -> ImagesOut:
    views = svc.upload_images(tenant_id, project_id, [Upload(f.filename, f.file) for f in files], capture)
    return ImagesOut(images=[ImageOut.model_validate(v, from_attributes=True) for v in views])


@router.get("/projects/{project_id}/images", response_model=ImagesOut, tags=["images"])
def list_images(project_id: str, svc: Svc, tenant_id: Tenant) -> ImagesOut:
    views = svc.list_images(tenant_id, project_id)
    return ImagesOut(images=[ImageOut.model_validate(v, from_attributes=True) for v in views])


@router.get(
    "/projects/{project_id}/images/{name}",
    tags=["images"],
    response_class=FileResponse,
    responses={200: {"content": {m: {} for m in IMAGE_MEDIA.values()}, "description": "the bytes"}},
)
def image_file(project_id: str, name: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    """The uploaded bytes, typed by the format the upload check found (never sniffed)."""
    path, media = svc.image_file(tenant_id, project_id, name)
    return FileResponse(path, media_type=media, headers={"X-Content-Type-Options": "nosniff"})


# -- jobs ----------------------------------------------------------------------------------------
@router.post("/projects/{project_id}/match", status_code=202, response_model=JobAccepted, tags=["jobs"])
def match(project_id: str, body: MatchIn, svc: Svc, tenant_id: Tenant) -> JobAccepted:
    req = MatchRequest(**body.model_dump())
    job, follower = svc.start_match(tenant_id, project_id, req)
    return JobAccepted(job_id=job.id, reconstruct_job_id=follower.id if follower else None)


@router.post("/projects/{project_id}/reconstruct", status_code=202, response_model=JobAccepted, tags=["jobs"])
def reconstruct(
    project_id: str, svc: Svc, tenant_id: Tenant, body: ReconstructIn | None = None
) -> JobAccepted:
    job = svc.start_reconstruct(tenant_id, project_id, body.mapper if body else None)
    return JobAccepted(job_id=job.id)


@router.get("/jobs/{job_id}", response_model=JobOut, tags=["jobs"])
def get_job(job_id: str, svc: Svc, tenant_id: Tenant) -> JobOut:
    return job_out(svc.get_job(tenant_id, job_id))


@router.delete("/jobs/{job_id}", response_model=JobOut, tags=["jobs"])
def cancel_job(job_id: str, svc: Svc, tenant_id: Tenant) -> JobOut:
    return job_out(svc.cancel_job(tenant_id, job_id))


@router.get(
    "/jobs/{job_id}/events",
    tags=["jobs"],
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/event-stream": {}}, "description": "`event: job` per change, until it ends"}
    },
)
async def job_events(job_id: str, svc: Svc, tenant_id: Tenant) -> StreamingResponse:
    """Async on purpose: a watcher holds no worker thread while it waits, only for each poll."""
    await run_in_threadpool(svc.get_job, tenant_id, job_id)  # 404 before the stream starts
    watch = JobWatch(svc, tenant_id, job_id)

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
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


# -- outputs -------------------------------------------------------------------------------------
SCENE = "scene"  # computed from the model's text files for a viewer, not a stored file


def model_router() -> APIRouter:
    """GET /projects/{id}/model, made with each app: its formats are the export table's
    (geomatch.export.formats) as it is then, which the OpenAPI schema lists."""
    files, exports = model_files(), export_formats()
    media = {m.name: m.media_type for m in files} | {f.name: f.media_type for f in exports}
    names = (*(m.name for m in files), SCENE, *(f.name for f in exports))
    described = (
        ", ".join(f"{m.name}: {m.help}" for m in files)
        + f", {SCENE}: points and cameras for a viewer; zips for other tools (docs/exports.md), built on "
        + "first request: "
        + ", ".join(f"{f.name}: {f.help}" for f in exports)
    )
    out = APIRouter(prefix="/v1", responses=ERRORS)

    def model(project_id: str, svc: Svc, tenant_id: Tenant, format: str = "zip") -> Response:
        if format == SCENE:
            scene = SceneOut.model_validate(svc.model_scene(tenant_id, project_id))
            return Response(scene.model_dump_json(), media_type="application/json")
        path = svc.model_file(tenant_id, project_id, format)
        return FileResponse(path, media_type=media[format], filename=f"{project_id}-{path.name}")

    # the formats are known only now, and this module's annotations are strings resolved in its
    # globals: the parameter's type is set on the function itself
    model.__annotations__["format"] = Annotated[Literal[names], Query(description=described)]  # type: ignore[valid-type]
    out.add_api_route(
        "/projects/{project_id}/model",
        model,
        methods=["GET"],
        tags=["outputs"],
        response_class=FileResponse,
        responses={200: {"content": {m: {} for m in media.values()}}},
    )
    return out


@router.get(
    "/projects/{project_id}/database",
    tags=["outputs"],
    response_class=FileResponse,
    responses={200: {"content": {"application/vnd.sqlite3": {}}}},
)
def database(project_id: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    path = svc.database_snapshot(tenant_id, project_id)
    return FileResponse(
        path,
        media_type="application/vnd.sqlite3",
        filename=f"{project_id}-database.db",
        background=BackgroundTask(remove_quietly, path),
    )


@router.get("/projects/{project_id}/pairs", response_model=PairsOut, tags=["outputs"])
def list_pairs(project_id: str, svc: Svc, tenant_id: Tenant) -> PairsOut:
    """Matched pairs with their counts, most verified matches first (empty before matching)."""
    views = svc.list_pairs(tenant_id, project_id)
    return PairsOut(pairs=[PairOut.model_validate(v, from_attributes=True) for v in views])


@router.get(
    "/projects/{project_id}/pairs/{name0}/{name1}/matches.png",
    tags=["outputs"],
    response_class=FileResponse,
    responses={200: {"content": {"image/png": {}}}},
)
def matches_png(project_id: str, name0: str, name1: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    return FileResponse(svc.matches_picture(tenant_id, project_id, name0, name1), media_type="image/png")
