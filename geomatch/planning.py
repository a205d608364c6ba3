"""Which pairs of a project are matched, and how: the plan's parts (``options.PAIR_KINDS``, each
kind's planner in :data:`PLANNERS`), which pairs are tiled, their order (all pairs of one aerial
image together, for the feature caches), and for a survey each aerial photo's quarter turn, decided
once per image (:func:`image_turns`). Every caller plans through :func:`plan`: ``geomatch run``,
a worker's plan step and the service's two-image match.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .geo import gps
from .geo.gps import GpsFixes
from .imagefolder import Images
from .matching.matcher import Matcher
from .matching.probes import TURN_SURE, TURN_SURE_SEED, turn_scores
from .matching.rotation import PROBE_MARGIN, quarter_turn, turn_score
from .matching.turnhint import HINT_MIN_INLIERS, SiftHints, TurnHint
from .matching.variants import for_pair
from .metadata import ImageMeta
from .options import DEFAULTS
from .sfm import pairs as pairing
from .sfm.pairs import Pair
from .sfm.retrieval import vlad

log = logging.getLogger(__name__)


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
    image_dir: Path,
    names: Sequence[str],
    aerial: set[str],
    spec: str = DEFAULTS["pairs"],
    pairs_list: Sequence[Sequence[str]] | None = None,
    tiling: str = DEFAULTS["tiling"],
    matcher: Matcher | None = None,
    images: Images | None = None,
    progress: bool = False,
    fixes: GpsFixes | None = None,
    metas: Mapping[str, ImageMeta] | None = None,
) -> list[Pair]:
    """The pairs to match (``pairs_list``, else ``spec``, a union of its parts), tiled where
    ``tiling`` says, in a cache-friendly order: all pairs of one aerial image (its five crops)
    together. With ``matcher`` the plain pairs with an aerial side get their quarter turn once per
    image (:func:`image_turns`), else each pair probes its own. ``retrieval:K`` needs ``matcher``
    (global descriptors come from its sparse features); ``gps:K`` pairs by the ``fixes`` (images
    without one: see pairs.gps_neighbours), by look point, and by shared ground where ``metas``
    give both images a footprint (gps.plan_points, gps.footprints); ``auto`` is exhaustive or
    ``gps:K`` by the project's size and fixes (pairs.auto_pairs)."""
    # not ``images or ...``: an Images with nothing decoded yet has length 0, and a fresh
    # Images(image_dir) would read the photos at their stored size, not at the caller's working size
    folder = images if images is not None else Images(image_dir)
    gps_enu: Mapping[str, np.ndarray] = {}
    footprints: Mapping[str, np.ndarray] | None = None
    if fixes is not None:
        gps_enu = gps.plan_points(fixes, metas) if metas is not None else fixes.enu
        footprints = gps.footprints(fixes, metas) if metas is not None else None
    names = list(names)
    if pairs_list is not None:
        raw = pairing.explicit(pairs_list, names)
    else:
        parts = pairing.parse_plan(spec)
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
    planned = pairing.finalize(raw, aerial, tiling)
    # a survey (every image aerial) gets its turns once per image and its pairs the guided matcher;
    # a project with ground images keeps the per-pair probe and geo (matching.variants.for_pair)
    if matcher is not None and aerial >= set(names) and any(p.rotate and not p.tiled for p in planned):
        # ranked as a plain pair of two aerial photos is first matched (auto: the guided seed)
        probe = for_pair(matcher, tiled=False, aerial_project=True, aerial_pair=True)
        guided = probe.config.light_first and probe.config.guided_keypoints > 0
        turns = image_turns(
            planned,
            partial(turn_score, probe),
            folder,
            gps_enu,
            progress,
            sure=TURN_SURE_SEED if guided else TURN_SURE,
            hint=SiftHints().hint,
        )
        planned = pairing.with_turns(planned, turns)
    return sorted(planned, key=lambda p: (not p.tiled, p.name0 if p.aerial_first else p.name1, p.key))


# an image's turn is decided on its first probed pair when a turn scores sure (TURN_SURE, or
# TURN_SURE_SEED with the guided matcher: geomatch.matching.probes), else when TURN_VOTES pairs
# agree on a turn with PROBE_MARGIN times the runner-up's score; at most TURN_PROBES of its pairs to
# images already decided are probed
TURN_VOTES = 2
TURN_PROBES = 3
TURN_MIN_MATCHES = 20  # fewer probe matches on the best turn: the pair does not vote


