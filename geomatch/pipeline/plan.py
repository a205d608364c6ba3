"""Which pairs of a project are matched, and how: the plan's parts (``options.PAIR_KINDS``, each
kind's planner in :data:`PLANNERS`, the pairings in pair_sources.py), which pairs are tiled, their
order (all pairs of one aerial image together, for the feature caches), and for a survey each
aerial photo's quarter turn, decided once per image (turns.py). Every caller plans through
:func:`plan`: ``geomatch run``, a worker's plan step and the service's two-image match; a
project's plan is kept as a :class:`Plan`, which also says what the mapping needs of it.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..imagefolder import Images
from ..matching.matcher import Matcher
from ..matching.probes import TURN_SURE, TURN_SURE_SEED
from ..matching.rotation import turn_score
from ..matching.turnhint import SiftHints, TurnHint
from ..matching.variants import for_pair
from ..options import parse_plan
from . import pair_sources as pairing
from .pair_sources import Pair
from .project import PlanRequest, ProjectImages
from .retrieval import vlad
from .turns import image_turns

# a pair's turn hint: (name0, image0, name1, image1) -> TurnHint (matching.turnhint)
Hint = Callable[[str, np.ndarray, str, np.ndarray], TurnHint]


@dataclass(frozen=True)
class PlanInputs:
    """What the planners of a plan's parts read (one spec's parts share it)."""

    names: list[str]
    kinds: set[str]  # the plan's kinds: a union's parts may leave an image to another part
    aerial: set[str]
    gps_enu: Mapping[str, np.ndarray]
    footprints: Mapping[str, np.ndarray] | None
    matcher: Matcher | None
    images: Images
    progress: bool


def _gps_planner(p: PlanInputs, k: int) -> list[tuple[str, str]]:
    unlocated_all = "retrieval" not in p.kinds  # else retrieval pairs the images without a fix
    return pairing.gps_neighbours(p.names, p.gps_enu, k, unlocated_all, footprints=p.footprints)


def _retrieval_planner(p: PlanInputs, k: int) -> list[tuple[str, str]]:
    assert p.matcher is not None  # options.PairKind.needs_matcher: the caller built one
    descriptors = global_descriptors(p.matcher, p.images, p.names, p.progress)
    return pairing.nearest_neighbours(descriptors, p.names, k) + pairing.cross_view(p.names, p.aerial)


# the planner of each kind of options.PAIR_KINDS that plans by itself (``auto`` chooses between
# the others: pairs.auto_pairs); tests/test_pair_kinds.py holds the two tables together
PLANNERS: dict[str, Callable[[PlanInputs, int], list[tuple[str, str]]]] = {
    "exhaustive": lambda p, k: pairing.exhaustive(p.names),
    "sequential": lambda p, k: pairing.sequential(p.names, k),
    "retrieval": _retrieval_planner,
    "gps": _gps_planner,
}


def plan(
    images: ProjectImages,
    aerial: set[str],
    request: PlanRequest,
    matcher: Matcher | None = None,
    decoded: Images | None = None,
    progress: bool = False,
    hint: Hint | None = None,
) -> list[Pair]:
    """The pairs to match (``request.pairs_list``, else ``request.spec``, a union of its parts),
    tiled where ``request.tiling`` says, in a cache-friendly order: all pairs of one aerial image
    (its five crops) together. With ``matcher`` the plain pairs with an aerial side get their
    quarter turn once per image (:func:`image_turns`), else each pair probes its own.
    ``retrieval:K`` needs ``matcher`` (global descriptors come from its sparse features); ``gps:K``
    pairs by the images' fixes (images without one: see pairs.gps_neighbours), by look point, and
    by shared ground where the metadata give both images a footprint (gps.plan_points,
    gps.footprints); ``auto`` is exhaustive or ``gps:K`` by the project's size and fixes
    (pairs.auto_pairs). ``decoded``: the photos as the matcher reads them (the working size).
    ``hint``: the turns' SIFT hints (SiftHints.hint by default; a queued plan passes those its
    earlier step made)."""
    # not ``decoded or ...``: an Images with nothing decoded yet has length 0, and a fresh
    # Images(folder) would read the photos at their stored size, not at the caller's working size
    folder = decoded if decoded is not None else Images(images.folder)
    gps_enu, footprints = images.plan_points(), images.footprints()
    names = list(images.names)
    spec, pairs_list, tiling = request.spec, request.pairs_list, request.tiling
    if pairs_list is not None:
        raw = pairing.explicit(pairs_list, names)
    else:
        parts = parse_plan(spec)
        raw = []
        if parts == [("auto", 0)]:
            raw, _ = pairing.auto_pairs(names, gps_enu, footprints)
            parts = []
        inputs = PlanInputs(
            names,
            {kind for kind, _ in parts},
            aerial,
            gps_enu,
            footprints,
            matcher,
            folder,
            progress,
        )
        for kind, k in parts:
            raw += PLANNERS[kind](inputs, k)
    survey = bool(names) and aerial >= set(names)
    planned = pairing.finalize(raw, aerial, tiling, survey)
    # a survey (every image aerial) gets its turns once per image and its pairs the guided matcher;
    # a project with ground images keeps the per-pair probe and geo (matching.variants.for_pair)
    if matcher is not None and survey and any(p.rotate and not p.tiled for p in planned):
        probe, sure = turn_probe(matcher)
        score = partial(turn_score, probe)
        hint = hint or SiftHints().hint
        turns = image_turns(planned, score, folder, gps_enu, progress, sure=sure, hint=hint)
        planned = pairing.with_turns(planned, turns)
    return sorted(planned, key=lambda p: (not p.tiled, p.name0 if p.aerial_first else p.name1, p.key))


def turn_probe(matcher: Matcher) -> tuple[Matcher, int]:
    """The matcher a survey's turns are scored with, and the score that is sure: ranked as a plain
    pair of two aerial photos is first matched (auto: the guided seed)."""
    probe = for_pair(matcher, tiled=False, aerial_project=True, aerial_pair=True)
    guided = probe.config.light_first and probe.config.guided_keypoints > 0
    return probe, TURN_SURE_SEED if guided else TURN_SURE


def plan_in_words(spec: str, images: ProjectImages) -> str:
    """The plan :func:`plan` makes of ``spec``, in words: ``auto``'s choice (pairs.auto_pairs)."""
    if spec.strip() != "auto":
        return spec.strip()
    return pairing.auto_pairs(list(images.names), images.plan_points(), images.footprints())[1]


