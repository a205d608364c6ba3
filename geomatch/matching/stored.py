"""A :class:`~geomatch.matching.matcher.Matcher` whose per-image features go through a
:class:`~geomatch.features.store.FeatureStore` on disk (the in-memory LRU stays in front of it),
and the matchers the pipeline, the workers and localization build from options."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ..features.base import ImageFeatures
from ..features.store import FeatureStore
from ..imageio import image_key
from .matcher import Matcher, MatcherConfig, config_from_options


class StoredFeaturesMatcher(Matcher):
    """A Matcher whose per-image features are read from / written to a :class:`FeatureStore`.

    The Matcher's in-memory cache stays the first level; entries read from disk are put into it
    (:meth:`Matcher.put_features`), so ``match`` finds them as if computed.
    """

    def __init__(self, config: MatcherConfig, store: FeatureStore) -> None:
        super().__init__(config)
        self.store = store

    def sibling(self, **overrides: Any) -> Matcher:
        """As :meth:`Matcher.sibling`, reading and writing the same store (so does every matcher
        :meth:`Matcher.derive` makes of it)."""
        return StoredFeaturesMatcher(replace(self.config, **overrides), self.store)

    def features(self, image: np.ndarray, key: str | None = None) -> dict[str, ImageFeatures]:
        key = key or image_key(image)
        paths, missing = {}, set()
        for name, dense in self.needed_extractors():
            paths[name] = self.store.path(key, name, dense, self.config)
            if self.has_features(key, name, dense):
                continue
            feats = self.store.load(paths[name], self.device)
            if feats is None:
                missing.add(name)  # computed below, then written (over a torn file, if any)
                continue
            self.put_features(key, name, dense, feats, image)
        out = super().features(image, key)
        for name in missing:
            self.store.save(paths[name], out[name])
        return out


def build_matcher(store: FeatureStore | None = None, **options: Any) -> Matcher:
    """A matcher from pipeline-style options (``method``, ``resize``, ``device``, optimizer fields)
    over ``store`` (None: features in memory only): how ``geomatch run``, a worker and a
    localization build theirs."""
    config = config_from_options(**options)
    return StoredFeaturesMatcher(config, store) if store is not None else Matcher(config)