def image_turns(
    planned: Sequence[Pair],
    score: Callable[[np.ndarray, np.ndarray], int],
    images: Images,
    enu: Mapping[str, np.ndarray],
    progress: bool = False,
    sure: int = TURN_SURE,
    hint: Callable[[str, np.ndarray, str, np.ndarray], TurnHint] | None = None,
) -> dict[str, int]:
    """Each aerial photo's quarter turn (np.rot90) into one frame for the project, decided once
    per image instead of once per pair: the image with the most planned partners is the frame;
    every other one is scored (``score``: matching.rotation.turn_score) at the four turns against
    its nearest partners already decided (the photo taken before or after it, else by GPS distance). A pair
    then matches with each image at its own turn (one turned copy per image, so features once),
    unprobed. An image whose probes do not settle keeps the per-pair probe on its pairs. With
    ``hint`` (SiftHints.hint: rotation-invariant, one cheap extraction per photo) a pair the hint
    finds no overlap in is not probed and costs the image none of its probes, and the turn the hint
    reads from the pair is scored first: the score still decides.

    Why not the photos' own headings (DJI XMP gimbal yaw, or the direction of travel between
    GPS fixes): on real surveys they do not say how the pixels are turned. A return line flown
    180 deg round can hold photos that are not turned at all, and a camera that yaws against the
    track turns some pairs by a half turn and others by a quarter (docs/benchmarks.md)."""
    partners: dict[str, list[Pair]] = {}
    for p in planned:
        if p.rotate and not p.tiled:
            partners.setdefault(p.name0, []).append(p)
            partners.setdefault(p.name1, []).append(p)
    if not partners:
        return {}

    # file names (a camera's counter) are the capture order: a photo and the next one taken
    # overlap most and share a turn along a flight line, more surely than GPS neighbours (a
    # compact camera's fixes are tens of metres off, and the nearest fix can be on the next line)
    rank = {n: i for i, n in enumerate(sorted(partners))}

    def distance(p: Pair) -> tuple[bool, float]:
        d = float("inf")
        if p.name0 in enu and p.name1 in enu:
            d = float(np.linalg.norm(np.asarray(enu[p.name0])[:2] - np.asarray(enu[p.name1])[:2]))
        return (abs(rank[p.name0] - rank[p.name1]) != 1, d)

    # once per pair, not once per pair per decision: the loop below looks at every candidate
    # pair each time it decides an image
    order = {p.key: distance(p) for ps in partners.values() for p in ps}

    root = max(sorted(partners), key=lambda n: len(partners[n]))
    turns = {root: 0}
    tried: set[tuple[str, str]] = set()
    probed: dict[str, int] = {}  # pairs probed per image: at most TURN_PROBES
    votes: dict[str, dict[int, int]] = {n: {} for n in partners}
    bar = tqdm(total=len(partners) - 1, desc="quarter turns", disable=not progress, leave=False)
    while True:
        # the undecided image taken next to a decided one, else the nearest, goes next against
        # that partner: the frame grows outwards from the root through the pairs most likely to
        # overlap, so the partner's own turn is usually the image's and one turned copy is scored
        options = [
            (order[p.key], p.key, n, p)
            for n in partners
            if n not in turns and probed.get(n, 0) < TURN_PROBES
            for p in partners[n]
            if p.key not in tried and (p.name1 if p.name0 == n else p.name0) in turns
        ]
        if not options:
            break
        _, _, n, p = min(options)
        tried.add(p.key)
        known = p.name1 if p.name0 == n else p.name0
        first = turns[known]
        if hint is not None:
            h = hint(known, images[known], n, images[n])
            log.debug("turn hint %s -> %s: %s", known, n, h)
            if h.inliers >= HINT_MIN_INLIERS:
                first = (turns[known] + h.turn) % 4
            elif abs(rank[known] - rank[n]) != 1:
                continue  # the two share nothing: four turned copies would score noise
            # photos taken one after the other overlap on a survey whatever SIFT finds: over
            # low-texture fields (a near-infrared camera over crops) its similarity fits a handful
            # where the network's seed fits a thousand, and skipping them left a fixed-wing
            # flight's turns undecided (each pair then probed its own, four turns each)
        probed[n] = probed.get(n, 0) + 1
        # scored in the frame: the partner as it will be matched (its features are reused), the
        # image first at the hinted turn or else the partner's, then the half turn of a line flown
        # back; a turn with a sure score is the answer without trying the rest
        counts = turn_scores(score, quarter_turn(images[known], turns[known]), images[n], first, sure)
        best, runner_up = sorted(counts, reverse=True)[:2]
        log.debug("turn probe %s -> %s: %s", known, n, counts)
        if best < TURN_MIN_MATCHES or (best < sure and best < PROBE_MARGIN * max(runner_up, 1)):
            continue
        t = int(np.argmax(counts))
        votes[n][t] = votes[n].get(t, 0) + 1
        if best >= sure or votes[n][t] >= TURN_VOTES:
            turns[n] = t
            bar.update()
    bar.close()
    return turns


def plan_in_words(
    spec: str, names: Sequence[str], fixes: GpsFixes | None, metas: Mapping[str, ImageMeta] | None
) -> str:
    """The plan :func:`plan` makes of ``spec``, in words: ``auto``'s choice (pairs.auto_pairs)."""
    if spec.strip() != "auto":
        return spec.strip()
    enu = gps.plan_points(fixes, metas) if fixes is not None and metas is not None else {}
    footprints = gps.footprints(fixes, metas) if fixes is not None and metas is not None else None
    return pairing.auto_pairs(list(names), enu, footprints)[1]


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
