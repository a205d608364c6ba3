"""Prepare a project for matching: read its photos (metadata, GPS fixes), decide which are aerial,
plan its pairs, and register its images (with their pose priors) in its COLMAP database. Both
runners (``geomatch run`` and a match job's plan step) do exactly this before any pair is matched.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

from ..geo import gps
from ..imagefolder import Images
from ..imageio import WORKING_SIDE
from ..matching.matcher import Matcher
from ..options import plan_needs_matcher
from ..sfm.colmapdb import ColmapDatabase
from . import database
from .aerial import aerial_set
from .plan import Hint, Plan, plan, plan_in_words
from .project import PlanRequest, ProjectImages


def frames(folder: Path, budget_mb: float) -> Images:
    """The project's decoded photos as the matcher reads them: at most the working size
    (imageio.WORKING_SIDE; matches are written in the photos' own pixels) within ``budget_mb``."""
    return Images(folder, budget_mb, WORKING_SIDE)


def plan_project(
    images: ProjectImages,
    captures: Mapping[str, str],
    request: PlanRequest,
    matcher: Callable[[], Matcher],
    decoded: Images,
    progress: bool = False,
    hint: Hint | None = None,
) -> Plan:
    """The project's plan: its aerial images (``captures``: aerial | ground | auto per image,
    aerial.aerial_set), its pairs (plan.plan) and the plan in words. ``matcher`` is called only
    when the plan reads the images' features (retrieval's global descriptors, a survey's quarter
    turns), so a plan that does not loads no network. ``hint``: as plan.plan's."""
    enu = images.fixes.enu if images.fixes is not None else None
    aerial = aerial_set(captures, images.metas, enu)
    survey = bool(images.names) and aerial >= set(images.names)
    explicit = request.pairs_list is not None
    needs = (not explicit and plan_needs_matcher(request.spec)) or survey
    pairs = plan(images, aerial, request, matcher() if needs else None, decoded, progress, hint)
    words = "explicit list" if explicit else plan_in_words(request.spec, images)
    return Plan(pairs, sorted(aerial), words, survey)


def register(path: Path, images: ProjectImages, share_camera: bool | None) -> dict[str, int]:
    """Every image in the project's COLMAP database at ``path`` (a no-op for those there), with
    its GPS fix as a pose prior; their ids by name."""
    with ColmapDatabase(path) as db:
        ids = database.register(db, images.names, images.metas, share_camera)
    if images.fixes is not None:
        gps.write_pose_priors(path, ids, images.fixes)
    return ids
