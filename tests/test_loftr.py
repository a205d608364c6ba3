"""LoFTR weights are not obtainable here: the code path is exercised with a saved random init."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from kornia.feature import LoFTR

from geomatch import Matcher, MatcherConfig, WeightsNotFoundError
from geomatch.features.loftr import LoftrExtractor, LoftrHead


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> str:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "loftr_random.ckpt"
    torch.save({"state_dict": LoFTR(pretrained=None).state_dict()}, path)
    return str(path)


@pytest.mark.nets
def test_loading_and_shapes(checkpoint: str) -> None:
    ext = LoftrExtractor(torch.device("cpu"), weights=checkpoint)
    assert not ext.net.training
    img_a, img_b = torch.rand(1, 3, 96, 128), torch.rand(1, 3, 128, 96)
    fa, fb = ext.extract(img_a).dense, ext.extract(img_b).dense
    assert fa is not None and fb is not None
    assert fa.coarse.shape == (256, 12, 16) and fa.fine.shape == (128, 48, 64)
    head = LoftrHead(ext)
    pair = head.coarse_pair(fa, fb)
    assert pair.feats_a.shape == (12 * 16, 256) and pair.feats_b.shape == (16 * 12, 256)
    assert pair.grid_a.shape == (192, 2) and pair.temperature == pytest.approx(0.1)
    idx = torch.tensor([0, 17, 100])
    ref = head.refine(fa, fb, pair, idx, idx + 1, None)
    assert ref.points_a.shape == (3, 2) and ref.points_b.shape == (3, 2) and ref.confidence.shape == (3,)
    # the fine stage moves B by at most half a window (5 fine px at stride 2 -> 4 px)
    assert float((ref.points_b - pair.grid_b[idx + 1]).abs().max()) <= 4.0 + 1e-4


@pytest.mark.nets
def test_loftr_runs_through_the_matcher(checkpoint: str) -> None:
    rng = np.random.default_rng(0)
    img = (rng.uniform(0, 255, (120, 160, 3))).astype(np.uint8)
    m = Matcher(MatcherConfig(method="geo-noanchor", dense="loftr", loftr_weights=checkpoint, resize=160))
    r = m.match(img, img[:, ::-1].copy())
    assert r.keypoints0.shape[1] == 2 and r.keypoints0.shape == r.keypoints1.shape


@pytest.mark.unit
def test_missing_checkpoint_is_a_clear_error(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("GEOMATCH_WEIGHTS_DIR", str(tmp_path))
    monkeypatch.delenv("GEOMATCH_LOFTR_WEIGHTS", raising=False)
    with pytest.raises(WeightsNotFoundError, match=r"loftr_outdoor\.ckpt"):
        LoftrExtractor(torch.device("cpu"))
