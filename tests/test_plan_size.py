"""The size of a pair plan before it is made (``geomatch.options.fewest_pairs``): what the API
compares with GEOMATCH_MAX_PAIRS_PER_JOB without planning, against the library's planners."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.options import fewest_pairs
from geomatch.pipeline import pair_sources as pairs
from geomatch_core.errors import too_many_pairs

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 30])
def test_exhaustive_and_sequential_counts_are_exact(n: int) -> None:
    names = [f"{i:03d}.jpg" for i in range(n)]
    assert fewest_pairs("exhaustive", n) == (len(pairs.exhaustive(names)), True)
    for k in (1, 2, 5, 40):
        assert fewest_pairs(f"sequential:{k}", n) == (len(pairs.sequential(names, k)), True)


@pytest.mark.parametrize("k", [1, 3, 12])
def test_neighbour_plans_have_at_least_the_bound(k: int) -> None:
    rng = np.random.default_rng(k)
    names = [f"{i:03d}.jpg" for i in range(40)]
    enu = {n: rng.normal(size=3) * 100 for n in names}
    least, exact = fewest_pairs(f"gps:{k}", len(names))
    assert not exact and least <= len(pairs.gps_neighbours(names, enu, k))
    least, _ = fewest_pairs(f"retrieval:{k}", len(names))
    assert least <= len(pairs.nearest_neighbours(rng.normal(size=(40, 8)), names, k))
    # a union has at least its largest part; auto is unknown without the images
    assert fewest_pairs(f"gps:{k}+sequential:20", 40)[0] == fewest_pairs("sequential:20", 40)[0]
    assert fewest_pairs("auto", 1000) == (0, False)


def test_the_refusal_says_the_limit_the_count_and_how_to_split() -> None:
    m = too_many_pairs(499_500, 1000, 20_000, "exhaustive")
    assert "would plan 499500 pairs (exhaustive over 1000 images)" in m
    assert "limit of 20000 pairs per job (GEOMATCH_MAX_PAIRS_PER_JOB)" in m
    assert '"gps:20"' in m and '"retrieval:20"' in m and '"sequential:20"' in m
    assert "at least 2000 pairs" in too_many_pairs(2000, 400, 1000, "gps:10", exact=False)
