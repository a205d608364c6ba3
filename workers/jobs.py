"""The steps of match and reconstruct jobs, whatever runs them (Celery worker processes or the
embedded threads), and what a job's failure records (a localize job's step: localize.py).

A match job is ``plan_match`` -> ``match_pair`` per pair, a window of them at a time (each pair
step makes the features it needs and queues the next pair); a survey's or a retrieval plan's
photos first get their features in ``plan_features`` steps on every worker, the last of which
queues ``plan_match`` again to plan (photosteps.py); a reconstruct job is one
``reconstruct``, a localize job one ``localize``. The planning and the mapping are the library's
stages (geomatch.pipeline.prepare, geomatch.pipeline.reconstruction), the ones ``geomatch run``
calls: this module runs them queued. Every step may run twice (redelivery
after a worker died, a duplicate dispatch) and must then do nothing twice:

- a pair already in the COLMAP database is not matched again, and ``write_pair`` is a no-op for
  a pair that is there (both checked under the project's writer lock);
- a pair counts towards progress when its ``job_pairs`` row flips to done, once;
- the model is built in a fresh folder and swapped in whole.

A step first checks that its job is still running: cancelled, failed or deleted jobs are skipped,
which is how cancellation stops the pair steps still queued. The library is imported inside the
steps only, so importing this module does not import torch.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from geomatch.options import (
    DEFAULTS,
    fewest_pairs,
)
from geomatch.sfm.sqlitecopy import snapshot_sqlite
from geomatch_core import jobstate
from geomatch_core.errors import too_many_pairs, too_much_queued
from geomatch_core.models import Image, Job, JobPair
from geomatch_core.queue import LOCALIZE, MATCH_PAIR, RENDER_PAIR

from . import photosteps, redact, runtime
from .context import PermanentError, StepContext
from .localize import drop_photos

log = logging.getLogger("geomatch.workers")


# -- match jobs ---------------------------------------------------------------------------------
def plan_match(ctx: StepContext, job_id: str) -> str:
    job = jobstate.claim(ctx.store, job_id)
    if job is None:
        return "skipped"
    if not job.planned:
        if not photosteps.ready(ctx, job):  # the plan's features still being extracted
            return "features spread"
        _plan(ctx, job)
    return _dispatch(ctx, job_id)


def _plan(ctx: StepContext, job: Job) -> None:
    """The project prepared as ``geomatch run`` prepares it (geomatch.pipeline.prepare): its
    photos read, its aerial images and plan decided, its images registered; the plan kept beside
    the database (plan.json) for the reconstruct job, the pairs not matched yet as the job's rows."""
    from geomatch.pipeline import database
    from geomatch.pipeline.prepare import frames, plan_project, register
    from geomatch.pipeline.project import PlanRequest, ProjectImages
    from geomatch.sfm.colmapdb import ColmapDatabase

    t0 = time.perf_counter()
    opts, pid = runtime.job_options(job.options), job.project_id
    with ctx.store.session() as s:
        rows = s.execute(
            select(Image.name, Image.capture).where(Image.project_id == pid).order_by(Image.name)
        ).all()
    names = [n for n, _ in rows]
    image_dir = ctx.storage.images_dir(pid)
    images = ProjectImages.read(image_dir, names)
    spec = opts["pairs"] if isinstance(opts["pairs"], str) else DEFAULTS["pairs"]
    pairs_list = opts["pairs"] if isinstance(opts["pairs"], list) else None
    limit = ctx.settings.max_pairs_per_job
    least, exact = fewest_pairs(spec, len(names)) if pairs_list is None else (len(pairs_list), True)
    if limit and least > limit:  # the API refused this at its image count: images were added since
        words = spec if pairs_list is None else "the pair list"
        raise PermanentError(too_many_pairs(least, len(names), limit, words, exact))
    request = PlanRequest(spec, pairs_list, opts["tiling"])
    computed = _computed(ctx, opts)
    plan = plan_project(
        images,
        dict(rows),
        request,
        lambda: runtime.matcher(ctx, opts),
        frames(image_dir, runtime.images_mb(ctx)),
        hint=photosteps.known_hints(ctx, job),
    )
    if limit and len(plan.pairs) > limit:  # auto, gps:K, retrieval:K: known once planned; no row written
        words = plan.in_words if pairs_list is None else "the pair list"
        raise PermanentError(too_many_pairs(len(plan.pairs), len(names), limit, words))
    aerial = set(plan.aerial)
    with ctx.store.session() as s:
        for n in names:
            s.execute(
                update(Image).where(Image.project_id == pid, Image.name == n).values(aerial=n in aerial)
            )
    db_path = ctx.storage.database_path(pid)
    with ctx.locks.project(pid):
        if not jobstate.is_active(ctx.store, job.id):
            return
        ids = register(db_path, images, opts["share_camera"])
        with ColmapDatabase(db_path) as db:
            todo = database.unmatched(db, ids, plan.pairs)
        plan.write(ctx.storage.plan_path(pid))
    queue_limit = ctx.settings.max_queued_pairs
    if queue_limit:  # the API counted this job by the fewest pairs its plan could have
        queued, jobs, _ = jobstate.queued_pairs(ctx.store, job.tenant_id, other_than=job.id)
        if queued + len(todo) > queue_limit:
            raise PermanentError(too_much_queued(queued, jobs, len(todo), queue_limit))
    with ctx.store.session() as s:
        row = s.get(Job, job.id, with_for_update=True)
        if row is None or row.planned:  # a duplicate of this step planned it first
            return
        s.add_all(
            JobPair(
                job_id=job.id,
                idx=i,
                name0=p.name0,
                name1=p.name1,
                tiled=p.tiled,
                aerial_first=p.aerial_first,
                rotate=p.rotate,
                turn0=-1 if p.turns is None else p.turns[0],
                turn1=-1 if p.turns is None else p.turns[1],
                aerial_project=p.aerial_project,
                survey=p.survey,
            )
            for i, p in enumerate(todo)
        )
        row.total = len(todo)
        row.planned = True
    photosteps.forget(ctx, job)
    log.info(
        "planned %d pairs (%d already matched, %d tiled) in %.1fs, %d features computed; "
        "the plan stage took %.1fs since the job started",
        len(todo),
        len(plan.pairs) - len(todo),
        sum(p.tiled for p in todo),
        time.perf_counter() - t0,
        _computed(ctx, opts) - computed,
        jobstate.running_for(job),
        extra={"job_id": job.id, "project_id": pid},
    )


