"""Backbones by name: one table (:data:`BACKBONES`) of what each name builds. Networks are
imported lazily so that naming one loads only that one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
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


ExtractorBuilder = Callable[[torch.device, BackboneConfig], Extractor]
HeadBuilder = Callable[[BackboneConfig, Extractor], DenseHead]


# the builders import their network when called, so that naming a backbone loads only that one
def _aliked(device: torch.device, config: BackboneConfig) -> Extractor:
    from .aliked import AlikedExtractor

    return AlikedExtractor(device, max_keypoints=config.max_keypoints)


def _disk(device: torch.device, config: BackboneConfig) -> Extractor:
    from .disk import DiskExtractor

    return DiskExtractor(device, max_keypoints=config.max_keypoints)


def _loftr(device: torch.device, config: BackboneConfig) -> Extractor:
    from .loftr import LoftrExtractor

    return LoftrExtractor(device, weights=config.loftr_weights)


def _descriptor_head(config: BackboneConfig, extractor: Extractor) -> DenseHead:
    from .descriptor_head import DescriptorHead

    return DescriptorHead(config.dense, refine=config.refine)


def _loftr_head(config: BackboneConfig, extractor: Extractor) -> DenseHead:
    from .loftr import LoftrExtractor, LoftrHead

    assert isinstance(extractor, LoftrExtractor)
    return LoftrHead(extractor)


@dataclass(frozen=True)
class Backbone:
    """One backbone name: the network it runs per image and what it may be chosen for."""

    extractor: ExtractorBuilder | None = None  # its per-image pass (keypoints, descriptors, maps)
    anchors: bool = False  # a --sparse choice: its keypoints matched by its own LightGlue
    dense: bool = False  # a --dense choice
    # the dense branch over its per-image maps; None for a dense choice that is a LightGlue soft
    # assignment, which the matcher makes per pair from keypoints
    head: HeadBuilder | None = None


# ``lightglue``: the anchors' own soft assignment; ``<detector>-lightglue``: a second detector's
# keypoints matched by its own LightGlue. ``geomatch.options`` names the same choices without
# importing torch (SPARSE_BACKBONES, DENSE_BACKBONES; tests/test_registry.py checks they agree).
BACKBONES: dict[str, Backbone] = {
    "aliked": Backbone(_aliked, anchors=True, dense=True, head=_descriptor_head),
    "disk": Backbone(_disk, anchors=True, dense=True, head=_descriptor_head),
    "loftr": Backbone(_loftr, dense=True, head=_loftr_head),
    "lightglue": Backbone(dense=True),
    "disk-lightglue": Backbone(dense=True),
    "aliked-lightglue": Backbone(dense=True),
}


def _backbone(name: str) -> Backbone:
    row = BACKBONES.get(name)
    if row is None:
        raise ValueError(f"unknown backbone {name!r}; choose from {', '.join(BACKBONES)}")
    return row


def build_extractor(name: str, device: torch.device, config: BackboneConfig) -> Extractor:
    build = _backbone(name).extractor
    if build is None:
        raise ValueError(f"backbone {name!r} has no network of its own (a LightGlue soft assignment)")
    return build(device, config)


def build_sparse_matcher(config: BackboneConfig, device: torch.device) -> SparseMatcher:
    from .lightglue import LightGlueMatcher

    if not _backbone(config.sparse).anchors:
        raise ValueError(f"backbone {config.sparse!r} has no LightGlue of its own")
    return LightGlueMatcher(
        config.sparse,
        device,
        filter_threshold=config.lightglue_threshold,
        depth_confidence=config.lightglue_depth_confidence,
        width_confidence=config.lightglue_width_confidence,
    )


def build_dense_head(config: BackboneConfig, extractor: Extractor) -> DenseHead:
    build = _backbone(config.dense).head
    if build is None:
        raise ValueError(f"dense backbone {config.dense!r} has no head over per-image maps")
    return build(config, extractor)
