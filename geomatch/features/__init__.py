"""Backbones behind two small interfaces: sparse (keypoints + matcher) and dense (coarse + fine maps)."""

from .base import (
    CoarsePair,
    DenseFeatures,
    DenseHead,
    Extractor,
    ImageFeatures,
    Refined,
    SparseFeatures,
    SparseMatch,
    SparseMatcher,
)

__all__ = [
    "CoarsePair",
    "DenseFeatures",
    "DenseHead",
    "Extractor",
    "ImageFeatures",
    "Refined",
    "SparseFeatures",
    "SparseMatch",
    "SparseMatcher",
]
