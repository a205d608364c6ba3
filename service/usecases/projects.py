"""Projects: create, list, read and delete a tenant's projects."""

from __future__ import annotations

from typing import Any

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from geomatch.options import PAIR_SPEC_WORDS
from geomatch_core import jobstate
from geomatch_core.errors import InvalidRequest, NotFound, QuotaExceeded
from geomatch_core.models import Image, Job, Project

from ..paging import PROJECTS, Page, page_of
from ..validation import check_project_name
from .base import UseCases, check_config
from .views import ProjectView


class ProjectUseCases(UseCases):
    def create_project(self, tenant_id: str, name: str, config: dict[str, Any] | None = None) -> ProjectView:
        name = check_project_name(name)
        cfg = check_config(config or {})
        if isinstance(cfg.get("pairs"), list):
            raise InvalidRequest(f"a project's default pairs is a spec ({PAIR_SPEC_WORDS}), not a list")
        with self.ctx.store.session() as s:
            self._within_project_quota(s, tenant_id)
            p = Project(tenant_id=tenant_id, name=name, config=cfg)
            s.add(p)
            s.flush()
            return self._project_view(s, p)

    def _within_project_quota(self, s: Session, tenant_id: str) -> None:
        """QuotaExceeded at ``quota_projects``. Checked in the creating transaction, not locked:
        concurrent creates may pass it by a few, which a quota against slow exhaustion allows."""
        quota = self.ctx.settings.quota_projects
        if not quota:
            return
        n = s.scalar(select(func.count()).select_from(Project).where(Project.tenant_id == tenant_id)) or 0
        if n >= quota:
            raise QuotaExceeded(
                f"this key's tenant has {n} projects, its quota is {quota}: delete one to create another"
            )

    def list_projects(self, tenant_id: str, offset: int = 0, limit: int | None = None) -> Page[ProjectView]:
        """One page of the tenant's projects, oldest first (``paging.PROJECTS``: its sizes)."""
        limit = PROJECTS.clamp(limit)
        with self.ctx.store.session() as s:
            rows = s.scalars(
                select(Project)
                .where(Project.tenant_id == tenant_id)
                .order_by(Project.created_at, Project.id)
                .offset(offset)
                .limit(limit + 1)
            ).all()
            return page_of([self._project_view(s, p) for p in rows], offset, limit)

    def get_project(self, tenant_id: str, project_id: str) -> ProjectView:
        with self.ctx.store.session() as s:
            return self._project_view(s, self._project(s, tenant_id, project_id))

    def delete_project(self, tenant_id: str, project_id: str) -> None:
        """Of concurrent deletes of one project exactly one succeeds, the others find it gone: the
        row is deleted by one statement whose row count says who did it."""
        with self.ctx.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            jobs = s.scalars(select(Job.id).where(Job.project_id == p.id)).all()
        for job_id in jobs:  # workers see their job gone or cancelled and stop
            jobstate.cancel(self.ctx.store, job_id, "project deleted")
        with self.ctx.store.session() as s:
            gone = s.execute(delete(Project).where(Project.id == project_id, Project.tenant_id == tenant_id))
            if gone.rowcount != 1:  # type: ignore[attr-defined]  # typed Result; a DELETE gets a CursorResult
                raise NotFound(f"project {project_id} not found")
        # the writer lock: a worker writing this project right now finishes before the files go
        with self.ctx.locks.project(project_id):
            self.ctx.storage.delete_project(project_id)

    def _project_view(self, s: Session, p: Project) -> ProjectView:
        n = s.scalar(select(func.count()).select_from(Image).where(Image.project_id == p.id)) or 0
        has_model = (self.ctx.storage.model_dir(p.id) / "summary.json").is_file()
        return ProjectView(p.id, p.name, dict(p.config), p.created_at, int(n), has_model)