def _computed(ctx: StepContext, opts: dict[str, Any]) -> int:
    """Features this process's matcher for ``opts`` has computed and stored so far (0 before it is
    built: counting builds none, so a plan that reads no features loads no network)."""
    store = getattr(runtime.built_matcher(ctx, opts), "store", None)
    return int(store.saved) if store is not None else 0


def _dispatch(ctx: StepContext, job_id: str) -> str:
    """Queue the pair steps the job's window holds: again those handed out before and not done
    (after a redelivery or a restart that lost the queue: duplicates skip), then new ones up to
    the window. Each pair step queues the next as it ends (:func:`_next_pairs`), so a job of
    thousands of pairs keeps only a few steps in the queue and another job's steps are never
    behind all of it. Features are made by the first pair step that needs them (on disk for the
    rest), which keeps extraction inside the window too."""
    with ctx.store.session() as s:
        job = s.get(Job, job_id)
        handed = job.dispatched if job is not None else 0
        pending = s.scalars(
            select(JobPair.idx)
            .where(JobPair.job_id == job_id, JobPair.done.is_(False), JobPair.idx < handed)
            .order_by(JobPair.idx)
        ).all()
    if job is None:
        return "skipped"
    if job.done >= job.total:
        if jobstate.finish_if_complete(ctx.store, job_id):
            jobstate.release_followers(ctx.store, ctx.queue, job_id)
        return "nothing to match"
    for idx in pending:
        ctx.queue.enqueue(MATCH_PAIR, job_id, idx)
    fresh = _next_pairs(ctx, job_id)
    return f"dispatched {len(pending) + fresh} pairs"


def _next_pairs(ctx: StepContext, job_id: str) -> int:
    """Hand the queue the job's next pairs while its window has room; how many."""
    window = ctx.settings.pairs_in_flight or ctx.queue.slots()
    claimed = jobstate.claim_pairs(ctx.store, job_id, max(1, window))
    for idx in claimed:
        ctx.queue.enqueue(MATCH_PAIR, job_id, idx)
    return len(claimed)


