"""Localize: new photos posed against a project's model, answered at once when the work is quick,
as a job otherwise.

The photos pass the upload checks (name, size, type, truncation) before anything is kept. Not
added (the default), they are staged into the job's own folder inside the project, which the
worker removes when the job ends; with ``add`` they are uploaded to the project as any image is
(all or none, quotas, the same name with other bytes a conflict) and the job writes them and their
matches into the COLMAP database, so a later reconstruct uses them. Either way the work is one
``localize`` job run by the workers (``workers.localize.localize``), so it is queued, retried, resumed
after a restart and read like every other job; the request waits for it for a while
(``Settings.localize_wait_s``, or less when the client asks) and answers with the finished job
when it can.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterable
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from geomatch.options import CAPTURES, PROJECT_OPTIONS, RECONSTRUCT_OPTIONS
from geomatch_core.errors import BadFile, Conflict, InvalidRequest, NotFound, Overloaded, QuotaExceeded
from geomatch_core.models import Image, Job, Project, new_id

from ..validation import check_name
from .base import DEFAULTS, Context, Staged, UseCases, check_config, check_open_jobs, choice, staged_bytes
from .images import ImageUseCases
from .jobs import JobUseCases
from .views import JobView, Upload, job_view

WAIT_POLL_S = 0.1  # how often a waiting request reads its job


class LocalizeUseCases(UseCases):
    """Built on the uploads (``add``) and the jobs (queueing, reading) of the project: the
    service's own image and job use cases, over the same context."""

    def __init__(self, ctx: Context, images: ImageUseCases, jobs: JobUseCases) -> None:
        super().__init__(ctx)
        self.images = images
        self.jobs = jobs

    def localize(
        self,
        tenant_id: str,
        project_id: str,
        uploads: Iterable[Upload],
        add: bool = False,
        capture: str = "auto",
        wait_s: float | None = None,
    ) -> JobView:
        """The localize job of these photos: finished (its result holds one answer per photo, in
        the order sent) when it ended within the wait, queued or running otherwise. ``wait_s``
        shortens the service's wait (``Settings.localize_wait_s``), never lengthens it; 0 answers
        with the job at once."""
        capture = choice("capture", capture, CAPTURES)
        wait = self._localize_wait(wait_s)
        with self._unless_deleted(tenant_id, project_id):
            with self.ctx.store.session() as s:
                config = dict(self._project(s, tenant_id, project_id).config)
                check_open_jobs(s, self.ctx.settings, tenant_id)  # before a byte is kept
            self._model_ready(project_id)
            job_id = new_id()
            staged = 0
            if add:
                views = self.images.upload_images(tenant_id, project_id, uploads, capture)
                photos = [(v.name, v.capture) for v in views]
            else:
                photos, staged = self._stage_photos(project_id, job_id, uploads, capture)
            try:
                with self.ctx.store.session() as s:
                    self._project(s, tenant_id, project_id)
                    check_open_jobs(s, self.ctx.settings, tenant_id)
                    self._within_quota(s, tenant_id, staged)
                    job = self._localize_job(s, job_id, project_id, tenant_id, config, photos, add, staged)
                    view = job_view(job)
            except BaseException:
                shutil.rmtree(self.ctx.storage.localize_dir(project_id, job_id), ignore_errors=True)
                raise
        try:
            self.jobs.enqueue(view)
        except BaseException:
            shutil.rmtree(self.ctx.storage.localize_dir(project_id, job_id), ignore_errors=True)
            raise
        return self._wait_for(tenant_id, view, wait)

    def _localize_wait(self, wait_s: float | None) -> float:
        most = self.ctx.settings.localize_wait_s
        if wait_s is None:
            return most
        if not wait_s >= 0:  # negative, or NaN
            raise InvalidRequest(f"wait must be a number of seconds >= 0, not {wait_s!r}")
        return min(float(wait_s), most)

    def _model_ready(self, project_id: str) -> None:
        """Conflict unless the project has a model with registered images to localize against."""
        model = self.ctx.storage.model_dir(project_id)
        if not (model / "summary.json").is_file():
            raise Conflict(
                f"project {project_id} has no model yet: localizing needs one "
                "(POST .../match with reconstruct, or .../reconstruct, first)"
            )
        if not (model / "sparse" / "0" / "images.bin").is_file():
            raise Conflict(
                f"the model of project {project_id} registered no images: there is nothing to "
                "localize against (add images and reconstruct again)"
            )

    def _within_quota(self, s: Session, tenant_id: str, staged: int) -> None:
        """QuotaExceeded when ``staged`` more bytes would take the tenant's stored images and the
        photos its unfinished localize jobs hold past ``quota_bytes``: a staged photo is on the
        server's disk for as long as its job runs (15 requests once staged 86 MB under a 20 MB
        quota while an image upload was refused)."""
        quota = self.ctx.settings.quota_bytes
        if not quota or not staged:
            return
        stored = s.scalar(
            select(func.coalesce(func.sum(Image.size_bytes), 0))
            .join(Project, Project.id == Image.project_id)
            .where(Project.tenant_id == tenant_id)
        )
        held = int(stored or 0) + staged_bytes(s, tenant_id)
        if held + staged > quota:
            raise QuotaExceeded(
                f"this key's tenant stores {held} bytes of images and photos staged for localizing, its "
                f"quota is {quota}: these {staged} would pass it (wait for its localize jobs to end, or "
                "delete a project to make room)"
            )

    def _stage_photos(
        self, project_id: str, job_id: str, uploads: Iterable[Upload], capture: str
    ) -> tuple[list[tuple[str, str]], int]:
        """Every photo checked as an upload is and put in the job's folder, or none (the folder is
        removed on any error); with its capture (the file's own, else the request's); and their
        bytes in all."""
        folder = self.ctx.storage.localize_dir(project_id, job_id)
        photos: list[tuple[str, str]] = []
        size = 0
        try:
            for up in uploads:
                name = check_name(up.name)
                if name in (n for n, _ in photos):
                    raise BadFile(f"{name}: sent twice in one request")
                taken = capture if up.capture is None else choice("capture", up.capture, CAPTURES)
                staged: Staged = self._stage(name, up.stream)
                try:
                    folder.mkdir(parents=True, exist_ok=True)
                    os.replace(staged.path, folder / name)
                finally:
                    staged.path.unlink(missing_ok=True)
                photos.append((name, taken))
                size += staged.size
            if not photos:
                raise InvalidRequest("no photos: send one or more multipart fields named 'files'")
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return photos, size

    def _localize_job(
        self,
        s: Session,
        job_id: str,
        project_id: str,
        tenant_id: str,
        config: dict[str, Any],
        photos: list[tuple[str, str]],
        add: bool,
        staged: int = 0,
    ) -> Job:
        opts = {**DEFAULTS, **check_config(config)}
        # the project's matcher and its options; the mapping's and a match job's pairs do not apply
        skip = {*RECONSTRUCT_OPTIONS, "pairs"}
        opts = {k: v for k, v in opts.items() if k in PROJECT_OPTIONS and k not in skip}
        job = Job(
            id=job_id,
            project_id=project_id,
            tenant_id=tenant_id,
            kind="localize",
            options={
                **opts,
                "add": add,
                "photos": [n for n, _ in photos],
                "captures": [c for _, c in photos],
                "staged_bytes": staged,
            },
            total=len(photos),
        )
        s.add(job)
        s.flush()
        return job

    def _wait_for(self, tenant_id: str, job: JobView, wait_s: float) -> JobView:
        """The job once it ended, or as it is after ``wait_s``. Waiting holds one of the tenant's
        heavy slots, as a match picture's wait does; without a free one the job is answered at
        once (it runs all the same), rather than refused."""
        if wait_s <= 0:
            return job
        try:
            self.ctx.heavy.acquire(tenant_id)
        except Overloaded:
            return job
        try:
            deadline = time.monotonic() + wait_s
            while not job.terminal and time.monotonic() < deadline:
                time.sleep(min(WAIT_POLL_S, max(0.0, deadline - time.monotonic())))
                try:
                    job = self.jobs.get_job(tenant_id, job.id)
                except NotFound:  # the project was deleted meanwhile: as any job of it, gone
                    raise NotFound(f"project {job.project_id} not found") from None
            return job
        finally:
            self.ctx.heavy.release(tenant_id)


def localizations(job: JobView) -> list[dict[str, Any]] | None:
    """A finished localize job's answers, one per photo in the order sent; None before."""
    if job.state != "succeeded" or not job.result:
        return None
    found = job.result.get("localizations")
    return [dict(a) for a in found] if isinstance(found, list) else None