def global_descriptors(
    matcher: Matcher, images: Images, names: Sequence[str], progress: bool = True
) -> np.ndarray:
    sparse = matcher.derive(method="sparse")
    local = []
    for n in tqdm(names, desc="retrieval", disable=not progress, leave=False):
        feats = sparse.features(images[n])[sparse.config.sparse].sparse
        assert feats is not None
        local.append(feats.descriptors.float().cpu().numpy())
    return vlad(local)


@dataclass(frozen=True)
class Plan:
    """A project's plan as the stages after it read it: its pairs as planned (tiled, turned), which
    images are aerial, the plan in words, and what the mapping needs of it (:attr:`tiled`,
    :attr:`survey`). Kept as ``plan.json`` beside the project's database, so the service's
    reconstruct job maps what its match job planned, as ``geomatch run`` maps what it planned."""

    pairs: list[Pair]
    aerial: list[str]  # sorted
    in_words: str
    survey: bool  # every image aerial: the guided matcher's pairs, the survey's track refinement

    @property
    def tiled(self) -> bool:
        """Whether the project has tiled aerial x ground pairs: its mapping then keeps two-view
        tracks, a lower PnP floor and the leftover passes (geomatch.sfm.mapping)."""
        return any(p.tiled for p in self.pairs)

    @property
    def tiled_images(self) -> tuple[str, ...]:
        """The aerial sides of the tiled pairs, sorted: matched against ground photos through crops,
        so their keypoints there are not those of their other pairs, and two right models can
        share such an image and no point (the only join of models that may rest on one image:
        geomatch.sfm.modeljoin)."""
        return tuple(sorted({p.name0 if p.aerial_first else p.name1 for p in self.pairs if p.tiled}))

    def summary_fields(self) -> dict[str, Any]:
        """What summary.json says of the plan."""
        return {
            "pairs": len(self.pairs),
            "pair_plan": self.in_words,
            "tiled_pairs": sum(p.tiled for p in self.pairs),
            "aerial": self.aerial,
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "aerial": self.aerial,
            "in_words": self.in_words,
            "survey": self.survey,
            "pairs": [
                {
                    "name0": p.name0,
                    "name1": p.name1,
                    "tiled": p.tiled,
                    "aerial_first": p.aerial_first,
                    "rotate": p.rotate,
                    "turns": list(p.turns) if p.turns is not None else None,
                }
                for p in self.pairs
            ],
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Plan:
        pairs = [
            Pair(
                str(p["name0"]),
                str(p["name1"]),
                bool(p["tiled"]),
                bool(p["aerial_first"]),
                bool(p["rotate"]),
                (int(p["turns"][0]), int(p["turns"][1])) if p["turns"] is not None else None,
                aerial_project=bool(data["aerial"]),
                survey=bool(data["survey"]),
            )
            for p in data["pairs"]
        ]
        return cls(pairs, [str(n) for n in data["aerial"]], str(data["in_words"]), bool(data["survey"]))

    def write(self, path: Path) -> None:
        """``path`` (plan.json) replaced whole: a reader never sees half a plan."""
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        tmp.replace(path)

    @classmethod
    def read(cls, path: Path) -> Plan:
        return cls.from_json(json.loads(path.read_text()))
