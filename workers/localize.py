"""The localize job's step: a job's photos posed against the project's model
(``geomatch.localize``), one answer per photo as the job's result; ``drop_photos`` removes the
photos the job brought (the failure handler calls it too)."""

from __future__ import annotations

import logging
import shutil
import time
from typing import Any

from sqlalchemy import select

from geomatch.options import PROJECT_OPTIONS
from geomatch_core import jobstate
from geomatch_core.models import Image

from . import runtime
from .context import PermanentError, StepContext

log = logging.getLogger("geomatch.workers")


def localize(ctx: StepContext, job_id: str) -> str:
    """Pose the job's photos against the project's model (``geomatch.localize``) and store one
    answer per photo as the job's result.

    Photos that are not added to the project live in the job's own folder, removed when the job
    ends however it ends (here, or in ``on_failure``). Added ones were stored as project images by
    the request; each is written with its matches into the COLMAP database under the project's
    writer lock, held for that write only (the matching before it takes seconds a photo, and a
    Redis lock expires after GEOMATCH_LOCK_TIMEOUT). Without ``add`` the step only reads the
    project, so it runs beside match and reconstruct jobs. A rerun after a redelivery starts over:
    the answers are the same, and an added photo's rows are written once (``add_to_project``
    leaves what the database holds)."""
    from geomatch.localize import LocalizeOptions, Localizer, Project, add_to_project

    job = jobstate.claim(ctx.store, job_id)
    if job is None:
        drop_photos(ctx, job_id)
        return "skipped"
    pid, stored = job.project_id, dict(job.options)
    add = bool(stored.get("add"))
    names = [str(n) for n in stored.get("photos", [])]
    folder = ctx.storage.images_dir(pid) if add else ctx.storage.localize_dir(pid, job_id)
    missing = [n for n in names if not (folder / n).is_file()]
    if missing:
        raise PermanentError(f"the photos {', '.join(missing)} are gone (deleted from the project meanwhile)")
    opts = runtime.job_options({k: v for k, v in stored.items() if k in PROJECT_OPTIONS})
    with ctx.store.session() as s:  # resolved by the match jobs: the model's aerial images
        aerial = set(s.scalars(select(Image.name).where(Image.project_id == pid, Image.aerial.is_(True))))
    t0 = time.perf_counter()
    project = Project.find(
        ctx.storage.project_dir(pid),
        model_dir=ctx.storage.model_dir(pid) / "sparse" / "0",
        images_dir=ctx.storage.images_dir(pid),
    )
    localizer = Localizer(project, LocalizeOptions(), runtime.matcher(ctx, opts), aerial)
    answers: list[dict[str, Any]] = []
    for k, name in enumerate(names):
        if not jobstate.is_active(ctx.store, job_id):
            drop_photos(ctx, job_id)
            return "cancelled"
        result, evidence = localizer.localize(folder / name)
        if add and evidence is not None:
            with ctx.locks.project(pid):
                add_to_project(
                    project, folder / name, evidence, localizer.matcher, float(opts["snap_radius"])
                )
        answers.append(result.to_json())
        jobstate.set_progress(ctx.store, job_id, k + 1)
    jobstate.succeed(ctx.store, job_id, {"localizations": answers})
    drop_photos(ctx, job_id)
    log.info(
        "localized %d of %d photos in %.1fs (add=%s)",
        sum(bool(a.get("localized")) for a in answers),
        len(answers),
        time.perf_counter() - t0,
        add,
        extra={"job_id": job_id, "project_id": pid},
    )
    return "done"


def drop_photos(ctx: StepContext, job_id: str) -> None:
    """Remove a localize job's own photos (none for a job that added them to the project)."""
    job = jobstate.get(ctx.store, job_id)
    if job is not None:
        shutil.rmtree(ctx.storage.localize_dir(job.project_id, job_id), ignore_errors=True)
