"""Backbones by name. Networks are imported lazily so that naming one loads only that one."""

from __future__ import annotations

from typing import Protocol

import torch

from .base import DenseHead, Extractor, SparseMatcher
from .refine import RefineOptions


class BackboneConfig(Protocol):
    """The fields of a matcher's configuration (``geomatch.matching.matcher.MatcherConfig``) that the
    builders read: described here so that the backbones need nothing from the matching above them."""

    @property
    def max_keypoints(self) -> int: ...
    @property
    def loftr_weights(self) -> str | None: ...
    @property
    def sparse(self) -> str: ...
    @property
    def lightglue_threshold(self) -> float: ...
    @property
    def lightglue_depth_confidence(self) -> float: ...
    @property
    def lightglue_width_confidence(self) -> float: ...
    @property
    def dense(self) -> str: ...
    @property
    def refine(self) -> RefineOptions: ...


def build_extractor(name: str, device: torch.device, config: BackboneConfig) -> Extractor:
    if name == "aliked":
        from .aliked import AlikedExtractor

        return AlikedExtractor(device, max_keypoints=config.max_keypoints)
    if name == "disk":
        from .disk import DiskExtractor

        return DiskExtractor(device, max_keypoints=config.max_keypoints)
    if name == "loftr":
        from .loftr import LoftrExtractor

        return LoftrExtractor(device, weights=config.loftr_weights)
    raise ValueError(f"unknown backbone {name!r}")


def build_sparse_matcher(config: BackboneConfig, device: torch.device) -> SparseMatcher:
    from .lightglue import LightGlueMatcher

    return LightGlueMatcher(
        config.sparse,
        device,
        filter_threshold=config.lightglue_threshold,
        depth_confidence=config.lightglue_depth_confidence,
        width_confidence=config.lightglue_width_confidence,
    )


def build_dense_head(config: BackboneConfig, extractor: Extractor) -> DenseHead:
    if config.dense == "loftr":
        from .loftr import LoftrExtractor, LoftrHead

        assert isinstance(extractor, LoftrExtractor)
        return LoftrHead(extractor)
    from .descriptor_head import DescriptorHead

    return DescriptorHead(config.dense, refine=config.refine)
