"""/v1/projects: create, list, read, delete."""

from __future__ import annotations

from fastapi import APIRouter, Response

from ..schemas import ProjectCreate, ProjectOut
from .deps import Svc, Tenant

router = APIRouter(tags=["projects"])


@router.post("/projects", status_code=201, response_model=ProjectOut)
def create_project(body: ProjectCreate, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    config = body.config.model_dump(exclude_none=True) if body.config else {}
    return ProjectOut.model_validate(svc.create_project(tenant_id, body.name, config), from_attributes=True)


@router.get("/projects", response_model=list[ProjectOut])
def list_projects(svc: Svc, tenant_id: Tenant) -> list[ProjectOut]:
    return [ProjectOut.model_validate(p, from_attributes=True) for p in svc.list_projects(tenant_id)]


@router.get("/projects/{project_id}", response_model=ProjectOut)
def get_project(project_id: str, svc: Svc, tenant_id: Tenant) -> ProjectOut:
    return ProjectOut.model_validate(svc.get_project(tenant_id, project_id), from_attributes=True)


@router.delete("/projects/{project_id}", status_code=204)
def delete_project(project_id: str, svc: Svc, tenant_id: Tenant) -> Response:
    svc.delete_project(tenant_id, project_id)
    return Response(status_code=204)
