"""The fused cross-attention (geomatch.features.lightglue.FusedCrossBlock) must compute what
kornia's own CrossBlock computes, with the released weights, with and without a mask: it only
changes how the arithmetic is laid out, and the matches of a real pair must not move."""

from __future__ import annotations

import pytest
import torch

from geomatch import Matcher
from geomatch.features.lightglue import FusedCrossBlock, LightGlueMatcher
from geomatch.synth.photos import WarpedPair

pytestmark = pytest.mark.nets


@pytest.fixture(scope="module")
def net() -> torch.nn.Module:
    return LightGlueMatcher("aliked", torch.device("cpu")).net


@pytest.mark.parametrize("masked", [False, True])
def test_fused_cross_block_equals_kornia(net: torch.nn.Module, masked: bool) -> None:
    fused = net.transformers[3].cross_attn
    assert isinstance(fused, FusedCrossBlock)
    original = fused.block
    g = torch.Generator().manual_seed(0)
    x0, x1 = torch.randn(1, 300, 256, generator=g), torch.randn(1, 200, 256, generator=g)
    mask = None
    if masked:  # the last 40 points of image 1 are padding
        mask = torch.ones(1, 1, 300, 200, dtype=torch.bool)
        mask[..., 160:] = False
    with torch.inference_mode():
        want0, want1 = original(x0, x1, mask)
        got0, got1 = fused(x0, x1, mask)
    assert torch.allclose(got0, want0, atol=1e-4, rtol=1e-4)
    assert torch.allclose(got1, want1, atol=1e-4, rtol=1e-4)
    assert (got0 - want0).abs().max() < 1e-3  # and far from a no-op: the block changes x
    assert (got0 - x0).abs().max() > 1e-2


def test_same_matches_as_kornia_on_a_real_pair(matcher: Matcher, astronaut_pair: WarpedPair) -> None:
    """The fused matcher and one with kornia's own attention give the same matches."""
    img0, img1 = astronaut_pair.image0, astronaut_pair.image1
    sparse = matcher.derive(method="sparse")
    f0 = sparse.features(img0)[sparse.config.sparse].sparse
    f1 = sparse.features(img1)[sparse.config.sparse].sparse
    fused = sparse.sparse_matcher.match(f0, f1)
    plain = LightGlueMatcher(sparse.config.sparse, torch.device("cpu"), fused=False).match(f0, f1)
    assert fused.idx_a.numel() > 50
    assert torch.equal(fused.idx_a, plain.idx_a) and torch.equal(fused.idx_b, plain.idx_b)
    assert torch.allclose(fused.scores, plain.scores, atol=1e-4)
