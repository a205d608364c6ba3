"""The interactive steps, whose answers go back to a waiting caller: gRPC MatchPair's, two images
that belong to no project matched (:func:`match_two`), and a project's matched pair drawn
(:func:`render_pair`).

For MatchPair the API stages both images (validated like uploads) in ``GEOMATCH_HOME/tmp/<work>/``
as ``0`` and ``1``; the step matches them with the worker's cached networks (``runtime.matcher``: the same
matcher, feature cache and device as job steps) and writes ``result.npz`` beside them. Paths travel
as the folder's name, not as absolute paths, because a worker on another host may mount the storage
root elsewhere. Nothing is retried or redelivered: the caller waits with a deadline, and work
found past it is dropped (between stages too, so an abandoned pair costs at most one stage).

It is in the static step table (``workers.steps``) like every other step: the embedded runner
calls it, and ``workers.tasks`` registers it for ``geomatch worker`` as a one-shot task whose
result is stored (job steps ignore theirs).
"""

from __future__ import annotations

import logging
import re
import time
from typing import Any

from . import redact, runtime
from .context import StepContext

log = logging.getLogger("geomatch.workers")
_WORK = re.compile(r"pair-[0-9a-f]{32}")


class DeadlinePassed(Exception):
    pass


def match_two(
    ctx: StepContext, work: str, captures: list[str], options: dict[str, Any], deadline: float
) -> dict[str, Any]:
    """``{"file": "result.npz", "matches": N, "timings": {...}}``, or ``{"error": reason}``."""
    if not _WORK.fullmatch(work):
        return {"error": f"bad work folder {work!r}"}
    folder = ctx.storage.tmp_dir / work
    try:
        return _match(ctx, folder, captures, options, deadline)
    except DeadlinePassed:
        return {"error": "the caller's deadline passed"}
    except FileNotFoundError:  # the caller gave up and removed the folder
        return {"error": "the images are gone (the caller gave up)"}
    except Exception as e:  # answered, not raised: the caller maps it, nothing is retried
        log.exception("match_two %s failed", work)
        return {"error": redact.without_paths(f"{type(e).__name__}: {e}", ctx.storage.root)}


def _match(
    ctx: StepContext, folder: Any, captures: list[str], options: dict[str, Any], deadline: float
) -> dict[str, Any]:
    import numpy as np

    from geomatch.imageio import read_image
    from geomatch.metadata import read_metadata
    from geomatch.pipeline import match_pairs
    from geomatch.pipeline.aerial import aerial_set
    from geomatch.pipeline.plan import plan
    from geomatch.pipeline.project import PlanRequest, ProjectImages

    def check() -> None:
        if time.time() > deadline:
            raise DeadlinePassed

    t0 = time.perf_counter()
    check()
    options = runtime.job_options(options)
    names = ["0", "1"]
    taken = dict(zip(names, captures, strict=True))
    metas = {n: read_metadata(folder / n) for n in names if taken[n] == "auto"}
    aerial = aerial_set(taken, metas)
    request = PlanRequest(pairs_list=[names], tiling=options["tiling"])
    pair = plan(ProjectImages(folder, names, metas, None), aerial, request)[0]
    a, b = read_image(folder / "0"), read_image(folder / "1")  # not runtime.image: these are read once
    matcher = runtime.matcher(ctx, options)
    t1 = time.perf_counter()
    timings = {"read": t1 - t0}
    for name, img in (("0", a), ("1", b)):  # features one image at a time: a deadline check between
        check()
        tiled_side = pair.tiled and (name == "0") == pair.aerial_first
        match_pairs.extract(matcher, img, full=not tiled_side, crops=tiled_side)
        timings[f"features{name}"] = time.perf_counter() - t1
        t1 = time.perf_counter()
    check()
    m = match_pairs.run_pair(matcher, pair, a, b).matches
    k0, k1, sc, F = m.keypoints0, m.keypoints1, m.scores, m.F
    timings["match"] = time.perf_counter() - t1
    out = folder / "result.npz"
    tmp = folder / "result.tmp.npz"
    np.savez(
        tmp,
        keypoints0=np.asarray(k0, np.float32).reshape(-1, 2),
        keypoints1=np.asarray(k1, np.float32).reshape(-1, 2),
        scores=np.asarray(sc, np.float32).reshape(-1),
        F=np.asarray(F, np.float64).reshape(3, 3),
        size0=np.array([a.shape[1], a.shape[0]]),
        size1=np.array([b.shape[1], b.shape[0]]),
        method=np.array(options["method"]),
        tiled=np.array(pair.tiled),
    )
    tmp.replace(out)
    timings["total"] = time.perf_counter() - t0
    log.info("match_two %s: %d matches, tiled=%s, %.2fs", folder.name, len(sc), pair.tiled, timings["total"])
    return {"file": out.name, "matches": len(sc), "timings": timings}


def render_pair(ctx: StepContext, project_id: str, name0: str, name1: str) -> dict[str, Any]:
    """Draw a matched pair from the COLMAP database: verified inliers red, other matches blue."""
    import numpy as np

    from geomatch.matching.matcher import MatchResult
    from geomatch.sfm.colmapdb import ColmapDatabase
    from geomatch.viz import save_matches

    db_path = ctx.storage.database_path(project_id)
    if not db_path.is_file():
        return {"error": "not_matched"}
    with ctx.locks.project(project_id), ColmapDatabase(db_path) as db:
        id0, id1 = db.image_id(name0), db.image_id(name1)
        if id0 is None or id1 is None or not db.has_pair(id0, id1):
            return {"error": "not_matched"}
        kp0, kp1 = db.keypoints(id0), db.keypoints(id1)
        m, inl = db.matches(id0, id1), db.inlier_matches(id0, id1)
    is_inlier = {(int(a), int(b)) for a, b in inl}
    scores = np.array([1.0 if (int(a), int(b)) in is_inlier else 0.0 for a, b in m], np.float32)
    a = runtime.image(ctx, ctx.storage.image_path(project_id, name0))
    b = runtime.image(ctx, ctx.storage.image_path(project_id, name1))
    result = MatchResult(
        keypoints0=kp0[m[:, 0]].astype(np.float32),
        keypoints1=kp1[m[:, 1]].astype(np.float32),
        scores=scores,
        F=np.zeros((3, 3)),
        method="stored",
        image_sizes=((a.shape[1], a.shape[0]), (b.shape[1], b.shape[0])),
    )
    pictures = ctx.storage.pictures_dir(project_id)
    pictures.mkdir(parents=True, exist_ok=True)
    path = ctx.storage.picture_path(project_id, name0, name1)
    tmp = path.with_suffix(f".{time.monotonic_ns()}.png")
    save_matches(tmp, a, b, result, caption=f"{len(inl)} verified (red) of {len(m)} matches")
    tmp.replace(path)
    return {"path": str(path), "matches": len(m), "inliers": len(inl)}