def match_pair(ctx: StepContext, job_id: str, idx: int) -> str:
    from geomatch.pipeline import match_pairs
    from geomatch.pipeline.pair_sources import Pair
    from geomatch.sfm.colmapdb import ColmapDatabase

    job = jobstate.get(ctx.store, job_id)
    if job is None or job.state != "running":
        return "skipped"
    with ctx.store.session() as s:
        p = s.get(JobPair, (job_id, idx))
    if p is None:
        return "skipped"
    pid, opts = job.project_id, runtime.job_options(job.options)
    db_path = ctx.storage.database_path(pid)
    matches = inliers = 0
    if not p.done:
        with ctx.locks.project(pid), ColmapDatabase(db_path) as db:
            id0, id1 = _image_id(db, p.name0), _image_id(db, p.name1)
            present = db.has_pair(id0, id1)  # redelivered after its write, or matched by another job
        if not present:
            a, photo0 = runtime.frame(ctx, ctx.storage.image_path(pid, p.name0))
            b, photo1 = runtime.frame(ctx, ctx.storage.image_path(pid, p.name1))
            turns = None if p.turn0 < 0 else (p.turn0, p.turn1)
            pair = Pair(
                p.name0, p.name1, p.tiled, p.aerial_first, p.rotate, turns, p.aerial_project, p.survey
            )
            target = match_pairs.PairTarget(
                lambda: _writable(ctx, job_id, pid, db_path),
                id0,
                id1,
                float(opts["snap_radius"]),
                read=lambda: _readable(ctx, pid, db_path),
                photos=(photo0, photo1),
            )
            r = match_pairs.run_pair(runtime.matcher(ctx, opts), pair, a, b, target)
            if r.written is None:
                return "cancelled"
            w = r.written
            matches, inliers = w.matches, w.inliers
            log.info(
                "pair %s x %s: %d matches, %d inliers (%s), match %.2fs write %.2fs",
                p.name0,
                p.name1,
                w.matches,
                w.inliers,
                w.config or "present",
                r.match_s,
                r.write_s,
                extra={"job_id": job_id, "project_id": pid},
            )
    jobstate.mark_pair_done(ctx.store, job_id, idx, matches, inliers)
    if jobstate.finish_if_complete(ctx.store, job_id):
        log.info("match job succeeded", extra={"job_id": job_id, "project_id": pid})
        jobstate.release_followers(ctx.store, ctx.queue, job_id)
    else:  # a redelivered step whose pair was done hands out one too: the window only grows by it
        _next_pairs(ctx, job_id)
    return "done"


@contextmanager
def _readable(ctx: StepContext, pid: str, db_path: Path) -> Iterator[Any]:
    """The project's COLMAP database for reading beside its writers: read without the writer lock
    (SQLite's WAL mode lets a reader see the last commit while a writer works), opened and closed
    under it (opening creates COLMAP's tables where missing, and the last connection to close
    checkpoints the WAL: both need the database to themselves, and SQLite answers "locked" at
    once rather than wait)."""
    from geomatch.sfm.colmapdb import ColmapDatabase

    with ctx.locks.project(pid):
        db = ColmapDatabase(db_path)
    try:
        yield db
    finally:
        with ctx.locks.project(pid):
            db.close()


@contextmanager
def _writable(ctx: StepContext, job_id: str, pid: str, db_path: Path) -> Iterator[Any]:
    """The project's COLMAP database under its writer lock, or None when the job was cancelled
    while its pair was matched (nothing is written then)."""
    from geomatch.sfm.colmapdb import ColmapDatabase

    with ctx.locks.project(pid):
        if not jobstate.is_active(ctx.store, job_id):
            yield None
            return
        ctx.storage.check_space(1 << 16)  # test hook (GEOMATCH_TEST_FILL_LIMIT); no-op otherwise
        with ColmapDatabase(db_path) as db:
            yield db


def _image_id(db: Any, name: str) -> int:
    image_id = db.image_id(name)
    if image_id is None:
        raise PermanentError(f"image {name!r} is not in the COLMAP database")
    return int(image_id)


