"""LightGlue over several pairs a forward pass (geomatch.features.lightglue_batch) must give each
pair what it gets on its own: padded points must not take part in the attention or the
assignment, whatever the keypoint counts of the pairs beside it."""

from __future__ import annotations

import pytest
import torch

from geomatch import Matcher
from geomatch.features.base import SparseFeatures, SparseMatch
from geomatch.features.lightglue import LightGlueMatcher
from geomatch.features.lightglue_batch import DEFAULT_BUDGET_BYTES, pair_bytes, plan_batches
from geomatch.synth.photos import WarpedPair, warped_pair

Pair = tuple[SparseFeatures, SparseFeatures]


def _first(f: SparseFeatures, n: int) -> SparseFeatures:
    """The image's first ``n`` keypoints: a real feature set of another size."""
    return SparseFeatures(f.keypoints[:n], f.descriptors[:n], f.scores[:n], f.image_size)


@pytest.fixture(scope="module")
def pairs(matcher: Matcher, astronaut_pair: WarpedPair) -> list[Pair]:
    """Two photo pairs cut to different keypoint counts on both sides (one pair swapped), so that
    every pair of a batch is padded on at least one side."""
    sparse = matcher.derive(method="sparse")

    def feats(w: WarpedPair) -> tuple[SparseFeatures, SparseFeatures]:
        f0 = sparse.features(w.image0)[sparse.config.sparse].sparse
        f1 = sparse.features(w.image1)[sparse.config.sparse].sparse
        assert f0 is not None and f1 is not None
        return f0, f1

    a0, a1 = feats(astronaut_pair)
    c0, c1 = feats(warped_pair("coffee", seed=0, strength=0.15))
    counts = [
        (a0, 300, a1, 450),
        (a0, 520, a1, 260),
        (c0, 410, c1, 350),
        (c0, 200, c1, 600),
        (a1, 380, a0, 330),
    ]
    out = [(_first(x, nx), _first(y, ny)) for x, nx, y, ny in counts]
    assert len({p[0].keypoints.shape[0] for p in out}) == len(out)
    assert len({p[1].keypoints.shape[0] for p in out}) == len(out)
    return out


@pytest.fixture(scope="module")
def lightglue(matcher: Matcher) -> LightGlueMatcher:
    lg = matcher.derive(method="sparse").sparse_matcher
    assert isinstance(lg, LightGlueMatcher) and lg.batches
    return lg


# the same matches exactly; scores to float32 noise: padding a pair into a batch changes the order
# of the attention's sums, and over nine layers that moves a score by about 1e-4 (seen on a loaded
# 2-core machine: 0.4155 against 0.4156)
SCORE_ATOL = 1e-3


def _assert_same(got: SparseMatch, want: SparseMatch) -> None:
    assert torch.equal(got.idx_a, want.idx_a) and torch.equal(got.idx_b, want.idx_b)
    assert torch.allclose(got.scores, want.scores, atol=SCORE_ATOL)
    assert got.assignment is not None and want.assignment is not None
    assert got.assignment.shape == want.assignment.shape
    assert torch.allclose(got.assignment, want.assignment, atol=SCORE_ATOL)


@pytest.mark.nets
def test_batch_equals_one_pair_at_a_time(lightglue: LightGlueMatcher, pairs: list[Pair]) -> None:
    """All five pairs in one padded forward pass (the default budget holds them), then the same
    split into several passes by a small budget: each pair's matches, scores and soft assignment
    as ``match`` gives them."""
    single = [lightglue.match(a, b) for a, b in pairs]
    assert all(s.idx_a.numel() > 50 for s in single)
    heads = lightglue.net.conf.num_heads
    sizes = [(a.keypoints.shape[0], b.keypoints.shape[0]) for a, b in pairs]
    assert len(plan_batches(sizes, heads, DEFAULT_BUDGET_BYTES)) == 1
    for got, want in zip(lightglue.match_batch(pairs), single, strict=True):
        _assert_same(got, want)
    small = 2 * pair_bytes(600, 600, heads)
    for got, want in zip(lightglue.match_batch(pairs, budget_bytes=small), single, strict=True):
        _assert_same(got, want)


@pytest.mark.nets
def test_batch_keeps_order_and_empty_pairs(lightglue: LightGlueMatcher, pairs: list[Pair]) -> None:
    """A pair with no keypoints on a side has no matches, as with ``match``, and the others keep
    their places in the list."""
    a, b = pairs[0]
    none = _first(b, 0)
    batch = [(a, none), pairs[2], (none, b), pairs[3]]
    got = lightglue.match_batch(batch)
    assert [r.idx_a.numel() for r in (got[0], got[2])] == [0, 0]
    _assert_same(got[1], lightglue.match(*pairs[2]))
    _assert_same(got[3], lightglue.match(*pairs[3]))


@pytest.mark.nets
def test_keypoints_outside_the_image_are_an_error(lightglue: LightGlueMatcher, pairs: list[Pair]) -> None:
    a, b = pairs[0]
    wrong = SparseFeatures(a.keypoints, a.descriptors, a.scores, (a.image_size[0] // 4, a.image_size[1] // 4))
    with pytest.raises(ValueError, match="outside their image"):
        lightglue.match_batch([(wrong, b), pairs[1]])


@pytest.mark.unit
def test_plan_batches_fits_the_budget() -> None:
    """Batches hold pairs of similar sizes, each within the budget, every pair exactly once; a
    pair over the budget on its own runs alone."""
    sizes = [(100, 900), (1000, 50), (120, 80), (600, 600), (90, 110), (2000, 10)]
    budget = 3 * pair_bytes(1000, 1000, 4)
    batches = plan_batches(sizes, 4, budget)
    assert sorted(i for b in batches for i in b) == list(range(len(sizes)))
    assert batches == [[4, 2, 3], [0, 1], [5]]
    for batch in batches[:-1]:
        n0, n1 = max(sizes[i][0] for i in batch), max(sizes[i][1] for i in batch)
        assert len(batch) * pair_bytes(n0, n1, 4) <= budget
    assert plan_batches(sizes, 4, 1) == [[i] for i in (4, 2, 3, 0, 1, 5)]
    assert plan_batches([], 4, budget) == []
    with pytest.raises(ValueError, match="positive"):
        plan_batches(sizes, 4, 0)
