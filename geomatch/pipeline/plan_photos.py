"""The plan's work per photo, apart from the plan: which features a project's plan will read of each
photo (a survey's turn scores, retrieval's global descriptors) and their extraction. A queued
runner extracts them in steps spread over its workers, into the feature store every worker reads
(geomatch.features.store), then plans in one step (prepare.plan_project, unchanged), which finds
them there, and the SIFT hints the guess of a survey's turns made (:attr:`PhotoWork.hints`). The
plan decides from the features and hints alone, wherever they were made, so it is the plan one
step would have made; ``geomatch run`` plans in one go and never calls this.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..imagefolder import Images
from ..matching.matcher import Matcher
from ..matching.rotation import quarter_turn, score_features
from ..matching.turnhint import SiftHints, TurnHint
from ..options import plan_needs_matcher
from .aerial import aerial_set
from .plan import plan, turn_probe
from .project import PlanRequest, ProjectImages
from .turns import likely_turns


@dataclass(frozen=True)
class PhotoWork:
    """What the plan will read of each photo: ``turns``, a survey's, the quarter turn at which each
    photo's turn will likely be scored (None: the plan scores no turns); ``sparse``: retrieval's
    upright sparse features of every photo."""

    turns: Mapping[str, int] | None
    sparse: bool
    hints: Mapping[tuple[str, str], TurnHint] = field(default_factory=dict)  # those the guess made

    def hints_json(self) -> list[list[Any]]:
        """:attr:`hints` as JSON keeps them (:func:`hints_from_json`)."""
        return [[a, b, h.turn, h.inliers] for (a, b), h in sorted(self.hints.items())]


def hints_from_json(rows: Sequence[Sequence[Any]]) -> dict[tuple[str, str], TurnHint]:
    return {(str(a), str(b)): TurnHint(int(t), int(n)) for a, b, t, n in rows}


def photo_work(
    images: ProjectImages, captures: Mapping[str, str], request: PlanRequest, decoded: Images
) -> PhotoWork | None:
    """The features ``prepare.plan_project`` will read of each photo, None when it reads none. A
    survey's turns are guessed as turns.likely_turns guesses them (SIFT hints only: cheap beside
    the network's features); with retrieval the pairs are not known before the descriptors, so its
    photos are guessed upright."""
    enu = images.fixes.enu if images.fixes is not None else None
    aerial = aerial_set(captures, images.metas, enu)
    survey = bool(images.names) and aerial >= set(images.names)
    sparse = request.pairs_list is None and plan_needs_matcher(request.spec)
    if not survey and not sparse:
        return None
    if not survey:
        return PhotoWork(None, sparse)
    if sparse:
        return PhotoWork(dict.fromkeys(images.names, 0), sparse)
    # the pairs plan.plan turns: planned without a matcher, they are the same, unturned
    pairs = plan(images, aerial, request, None, decoded)
    points = images.plan_points()
    sift, hints = SiftHints(), {}

    def hint(name0: str, image0: np.ndarray, name1: str, image1: np.ndarray) -> TurnHint:
        hints[name0, name1] = h = sift.hint(name0, image0, name1, image1)
        return h

    guessed = likely_turns(pairs, decoded, points, hint)
    return PhotoWork({n: guessed.get(n, 0) for n in images.names}, sparse, hints)


def extract(matcher: Matcher, image: np.ndarray, turn: int | None, sparse: bool) -> None:
    """The features of one photo the plan will read (:func:`photo_work`): at ``turn`` those its
    turn is scored with (None: no turn), with ``sparse`` the upright ones of its global descriptor
    (plan.global_descriptors)."""
    if turn is not None:
        score_features(turn_probe(matcher)[0], quarter_turn(image, turn))
    if sparse:
        matcher.derive(method="sparse").features(image)