# -- reconstruct jobs ---------------------------------------------------------------------------
def reconstruct(ctx: StepContext, job_id: str) -> str:
    """The project mapped as ``geomatch run`` maps it (geomatch.pipeline.reconstruction), from a
    snapshot of its database and the plan its match job kept, into a fresh folder swapped in whole."""
    from geomatch.pipeline.orthomap import add_map
    from geomatch.pipeline.outputs import finish
    from geomatch.pipeline.plan import Plan
    from geomatch.pipeline.project import ProjectImages
    from geomatch.pipeline.reconstruction import map_project, mapping_settings
    from geomatch.sfm.colmapdb import ColmapDatabase

    job = jobstate.claim(ctx.store, job_id)
    if job is None:
        return "skipped"
    pid = job.project_id
    db_path, plan_path = ctx.storage.database_path(pid), ctx.storage.plan_path(pid)
    if not db_path.is_file():
        raise PermanentError("the project has no COLMAP database: run a match job first")
    runtime.release()
    for name in ctx.storage.remove_stale_work(pid):  # left by attempts that died (SIGKILL)
        log.info("removed stale work folder %s", name, extra={"job_id": job_id, "project_id": pid})
    with ctx.storage.work(pid, f"reconstruct-{job_id}") as work:
        snapshot = work / "database.db"
        with ctx.locks.project(pid):  # a consistent copy; matching may go on while we map
            snapshot_sqlite(db_path, snapshot)
            if not plan_path.is_file():  # matched by a version that kept no plan
                raise PermanentError("the project has no plan: run a match job first (it keeps one)")
            plan = Plan.read(plan_path)
        image_dir = ctx.storage.images_dir(pid)
        with ColmapDatabase(snapshot) as db:
            names = [n for n in db.image_names() if (image_dir / n).is_file()]
        images = ProjectImages.read(image_dir, names)
        settings = mapping_settings(runtime.job_options(job.options), plan)
        out = work / "model"
        options = runtime.job_options(job.options)
        summary = map_project(
            snapshot, images, plan, out, settings, _control_points(ctx, job), {"job_id": job_id}
        )
        root, folder = ctx.storage.root, ctx.storage.project_dir(pid)
        summary = add_map(
            out,
            summary,
            image_dir,
            options["ortho"],
            options["ortho_gsd"],
            lambda e: redact.client_message(e, root, folder),
        )
        summary = finish(out, summary, archive=True)
        g = summary.get("gcp")
        if g is not None:
            fit = f"RMSE 3D control {g.get('control_rmse_3d_m')} m, check {g.get('check_rmse_3d_m')} m"
            log.info("GCPs: %s", g.get("error") or fit, extra={"job_id": job_id, "project_id": pid})
        # the result is stored first and the model swapped in only once it is: a result the store
        # refused (a number it cannot hold) once failed the job after its model had replaced the
        # good one. The job succeeds after the swap: no client reads it succeeded with the old model
        if not jobstate.store_result(ctx.store, job_id, summary):
            return "cancelled"
        ctx.storage.replace_dir(out, ctx.storage.model_dir(pid))
    jobstate.succeed(ctx.store, job_id, summary)
    log.info(
        "reconstructed: %s/%s images registered, %s points",
        summary.get("registered"),
        summary.get("images"),
        summary.get("points3D"),
        extra={"job_id": job_id, "project_id": pid},
    )
    jobstate.release_followers(ctx.store, ctx.queue, job_id)
    return "done"


def _control_points(ctx: StepContext, job: Job) -> Any:
    """The project's ground control points (``Storage.gcp_path``), held out at the job's check
    points; None when it has none. A failed fit is told without the server's paths."""
    from geomatch.pipeline.reconstruction import ControlPoints

    pid = job.project_id
    try:
        text = ctx.storage.gcp_path(pid).read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    root, folder = ctx.storage.root, ctx.storage.project_dir(pid)
    return ControlPoints(
        text, job.options.get("checkpoints") or 0, lambda e: redact.client_message(e, root, folder)
    )


# -- failures -----------------------------------------------------------------------------------
def on_failure(ctx: StepContext, step: str, args: tuple[Any, ...], exc: BaseException) -> None:
    """A step gave up (permanent error or retries exhausted): its job fails with the reason."""
    if step == RENDER_PAIR or not args:
        return
    job_id = str(args[0])
    where = f"pair {args[1]}" if step == MATCH_PAIR and len(args) > 1 else step.split(".")[-1]
    # the one place a job's error is written from a worker: clients read it, so no server paths,
    # no SQL and no driver's text (redact.client_message)
    reason = redact.client_message(exc, ctx.storage.root, _project_dir(ctx, job_id))
    if jobstate.fail(ctx.store, job_id, f"{where}: {reason}"):
        log.error("job failed in %s: %s", where, exc, extra={"job_id": job_id})
        jobstate.release_followers(ctx.store, ctx.queue, job_id)
    if step == LOCALIZE:
        try:
            drop_photos(ctx, job_id)
        except Exception as e:  # the store may be what failed the step
            log.warning("could not remove the photos of job %s (%s)", job_id, e)


def _project_dir(ctx: StepContext, job_id: str) -> Path | None:
    """The failed job's project folder, for its error's relative names; None when the store
    cannot say (the root's prefix still goes)."""
    try:
        job = jobstate.get(ctx.store, job_id)
    except Exception as e:  # the store may be what failed the step: the error is still recorded
        log.warning("no project folder for job %s's error (%s)", job_id, e)
        return None
    return ctx.storage.project_dir(job.project_id) if job is not None else None
