"""Backbones are one table (``geomatch.features.registry.BACKBONES``): the option choices are its
names, and a row added to it is built by name like the others."""

from __future__ import annotations

import pytest
import torch

from geomatch.features.base import Extractor, ImageFeatures
from geomatch.features.registry import BACKBONES, Backbone, build_dense_head, build_extractor
from geomatch.matching.matcher import MatcherConfig
from geomatch.options import DENSE_BACKBONES, OPTIONS, SPARSE_BACKBONES

pytestmark = pytest.mark.unit


def test_option_choices_are_the_table() -> None:
    """geomatch.options names the choices without importing torch; they are the table's."""
    assert set(SPARSE_BACKBONES) == {n for n, b in BACKBONES.items() if b.anchors}
    assert set(DENSE_BACKBONES) == {n for n, b in BACKBONES.items() if b.dense}
    assert OPTIONS["sparse"].choices == SPARSE_BACKBONES and OPTIONS["dense"].choices == DENSE_BACKBONES
    for name, row in BACKBONES.items():
        assert row.anchors <= (row.extractor is not None), name  # LightGlue matches its keypoints
        assert (row.head is None) or (row.extractor is not None), name  # a head reads its maps


class Throwaway(Extractor):
    name = "throwaway"

    def __init__(self, device: torch.device, max_keypoints: int) -> None:
        self.device, self.max_keypoints = device, max_keypoints

    def extract(self, image: torch.Tensor, dense: bool = True) -> ImageFeatures:
        return ImageFeatures()


def test_a_row_is_built_by_name() -> None:
    BACKBONES["throwaway"] = Backbone(lambda device, config: Throwaway(device, config.max_keypoints))
    try:
        built = build_extractor("throwaway", torch.device("cpu"), MatcherConfig(max_keypoints=77))
        assert isinstance(built, Throwaway) and built.max_keypoints == 77
    finally:
        del BACKBONES["throwaway"]
    with pytest.raises(ValueError, match="unknown backbone 'throwaway'"):
        build_extractor("throwaway", torch.device("cpu"), MatcherConfig())


def test_soft_assignments_have_no_network_of_their_own() -> None:
    with pytest.raises(ValueError, match="no network of its own"):
        build_extractor("lightglue", torch.device("cpu"), MatcherConfig())
    with pytest.raises(ValueError, match="no head"):
        build_dense_head(MatcherConfig(dense="disk-lightglue"), Throwaway(torch.device("cpu"), 1))
