"""/v1/projects/{id}/localize: new photos posed against the project's model."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Response, UploadFile

from ...usecases.localize import localizations
from ...usecases.views import JobView, Upload
from ..schemas import LocalizationOut, LocalizeOut, Progress
from .deps import Svc, Tenant

# the form's default wait: longer than any server allows, so the server's setting decides. Not
# None: a multipart form has no null, and a schema that says the field may be null invites one
WAIT_AS_LONG_AS_ALLOWED = 86400.0

router = APIRouter(tags=["localize"])


def localize_out(job: JobView) -> LocalizeOut:
    answers = localizations(job)
    return LocalizeOut(
        job_id=job.id,
        state=job.state,
        progress=Progress(done=job.done, total=job.total),
        error=job.error,
        localizations=None if answers is None else [LocalizationOut.model_validate(a) for a in answers],
    )


@router.post(
    "/projects/{project_id}/localize",
    status_code=200,
    response_model=LocalizeOut,
    responses={
        202: {
            "model": LocalizeOut,
            "description": "still running after the wait: follow GET /v1/jobs/{job_id} (its `result` "
            "holds the same `localizations` once it succeeded)",
        }
    },
)
def localize(
    project_id: str,
    response: Response,
    files: Annotated[
        list[UploadFile], File(description="one or more photos (repeat the field)", min_length=1)
    ],
    svc: Svc,
    tenant_id: Tenant,
    add: Annotated[
        bool,
        Form(
            description="also add the photos to the project as images, and their matches to its "
            "COLMAP database, so that a later reconstruct uses them"
        ),
    ] = False,
    capture: Annotated[
        Literal["aerial", "ground", "auto"], Form(description="auto: EXIF/XMP decides")
    ] = "auto",
    wait: Annotated[
        float,
        Form(
            ge=0,
            description="seconds to wait for the answer before answering 202 with the job; "
            "cut to the server's GEOMATCH_LOCALIZE_WAIT_S, so the default waits that long",
        ),
    ] = WAIT_AS_LONG_AS_ALLOWED,
) -> LocalizeOut:
    """Where was each photo taken: its pose in the model's frame, and on the map when the model is
    georeferenced. 200 when the job ended within the wait (its state says how: `succeeded` with
    one answer per photo, a photo that could not be placed answered `localized: false`), 202 with
    the job otherwise. 409 for a project without a model."""
    uploads = [Upload(f.filename, f.file) for f in files]
    job = svc.localize.localize(tenant_id, project_id, uploads, add=add, capture=capture, wait_s=wait)
    if not job.terminal:
        response.status_code = 202
        response.headers["Location"] = f"/v1/jobs/{job.id}"
    return localize_out(job)
