"""The match step: one planned pair's images' features (:func:`extract`), the pair matched
(:func:`match`: tiled and turned as the plan says) and written into the project's COLMAP database
(:func:`run_pair`, through :func:`geomatch.pipeline.database.write`). ``geomatch run``, a
worker's pair step and the service's two-image match all go through these functions, so a pair is
matched the same way wherever it runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np

from ..imagefolder import PhotoScale
from ..matching.matcher import Matcher, MatchResult
from ..matching.probes import pair_turn, tiled_turn
from ..matching.rotation import points_back, quarter_turn
from ..matching.tiling import TiledMatches, five_crops, match_tiled
from ..matching.variants import for_pair
from ..sfm.colmapdb import ColmapDatabase, PairWrite
from .database import PairMatches, commit, prepare, write
from .pair_sources import Pair


def extract(matcher: Matcher, image: np.ndarray, full: bool = True, crops: bool = False) -> int:
    """Features of an image (and of its five tiling crops when it is the aerial side of a tiled
    pair); returns how many entries that was. With a ``StoredFeaturesMatcher``
    (geomatch.matching.stored) the image's land on disk for every later task. With
    ``tile_crops="probe"`` a crop gets its sparse features only, in memory (what the crop probe
    needs, and cheap): its dense maps, several times dearer in time and memory, are made by the
    pair step for the crops the probe chooses."""
    n = 0
    if full:
        matcher.features(image)
        n += 1
    if crops:
        # with the crop probe only the chosen crops get dense maps (in the pair step, which stores
        # them for the image's other partners); every crop needs its sparse features for the probe
        crop_matcher = matcher.derive(method="sparse") if matcher.config.tile_crops == "probe" else matcher
        h, w = image.shape[:2]
        for crop in five_crops(w, h):
            crop_matcher.features(crop.cut(image))
            n += 1
    return n


# how ``geomatch run`` matches a pair (:func:`match`'s signature): matcher, pair, image0, image1
MatchPair = Callable[[Matcher, Pair, np.ndarray, np.ndarray], PairMatches]


def pair_matcher(matcher: Matcher, pair: Pair) -> Matcher:
    """The matcher a planned pair is matched with: under ``auto`` the pair and what the plan
    recorded of its project decide the method (:func:`geomatch.matching.variants.for_pair`)."""
    # two aerial photos of a survey (every image aerial): the guided matcher, turned or not yet
    aerial_pair = pair.rotate and not pair.tiled and (pair.survey or pair.turns is not None)
    return for_pair(matcher, pair.tiled, pair.aerial_project, aerial_pair=aerial_pair)


def match(matcher: Matcher, pair: Pair, image0: np.ndarray, image1: np.ndarray) -> PairMatches:
    """One planned pair, tiled and turned as the plan says, by its :func:`pair_matcher`."""
    matcher = pair_matcher(matcher, pair)
    sizes = ((image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0]))
    k0, k1, scores, source, crops = _match_turned(matcher, pair, image0, image1)
    return PairMatches(k0, k1, scores, sizes, pair.tiled, source, crops)


def _match_turned(
    matcher: Matcher, pair: Pair, image0: np.ndarray, image1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, MatchResult | TiledMatches | None, int]:
    """(keypoints0, keypoints1, scores, source, aerial crops matched) of the pair; with
    ``pair.turns`` (a survey) each image is matched turned into the project's frame, else with
    ``pair.rotate`` the aerial side (image1 of an untiled pair) at its best quarter turn
    (geomatch.matching.rotation); keypoints are mapped back, and the source is dropped when
    anything was turned (its F is in the turned frames)."""
    if pair.tiled:
        aerial, other = (image0, image1) if pair.aerial_first else (image1, image0)
        turns, crops = tiled_turn(matcher, aerial, other, pair.rotate)
        t = match_tiled(
            matcher,
            quarter_turn(aerial, turns),
            other,
            pair.aerial_first,
            crops=crops,
            min_crop_matches=matcher.config.tile_crop_min_matches,
        )
        if not turns:
            return t.keypoints0, t.keypoints1, t.scores, t, len(crops)
        h, w = aerial.shape[:2]
        if pair.aerial_first:
            return points_back(t.keypoints0, turns, w, h), t.keypoints1, t.scores, None, len(crops)
        return t.keypoints0, points_back(t.keypoints1, turns, w, h), t.scores, None, len(crops)
    if pair.turns is not None:  # each image in the project's frame: one turned copy, features once
        t0, t1 = pair.turns
    else:
        t0, t1 = 0, (pair_turn(matcher, image0, image1) if pair.rotate else 0)
    r = matcher.match(quarter_turn(image0, t0), quarter_turn(image1, t1))
    if not (t0 or t1):
        return r.keypoints0, r.keypoints1, r.scores, r, 0
    (h0, w0), (h1, w1) = image0.shape[:2], image1.shape[:2]
    k0, k1 = points_back(r.keypoints0, t0, w0, h0), points_back(r.keypoints1, t1, w1, h1)
    return k0, k1, r.scores, None, 0


@dataclass(frozen=True)
class PairTarget:
    """Where a matched pair is written: ``open`` opens the COLMAP database for the write, under
    whatever locks its caller holds, and yields None when the pair must not be written any more
    (a worker's job cancelled while the pair was matched); the images' ids there; the snap radius
    in network pixels. ``read``, when given, opens the database without the writer's locks: the
    pair is snapped and verified there first and only committed under ``open``, so that several
    workers' verifications run at once and the lock is held for the transaction alone."""

    open: Callable[[], AbstractContextManager[ColmapDatabase | None]]
    id0: int
    id1: int
    radius: float
    read: Callable[[], AbstractContextManager[ColmapDatabase]] | None = None
    # images matched below their photos' size (imagefolder.to_photo): the matches are written in
    # the photos' own pixels, which the database and the mapper speak
    photos: tuple[PhotoScale | None, PhotoScale | None] = (None, None)


@dataclass
class PairRun:
    matches: PairMatches
    written: PairWrite | None  # None: no target, or its ``open`` refused the write
    match_s: float
    write_s: float


def run_pair(
    matcher: Matcher,
    pair: Pair,
    image0: np.ndarray,
    image1: np.ndarray,
    target: PairTarget | None = None,
) -> PairRun:
    """One planned pair matched (:func:`match`) and written into ``target`` (:func:`database.write`, at
    the matcher's working size): the sequence of ``geomatch run``, a worker's pair step and the
    service's two-image match (no target: nothing is kept)."""
    t0 = time.perf_counter()
    m = match(matcher, pair, image0, image1)
    t1 = time.perf_counter()
    written = None
    if target is not None:
        m = m.in_photo_pixels(*target.photos)
        resize = matcher.config.resize
        prepared = None
        if target.read is not None:
            with target.read() as rdb:
                prepared = prepare(rdb, target.id0, target.id1, m, target.radius, resize)
        with target.open() as db:
            if db is not None:
                if prepared is None:
                    written = write(db, target.id0, target.id1, m, target.radius, resize)
                else:
                    written = commit(db, prepared)
    return PairRun(m, written, t1 - t0, time.perf_counter() - t1)
