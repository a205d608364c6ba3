"""A survey's quarter turns: each aerial photo's turn into one frame for the project, decided
once per image from cheap probes against its neighbours, so that its pairs are matched unprobed."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from ..imagefolder import Images
from ..matching.probes import TURN_SURE, turn_scores
from ..matching.rotation import PROBE_MARGIN, quarter_turn
from ..matching.turnhint import HINT_MIN_INLIERS, TurnHint
from .pair_sources import Pair

log = logging.getLogger(__name__)


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

    def probe(known: str, known_turn: int, n: str, first: int) -> list[int]:
        return turn_scores(score, quarter_turn(images[known], known_turn), images[n], first, sure)

    return _grow(planned, probe, images, enu, progress, sure, hint)


def likely_turns(
    planned: Sequence[Pair],
    images: Images,
    enu: Mapping[str, np.ndarray],
    hint: Callable[[str, np.ndarray, str, np.ndarray], TurnHint] | None = None,
) -> dict[str, int]:
    """The turns :func:`image_turns` gives when each photo scores sure at the first turn it is
    scored at (the hinted one, else its partner's), without a network: the turn whose features
    each photo's scoring will most likely read, so that they can be extracted ahead, in parallel
    (a queued plan's per-photo steps). The order of the probes and the hints are image_turns' own;
    a guess that is wrong costs its extraction, never the plan (image_turns still decides)."""

    def probe(known: str, known_turn: int, n: str, first: int) -> list[int]:
        counts = [0, 0, 0, 0]
        counts[first] = TURN_SURE
        return counts

    return _grow(planned, probe, images, enu, False, TURN_SURE, hint)


def _grow(
    planned: Sequence[Pair],
    probe: Callable[[str, int, str, int], list[int]],
    images: Images,
    enu: Mapping[str, np.ndarray],
    progress: bool,
    sure: int,
    hint: Callable[[str, np.ndarray, str, np.ndarray], TurnHint] | None,
) -> dict[str, int]:
    """The frame grown from the root as image_turns describes; ``probe(known, its turn, image,
    turn first)``: the image's scores at the four turns against its decided partner."""
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
        counts = probe(known, turns[known], n, first)
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
