"""The matcher's two in-memory caches, bounded in bytes so a worker's memory does not grow with
the project: each image's features with its prepared network input (keyed by pixel hash,
backbone and resolution), and recent pairs' LightGlue output (re-matching a pair with other
optimizer options, an ablation or a retried task, does not run LightGlue again).

Matchers derived from one another share these objects where the settings allow
(:func:`geomatch.matching.variants.share_networks`)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

from ..features.base import ImageFeatures, SparseMatch
from ..imageio import Prepared
from ..memory import trim_lru

FeatureKey = tuple[str, str, int | None]  # (pixel hash, backbone[+dense], resize)
AnchorKey = tuple[str, str, int | None, str | None]  # (hash A, hash B, resize, dense detector)


def feature_key(key: str, backbone: str, dense: bool, resize: int | None) -> FeatureKey:
    return (key, f"{backbone}+dense" if dense else backbone, resize)


def _entry_nbytes(entry: tuple[ImageFeatures, Prepared]) -> int:
    feats, prep = entry
    return feats.nbytes() + prep.tensor.numel() * prep.tensor.element_size()


class FeatureCache:
    """Recent images' features (dense maps included) and prepared inputs, least recently used
    first out beyond the budget the caller passes (each matcher sharing the cache trims to its
    own); the entry just added always stays (a pair needs both images)."""

    def __init__(self) -> None:
        self._data: OrderedDict[FeatureKey, tuple[ImageFeatures, Prepared]] = OrderedDict()

    def __contains__(self, key: FeatureKey) -> bool:
        return key in self._data

    def get(self, key: FeatureKey) -> ImageFeatures | None:
        """The features under ``key``, marked recently used; None when absent."""
        if key not in self._data:
            return None
        self._data.move_to_end(key)
        return self._data[key][0]

    def put(self, key: FeatureKey, feats: ImageFeatures, prep: Prepared, budget_mb: float) -> None:
        self._data[key] = (feats, prep)
        trim_lru(self._data, budget_mb, _entry_nbytes, keep=1)

    def prepared(self, key: str, resize: int | None) -> Prepared | None:
        """The prepared network input of the image ``key`` at ``resize``, from any backbone's entry."""
        for (k, _, r), (_, prep) in self._data.items():
            if k == key and r == resize:
                return prep
        return None

    def nbytes(self) -> int:
        """Bytes held: features and the prepared network inputs."""
        return sum(_entry_nbytes(e) for e in self._data.values())

    def clear(self) -> None:
        self._data.clear()


class AnchorCache:
    """Recent pairs' LightGlue output (soft assignments included), least recently used first out
    beyond the budget the caller passes."""

    def __init__(self) -> None:
        self._data: OrderedDict[AnchorKey, SparseMatch] = OrderedDict()

    def get_or_match(self, key: AnchorKey, run: Callable[[], SparseMatch], budget_mb: float) -> SparseMatch:
        """The cached output for ``key``, else ``run()``'s, cached."""
        if key in self._data:
            self._data.move_to_end(key)
            return self._data[key]
        out = run()
        self._data[key] = out
        trim_lru(self._data, budget_mb, lambda m: m.nbytes(), keep=0)
        return out

    def clear(self) -> None:
        self._data.clear()
