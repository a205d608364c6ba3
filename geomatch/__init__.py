"""geomatch: geometry-aware feature matching for Structure-from-Motion.

The public names load lazily: the service's API process imports ``geomatch.options`` and friends
without paying for torch, which only the matching code needs.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_EXPORTS = {
    "ImageReadError": "imageio",
    "read_image": "imageio",
    "METHODS": "options",
    "Matcher": "matching.matcher",
    "MatcherConfig": "matching.config",
    "MatchResult": "matching.config",
    "match_pair": "matching.matcher",
    "GeoOptions": "matching.optimizer",
    "RefineOptions": "features.refine",
    "WeightsNotFoundError": "features.weights",
    "localize_photos": "localize",
    "Localization": "localize",
    "LocalizeOptions": "localize",
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'geomatch' has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value
