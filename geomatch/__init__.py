"""geomatch: geometry-aware feature matching for Structure-from-Motion."""

from .imageio import ImageReadError, read_image
from .matcher import METHODS, Matcher, MatcherConfig, MatchResult, match_pair
from .optimizer import GeoOptions
from .refine import RefineOptions
from .weights import WeightsNotFoundError

__all__ = [
    "METHODS",
    "GeoOptions",
    "ImageReadError",
    "MatchResult",
    "Matcher",
    "MatcherConfig",
    "RefineOptions",
    "WeightsNotFoundError",
    "match_pair",
    "read_image",
]
__version__ = "0.1.0"
