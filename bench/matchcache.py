"""Raw pair matches cached on disk for benchmark runs and their variants: a rerun after a change
matches again only the pairs the change touches. Keyed by the pixels, the plan's decisions for the
pair and the config of the matcher the pair gets, so a change of any of them is a miss.

Only benchmarks (and the tests that run a scene twice) use it; ``geomatch run``, the workers and
the service always match. Importable as ``matchcache`` by the scripts here and as
``bench.matchcache`` from the tests.

    run(images, out, opts, match=matchcache.cached(folder))
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from geomatch.imageio import image_key
from geomatch.matching.matcher import Matcher
from geomatch.pipeline import match_pairs
from geomatch.pipeline.database import PairMatches
from geomatch.pipeline.match_pairs import MatchPair
from geomatch.pipeline.pair_sources import Pair


def match(
    matcher: Matcher,
    pair: Pair,
    image0: np.ndarray,
    image1: np.ndarray,
    cache: str | Path | None,
) -> PairMatches:
    """``geomatch.pipeline.match_pairs.match``, read back from the folder ``cache`` when the pair is there
    (None: no cache)."""
    if not cache:
        return match_pairs.match(matcher, pair, image0, image1)
    config = match_pairs.pair_matcher(matcher, pair).config
    sizes = ((image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0]))
    h = hashlib.sha256(
        repr(
            (
                image_key(image0),
                image_key(image1),
                pair.tiled,
                pair.aerial_first,
                pair.rotate,
                pair.turns,
                config,
            )
        ).encode()
    )
    path = Path(cache) / f"{h.hexdigest()[:32]}.npz"
    if path.is_file():
        with np.load(path) as z:
            return PairMatches(z["k0"], z["k1"], z["scores"], sizes, pair.tiled)
    out = match_pairs.match(matcher, pair, image0, image1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, k0=out.keypoints0, k1=out.keypoints1, scores=out.scores)
    tmp.replace(path)
    return out


def cached(cache: str | Path | None) -> MatchPair:
    """A pair matcher for ``geomatch.pipeline.run(..., match=)`` reading and filling ``cache``
    (None: ``geomatch.pipeline.match_pairs.match`` itself)."""
    if not cache:
        return match_pairs.match

    def match_cached(
        matcher: Matcher,
        pair: Pair,
        image0: np.ndarray,
        image1: np.ndarray,
    ) -> PairMatches:
        return match(matcher, pair, image0, image1, cache)

    return match_cached
