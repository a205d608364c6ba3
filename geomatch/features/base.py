"""The two small interfaces every backbone implements, and the tensors they exchange.

Coordinates are pixels of the *network input* (the resized image), with pixel centres at
integer coordinates (x right, y down): the pixel in column 0, row 0 covers [-0.5, 0.5)^2.
Mapping back to the original image is done once, in :mod:`geomatch.matching.matcher`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import torch


@dataclass
class SparseFeatures:
    """Keypoints of one image, as a detector-based matcher consumes them."""

    keypoints: torch.Tensor  # (K, 2) float, network-input pixels
    descriptors: torch.Tensor  # (K, D) L2-normalised
    scores: torch.Tensor  # (K,)
    image_size: tuple[int, int]  # (W, H) of the network input


@dataclass
class DenseFeatures:
    """Per-image dense maps; pair-dependent work (cross attention) happens in ``coarse_pair``."""

    coarse: torch.Tensor  # (C, h, w) coarse map on the 1/stride grid
    fine: torch.Tensor | None  # (C_f, H_f, W_f) map the refinement correlates on
    stride: int  # pixels per coarse cell
    image_size: tuple[int, int]  # (W, H) of the network input
    heatmap: torch.Tensor | None = None  # (H, W) detector response, picks a point inside each cell
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class ImageFeatures:
    """Everything one forward pass of one backbone produced for one image."""

    sparse: SparseFeatures | None = None
    dense: DenseFeatures | None = None

    def nbytes(self) -> int:
        tensors: list[torch.Tensor] = []
        if self.sparse is not None:
            tensors += [self.sparse.keypoints, self.sparse.descriptors, self.sparse.scores]
        if self.dense is not None:
            tensors += [t for t in (self.dense.coarse, self.dense.fine, self.dense.heatmap) if t is not None]
        return sum(t.numel() * t.element_size() for t in tensors)


@dataclass
class CoarsePair:
    """Coarse features of a pair, scaled so that the similarity is ``feats_a @ feats_b.T / temperature``."""

    feats_a: torch.Tensor  # (N, C)
    feats_b: torch.Tensor  # (M, C)
    grid_a: torch.Tensor  # (N, 2) cell centres in network-input pixels
    grid_b: torch.Tensor  # (M, 2)
    temperature: float
    context: dict[str, Any] = field(default_factory=dict)


@dataclass
class Refined:
    points_a: torch.Tensor  # (K, 2)
    points_b: torch.Tensor  # (K, 2)
    confidence: torch.Tensor  # (K,) in [0, 1]


class Extractor(ABC):
    """One network pass per image: yields sparse and/or dense features."""

    name: str
    provides_sparse: bool = False
    provides_dense: bool = False

    @abstractmethod
    def extract(self, image: torch.Tensor, dense: bool = True) -> ImageFeatures:
        """``image`` is (1, 3, H, W) RGB in [0, 1] with H, W multiples of 16.

        ``dense=False`` drops the dense maps (full-resolution maps are the bulk of the memory
        a cached image holds) when only the sparse branch is used.
        """


@dataclass
class SparseMatch:
    """A detector-based matcher's verdict on a pair of keypoint sets."""

    idx_a: torch.Tensor  # (K,) indices into a's keypoints
    idx_b: torch.Tensor  # (K,) indices into b's keypoints
    scores: torch.Tensor  # (K,) in [0, 1]
    # (N_a, N_b) soft assignment over ALL keypoints, when the matcher computes one for every keypoint
    # (LightGlue without point pruning): the optimizer's P_c with keypoints as cells
    assignment: torch.Tensor | None = None

    def nbytes(self) -> int:
        ts = [self.idx_a, self.idx_b, self.scores] + (
            [self.assignment] if self.assignment is not None else []
        )
        return sum(t.numel() * t.element_size() for t in ts)


class SparseMatcher(ABC):
    name: str

    @abstractmethod
    def match(self, a: SparseFeatures, b: SparseFeatures) -> SparseMatch:
        """Matches between ``a`` and ``b`` keypoints, with the soft assignment where available."""


class DenseHead(ABC):
    """Turns per-image dense maps into coarse pair features and refines coarse matches."""

    name: str

    @abstractmethod
    def coarse_pair(self, a: DenseFeatures, b: DenseFeatures) -> CoarsePair: ...

    @abstractmethod
    def refine(
        self,
        a: DenseFeatures,
        b: DenseFeatures,
        pair: CoarsePair,
        idx_a: torch.Tensor,
        idx_b: torch.Tensor,
        fundamental: torch.Tensor | None,
    ) -> Refined: ...
