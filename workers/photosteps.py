"""A match job's plan spread over the workers: the features its plan reads of each photo (a
survey's turn scores, retrieval's descriptors: geomatch.pipeline.plan_photos) extracted by
``plan_features`` steps on every worker, a chunk of photos each, before the one step that plans.

Why: that extraction is most of a survey's plan, and in one step it ran on one worker while the
others waited (docs/benchmarks.md, "A thousand photos"). The plan itself stays one step
(``jobs._plan``, the library's ``plan_project``): it finds the features in the feature store, so
it is the plan the one step would have made.

``plan_match`` asks :func:`ready` first. The first time it writes a ``job_photos`` row per photo
and queues the chunks; the chunk step that leaves no photo undone queues ``plan_match`` again,
which then plans. Each step may run twice: a chunk's rows flip to done once
(``jobstate.mark_photos_done``, the job's row locked), so one step sees the count reach zero; a
redelivered or recovered ``plan_match`` (workers.recovery, workers.sweep) queues again the chunks
not done. A small project, one whose plan reads no features, and a runner of one slot plan in one
step as before.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from geomatch.options import DEFAULTS
from geomatch_core import jobstate
from geomatch_core.models import Image, Job, JobPhoto
from geomatch_core.queue import PLAN_FEATURES, PLAN_MATCH

from . import runtime
from .context import StepContext

if TYPE_CHECKING:
    from geomatch.pipeline.plan import Hint

log = logging.getLogger("geomatch.workers")

# fewer photos: planned in one step (the steps' queue round trips would cost more than they spread)
MIN_PHOTOS = 8
CHUNKS_PER_SLOT = 2  # chunks per runner slot: a worker that ends first takes another


def ready(ctx: StepContext, job: Job) -> bool:
    """Whether ``job`` may be planned now: its plan's features extracted by the chunk steps, or
    none to extract. Otherwise the chunks not done are queued (the rows written first, once)."""
    with ctx.store.session() as s:
        rows = s.execute(select(JobPhoto.chunk, JobPhoto.done).where(JobPhoto.job_id == job.id)).all()
    if not rows:
        if not _spread(ctx, job):
            return True
        with ctx.store.session() as s:
            rows = s.execute(select(JobPhoto.chunk, JobPhoto.done).where(JobPhoto.job_id == job.id)).all()
    pending = sorted({chunk for chunk, done in rows if not done})
    for chunk in pending:
        ctx.queue.enqueue(PLAN_FEATURES, job.id, chunk)
    return not pending


def _spread(ctx: StepContext, job: Job) -> bool:
    """Write the job's photo rows, chunked; False when the plan is left to one step."""
    from geomatch.pipeline.plan_photos import photo_work
    from geomatch.pipeline.prepare import frames
    from geomatch.pipeline.project import PlanRequest, ProjectImages

    opts, pid = runtime.job_options(job.options), job.project_id
    with ctx.store.session() as s:
        captures = dict(
            s.execute(
                select(Image.name, Image.capture).where(Image.project_id == pid).order_by(Image.name)
            ).all()
        )
    names = sorted(captures)
    # no store: nothing to share; one slot (the embedded runner's one thread): nothing to run beside
    if len(names) < MIN_PHOTOS or ctx.settings.feature_cache_mb <= 0 or ctx.queue.slots() < 2:
        return False
    t0 = time.perf_counter()
    image_dir = ctx.storage.images_dir(pid)
    spec = opts["pairs"] if isinstance(opts["pairs"], str) else DEFAULTS["pairs"]
    pairs_list = opts["pairs"] if isinstance(opts["pairs"], list) else None
    work = photo_work(
        ProjectImages.read(image_dir, names),
        captures,
        PlanRequest(spec, pairs_list, opts["tiling"]),
        frames(image_dir, runtime.images_mb(ctx)),
    )
    if work is None:
        return False
    if work.hints:  # before the rows: a plan that finds the rows done finds the hints
        path = _hints_path(ctx, job)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(work.hints_json()) + "\n")
        tmp.replace(path)
    chunks = min(len(names), CHUNKS_PER_SLOT * ctx.queue.slots())
    size = math.ceil(len(names) / chunks)
    try:
        with ctx.store.session() as s:
            s.add_all(
                JobPhoto(
                    job_id=job.id,
                    name=n,
                    chunk=i // size,
                    turn=-1 if work.turns is None else work.turns[n],
                    sparse=work.sparse,
                )
                for i, n in enumerate(names)
            )
    except IntegrityError:  # a duplicate of this step wrote them first
        return True
    log.info(
        "plan features of %d photos spread in %d steps (decided in %.1fs)",
        len(names),
        math.ceil(len(names) / size),
        time.perf_counter() - t0,
        extra={"job_id": job.id, "project_id": pid},
    )
    return True


def _hints_path(ctx: StepContext, job: Job) -> Path:
    return ctx.storage.project_dir(job.project_id) / f"plan-hints-{job.id}.json"


def known_hints(ctx: StepContext, job: Job) -> Hint | None:
    """The SIFT hints the job's guess of its turns made (:func:`_spread`), for its plan; None
    where it made none (the plan then makes its own)."""
    from geomatch.matching.turnhint import KnownHints
    from geomatch.pipeline.plan_photos import hints_from_json

    try:
        rows = json.loads(_hints_path(ctx, job).read_text())
    except FileNotFoundError:
        return None
    return KnownHints(hints_from_json(rows)).hint


def forget(ctx: StepContext, job: Job) -> None:
    """Drop what the job's plan no longer needs, once planned."""
    _hints_path(ctx, job).unlink(missing_ok=True)


def plan_features(ctx: StepContext, job_id: str, chunk: int) -> str:
    """Extract the plan's features of one chunk of a job's photos into the feature store; the step
    that leaves no photo undone queues the plan (``plan_match``)."""
    from geomatch.pipeline.plan_photos import extract

    job = jobstate.get(ctx.store, job_id)
    if job is None or job.state != "running":
        return "skipped"
    with ctx.store.session() as s:
        rows = s.scalars(
            select(JobPhoto).where(JobPhoto.job_id == job_id, JobPhoto.chunk == chunk).order_by(JobPhoto.name)
        ).all()
    todo = [r for r in rows if not r.done]
    if not todo:
        return "done before"
    pid = job.project_id
    matcher = runtime.matcher(ctx, runtime.job_options(job.options))
    store = getattr(matcher, "store", None)
    saved = store.saved if store is not None else 0
    t0 = time.perf_counter()
    for r in todo:
        if not jobstate.is_active(ctx.store, job_id):
            return "cancelled"
        image, _ = runtime.frame(ctx, ctx.storage.image_path(pid, r.name))
        extract(matcher, image, None if r.turn < 0 else r.turn, r.sparse)
    computed = (store.saved if store is not None else 0) - saved
    left = jobstate.mark_photos_done(ctx.store, job_id, chunk)
    log.info(
        "plan features: chunk %d, %d photos, %d features computed, in %.1fs; %s",
        chunk,
        len(todo),
        computed,
        time.perf_counter() - t0,
        "counted before" if left is None else f"{left} photos left",
        extra={"job_id": job_id, "project_id": pid},
    )
    if left == 0:
        ctx.queue.enqueue(PLAN_MATCH, job_id)
    return "done"
