"""/v1/projects: create, list, read, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from ...paging import PROJECTS
from ..schemas import ProjectCreate, ProjectOut
from .deps import MAX_OFFSET, Svc, Tenant, link_next

router = APIRouter(tags=["projects"])


@router.post("/projects", status_code=201, response_model=ProjectOut)
def create_project(body: ProjectCreate, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    config = body.config.model_dump(exclude_none=True) if body.config else {}
    return ProjectOut.model_validate(
        svc.projects.create_project(tenant_id, body.name, config), from_attributes=True
    )


@router.get("/projects", response_model=list[ProjectOut])
def list_projects(
    request: Request,
    response: Response,
    svc: Svc,
    tenant_id: Tenant,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="projects to skip")] = 0,
    limit: Annotated[
        int,
        Query(
            ge=1,
            le=PROJECTS.max,
            description=f"page size (default {PROJECTS.default}); the next page is in the `Link` header",
        ),
    ] = PROJECTS.default,
) -> list[ProjectOut]:
    """The tenant's projects, oldest first, one page at a time."""
    page = svc.projects.list_projects(tenant_id, offset, limit)
    link_next(request, response, page.next_offset, limit)
    return [ProjectOut.model_validate(p, from_attributes=True) for p in page.items]


@router.get("/projects/{project_id}", response_model=ProjectOut)
def get_project(project_id: str, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    return ProjectOut.model_validate(svc.projects.get_project(tenant_id, project_id), from_attributes=True)


@router.delete("/projects/{project_id}", status_code=204)
def delete_project(project_id: str, svc: Svc, tenant_id: Tenant) -> Response:
    svc.projects.delete_project(tenant_id, project_id)
    return Response(status_code=204)
