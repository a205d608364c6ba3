"""/v1/projects/{id}/images: uploads, the list, an image's bytes."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Query, Request, Response, UploadFile
from fastapi.responses import FileResponse

from ...paging import IMAGES
from ...usecases.images import IMAGE_MEDIA
from ...usecases.views import Upload
from ..schemas import ImageOut, ImagesOut
from .deps import MAX_OFFSET, Svc, Tenant, link_next

router = APIRouter(tags=["images"])


@router.post("/projects/{project_id}/images", status_code=201, response_model=ImagesOut)
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
    views = svc.images.upload_images(
        tenant_id, project_id, [Upload(f.filename, f.file) for f in files], capture
    )
    return ImagesOut(images=[ImageOut.model_validate(v, from_attributes=True) for v in views])


@router.get("/projects/{project_id}/images", response_model=ImagesOut)
def list_images(
    project_id: str,
    request: Request,
    response: Response,
    svc: Svc,
    tenant_id: Tenant,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="images to skip")] = 0,
    limit: Annotated[
        int,
        Query(
            ge=1,
            le=IMAGES.max,
            description=f"page size (default {IMAGES.default}); the next page is in the `Link` header",
        ),
    ] = IMAGES.default,
) -> ImagesOut:
    """The project's images by name, one page at a time."""
    page = svc.images.list_images(tenant_id, project_id, offset, limit)
    link_next(request, response, page.next_offset, limit)
    return ImagesOut(images=[ImageOut.model_validate(v, from_attributes=True) for v in page.items])


@router.get(
    "/projects/{project_id}/images/{name}",
    response_class=FileResponse,
    responses={200: {"content": {m: {} for m in IMAGE_MEDIA.values()}, "description": "the bytes"}},
)
def image_file(project_id: str, name: str, svc: Svc, tenant_id: Tenant) -> FileResponse:
    """The uploaded bytes, typed by the format the upload check found (never sniffed)."""
    path, media = svc.images.image_file(tenant_id, project_id, name)
    return FileResponse(path, media_type=media, headers={"X-Content-Type-Options": "nosniff"})
