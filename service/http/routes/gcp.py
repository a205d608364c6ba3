"""/v1/projects/{id}/gcp: the project's ground control points (OpenDroneMap's gcp_list.txt)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from geomatch_core.errors import DomainError, InvalidRequest, UnsupportedFormat

from ...usecases.gcp import MAX_GCP_BYTES, NO_FILE
from ..schemas import GcpOut
from .deps import Svc, Tenant

router = APIRouter(tags=["ground control points"])

RAW = ("", "application/octet-stream", "application/x-www-form-urlencoded")  # the body is the file
FIELD = "file"  # the multipart field, as an HTML form or `curl -F file=@gcp_list.txt` sends it
BODY = {
    "required": True,
    "description": f"the gcp_list.txt, at most {MAX_GCP_BYTES // (1024 * 1024)} MiB of UTF-8 text: "
    f"the request's body, or the multipart field '{FIELD}'",
    "content": {
        "text/plain": {"schema": {"type": "string"}},
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "properties": {FIELD: {"type": "string", "format": "binary"}},
                "required": [FIELD],
            }
        },
    },
}


async def gcp_bytes(request: Request) -> bytes:
    """The file's bytes: the multipart field ``file``, or the whole body: text/plain, any text/*,
    application/octet-stream, none, and application/x-www-form-urlencoded, which is what
    ``curl --data-binary @gcp_list.txt`` says of a file it sends unless told otherwise."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == "multipart/form-data":
        async with request.form(max_files=1, max_fields=8) as form:
            part = form.get(FIELD)
            if isinstance(part, UploadFile):
                return await part.read()
            if isinstance(part, str):
                return part.encode("utf-8")
            raise InvalidRequest(f"no multipart field '{FIELD}': {NO_FILE}")
    if kind in RAW or kind.startswith("text/"):
        return await request.body()
    raise UnsupportedFormat(f"a GCP file of type {kind}: {NO_FILE}")


@router.put("/projects/{project_id}/gcp", response_model=GcpOut, openapi_extra={"requestBody": BODY})
async def put_gcp(project_id: str, request: Request, svc: Svc, tenant_id: Tenant) -> GcpOut:
    """Store the project's ground control points, replacing any earlier file. The file is checked
    against the project's images: one it cannot use (an unknown coordinate system, fewer than 3
    points seen in two images each) is 422 with the reason and nothing is stored; lines and points
    it can do without (an image not in the project yet, a pixel outside its image) are listed in
    `problems` and `unusable`. A reconstruct job then georeferences the model by the points."""
    try:
        data = await gcp_bytes(request)
    except (DomainError, HTTPException):  # a bad body (a malformed multipart one is Starlette's 400)
        await run_in_threadpool(svc.projects.get_project, tenant_id, project_id)  # an unknown project: 404
        raise
    view = await run_in_threadpool(svc.gcp.put_gcp, tenant_id, project_id, data)
    return GcpOut.model_validate(view, from_attributes=True)


@router.get("/projects/{project_id}/gcp", response_model=GcpOut)
def get_gcp(project_id: str, svc: Svc, tenant_id: Tenant) -> GcpOut:
    """The stored file's summary, read against the project's images as they are now; 404 when the
    project has none."""
    return GcpOut.model_validate(svc.gcp.get_gcp(tenant_id, project_id), from_attributes=True)


@router.delete("/projects/{project_id}/gcp", status_code=204)
def delete_gcp(project_id: str, svc: Svc, tenant_id: Tenant) -> Response:
    """Remove the project's ground control points (the model stays as it is until the next
    reconstruct); 404 when it has none."""
    svc.gcp.delete_gcp(tenant_id, project_id)
    return Response(status_code=204)
