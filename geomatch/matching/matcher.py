"""Pair matching: backbones, the optimizer and refinement put together.

Methods (the paper's ablations, selectable by name; each is a row of flags in
``geomatch.options.METHOD_TABLE``, and :meth:`Matcher.match` reads the flags, not the name):
``sparse``        anchors only (detector + LightGlue);
``dense``         dense mutual-NN + refinement, no optimisation;
``concat``        anchors naively concatenated to ``dense``;
``geo-noanchor``  optimisation initialised from the top half of the dense matches;
``geo``           the full method: anchors initialise F, dense matches are re-weighted,
                  refined under the epipolar prior, and anchors are kept alongside them.

Features are computed once per image (keyed by pixel hash, backbone and resolution) and kept
in a small in-memory LRU (geomatch.matching.featurecache), so matching one image against many
runs each network once. :meth:`Matcher.has_features`, :meth:`Matcher.put_features` and
:meth:`Matcher.clear_caches` let a store in front of it (``matching.stored.StoredFeaturesMatcher``)
fill it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..epipolar.geometry import estimate_fundamental, sampson_distance
from ..features.base import DenseHead, Extractor, ImageFeatures, SparseFeatures, SparseMatch, SparseMatcher
from ..features.registry import build_dense_head, build_extractor, build_sparse_matcher
from ..features.subpixel import refine_points
from ..imageio import Prepared, image_key, prepare, read_image
from .config import (
    DEDUP_RADIUS,
    MatcherConfig,
    MatchResult,
    StageTimer,
    config_from_options,
    pair_result,
    resolve_device,
)
from .dense import from_assignment, from_maps, merge_parts
from .featurecache import AnchorCache, FeatureCache, feature_key
from .guided import match_guided
from .variants import for_pair, full_matcher, light_matcher

__all__ = [
    "MatchResult",
    "Matcher",
    "MatcherConfig",
    "config_from_options",
    "match_pair",
    "resolve_device",
]

log = logging.getLogger(__name__)

Anchors = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # points in A, points in B, scores


@dataclass
class _Pair:
    """One pair in flight: its images' pixel hashes, features and prepared network inputs, and the
    stats and stage timings its answer reports."""

    key0: str
    key1: str
    f0: dict[str, ImageFeatures]
    f1: dict[str, ImageFeatures]
    prep0: Prepared
    prep1: Prepared
    stats: dict[str, Any]
    timer: StageTimer


class Matcher:
    """Holds the networks and the per-image feature cache; ``match`` is one pair."""

    def __init__(self, config: MatcherConfig | None = None, **overrides: Any) -> None:
        self.config = replace(config or MatcherConfig(), **overrides)
        self.device = resolve_device(self.config.device)
        self._extractors: dict[str, Extractor] = {}
        self._sparse: SparseMatcher | None = None
        self._dense_lightglue: SparseMatcher | None = None
        self._probe: SparseMatcher | None = None
        self._dense: DenseHead | None = None
        self.feature_cache = FeatureCache()
        self.anchor_cache = AnchorCache()
        self.extract_calls = 0
        # the matchers derived for its pairs (geomatch.matching.variants), each derived once
        self.variants: dict[str, Matcher] = {}

    def sibling(self, **overrides: Any) -> Matcher:
        """A new matcher of this kind with other options, sharing nothing yet (:meth:`derive`
        shares what it may): a subclass that keeps more than the options returns its own kind."""
        return Matcher(self.config, **overrides)

    def derive(self, **overrides: Any) -> Matcher:
        """A matcher with other options that shares this one's networks and feature cache.

        Sharing is valid because cached features depend only on the image, the backbone and
        the resolution, all part of the cache key; the sparse matcher is shared only when its
        own options are unchanged.
        """
        other = self.sibling(**overrides)

        def same(*names: str) -> bool:
            return all(getattr(self.config, n) == getattr(other.config, n) for n in names)

        if other.device != self.device or not same("max_keypoints", "loftr_weights"):
            return other  # networks built differently: nothing to share
        other._extractors = self._extractors
        other.feature_cache = self.feature_cache
        if same("sparse", "lightglue_threshold"):
            other._probe = self._probe
        if same("sparse", "lightglue_threshold", "lightglue_depth_confidence", "lightglue_width_confidence"):
            other._sparse = self._sparse
            other.anchor_cache = self.anchor_cache
            if same("dense_keypoints"):
                other._dense_lightglue = self._dense_lightglue
        return other

    # -- networks -------------------------------------------------------------------------
    def extractor(self, name: str) -> Extractor:
        if name not in self._extractors:
            self._extractors[name] = build_extractor(name, self.device, self.config)
        return self._extractors[name]

    @property
    def sparse_matcher(self) -> SparseMatcher:
        if self._sparse is None:
            self._sparse = build_sparse_matcher(self.config, self.device)
        return self._sparse

    @property
    def probe_matcher(self) -> SparseMatcher:
        """LightGlue with its own adaptive depth and width (0.95 / 0.99): the turn probe's."""
        if self._probe is None:
            self._probe = build_sparse_matcher(
                replace(self.config, lightglue_depth_confidence=0.95, lightglue_width_confidence=0.99),
                self.device,
            )
        return self._probe

    @property
    def dense_lightglue(self) -> SparseMatcher:
        """The second detector's LightGlue (``dense=disk-lightglue``); its pruning settings are
        the anchors' (a soft assignment needs width pruning off)."""
        if self._dense_lightglue is None:
            assert self.config.dense_keypoints is not None
            self._dense_lightglue = build_sparse_matcher(
                replace(self.config, sparse=self.config.dense_keypoints), self.device
            )
        return self._dense_lightglue

    @property
    def dense_head(self) -> DenseHead:
        if self._dense is None:
            self._dense = build_dense_head(self.config, self.extractor(self.config.dense))
        return self._dense

    def needed_extractors(self) -> list[tuple[str, bool]]:
        """(backbone, dense maps wanted) for each network pass an image needs."""
        cfg = self.config
        passes: dict[str, bool] = {}
        if cfg.needs_sparse:
            passes[cfg.sparse] = False
        if cfg.dense_keypoints is not None:
            passes.setdefault(cfg.dense_keypoints, False)
        if cfg.dense_maps:
            passes[cfg.dense] = True
        return list(passes.items())

    # -- the caches (geomatch.matching.featurecache) -------------------------------------------
    def has_features(self, key: str, backbone: str, dense: bool) -> bool:
        """Whether the in-memory cache holds ``backbone``'s features (``dense``: with dense maps)
        of the image whose pixel hash is ``key``, at this matcher's resolution."""
        return feature_key(key, backbone, dense, self.config.resize) in self.feature_cache

    def put_features(
        self, key: str, backbone: str, dense: bool, feats: ImageFeatures, image: np.ndarray
    ) -> None:
        """Put features computed elsewhere (a store on disk) into the in-memory cache, as if
        :meth:`features` had computed them from ``image`` (pixel hash ``key``)."""
        ck = feature_key(key, backbone, dense, self.config.resize)
        prep = prepare(image, self.config.resize, self.device)
        self.feature_cache.put(ck, feats, prep, self.config.cache_features_mb)

    def clear_caches(self, features: bool = True, anchors: bool = True) -> None:
        """Empty the per-image feature cache and / or the recent pairs' anchors, and those of the
        variants kept in ``variants`` (a variant with other LightGlue options has anchors of its
        own)."""
        if features:
            self.feature_cache.clear()
        if anchors:
            self.anchor_cache.clear()
        for variant in self.variants.values():
            if variant is not self:
                variant.clear_caches(features, anchors)

    def cache_nbytes(self) -> int:
        """Bytes the feature cache holds (features and the prepared network inputs)."""
        return self.feature_cache.nbytes()

    def features(self, image: np.ndarray, key: str | None = None) -> dict[str, ImageFeatures]:
        """Each needed backbone's features of ``image``, from the cache or computed once."""
        key = key or image_key(image)
        out: dict[str, ImageFeatures] = {}
        prepared: Prepared | None = None
        for name, dense in self.needed_extractors():
            ck = feature_key(key, name, dense, self.config.resize)
            cached = self.feature_cache.get(ck)
            if cached is not None:
                out[name] = cached
                continue
            if prepared is None:
                prepared = prepare(image, self.config.resize, self.device)
            with torch.inference_mode():
                feats = self.extractor(name).extract(prepared.tensor, dense=dense)
            self.extract_calls += 1
            self.feature_cache.put(ck, feats, prepared, self.config.cache_features_mb)
            out[name] = feats
        return out

    def prepared(self, image: np.ndarray, key: str) -> Prepared:
        """``image``'s network input at this matcher's resolution, the cached one when there is one."""
        cached = self.feature_cache.prepared(key, self.config.resize)
        return cached if cached is not None else prepare(image, self.config.resize, self.device)

    def match_anchors(
        self, key0: str, key1: str, sa: SparseFeatures, sb: SparseFeatures, dense: bool = False
    ) -> SparseMatch:
        """One LightGlue pass, cached per pair: the anchors' (``dense`` False) or the dense
        branch's second detector's (``dense`` True)."""
        ak = (key0, key1, self.config.resize, self.config.dense_keypoints if dense else None)
        return self.anchor_cache.get_or_match(
            ak,
            lambda: (self.dense_lightglue if dense else self.sparse_matcher).match(sa, sb),
            self.config.cache_anchors_mb,
        )

    # -- one pair, by the paper's steps ------------------------------------------------------
    @torch.inference_mode()
    def match(self, image0: np.ndarray, image1: np.ndarray) -> MatchResult:
        """One pair: the anchors; the answer is theirs where they fit an F well enough
        (``anchors_suffice``); else the dense matches (geometry-aware rounds from the anchors' F
        for the methods that optimise), merged after the anchors, refined to sub-pixel, and
        checked against the final F. Which steps run is the method's flags."""
        cfg = self.config
        if cfg.light_first and cfg.flags.optimise and cfg.anchors_suffice > 0:
            return self._light_first(image0, image1)
        pair = self._features(image0, image1)
        lg, anchors = self._anchors(pair)
        if anchors is not None and cfg.flags.optimise and cfg.anchors_suffice > 0:
            answer = self._anchors_suffice(pair, anchors)
            if answer is not None:
                return answer
        dense = self._dense_matches(pair, lg, anchors) if cfg.needs_dense else None
        pa, pb, ps = self._merge(pair, anchors, dense)
        pb = self._subpixel(pair, pa, pb)
        with pair.timer("merge"):
            F_net, pa, pb, ps = self._final_check(pair, pa, pb, ps)
            pa, pb, ps = self._anchor_support(pair, F_net, anchors, pa, pb, ps)
        return self._result(pa, pb, ps, F_net, pair)

    def _light_first(self, image0: np.ndarray, image1: np.ndarray) -> MatchResult:
        """``light_first``: the light matcher's answer where its F has at least ``anchors_suffice``
        inliers (or fewer than ``escalate_from``); else the full method, whose timings include the
        light attempt."""
        cfg = self.config
        lm = light_matcher(self)
        light = match_guided(lm, image0, image1) if cfg.guided_keypoints else lm.match(image0, image1)
        inliers = light.stats.get("f_inliers", 0)
        if inliers >= cfg.anchors_suffice or inliers < cfg.escalate_from:
            light.stats["anchors_suffice"] = "light"
            return light
        full = full_matcher(self).match(image0, image1)
        full.timings = {"light": light.timings.get("total", 0.0), **full.timings}
        full.timings["total"] += full.timings["light"]
        return full

    def _features(self, image0: np.ndarray, image1: np.ndarray) -> _Pair:
        """Step 0: both images' features (cached per image) and network inputs."""
        timer = StageTimer(self.device)
        key0, key1 = image_key(image0), image_key(image1)
        with timer("features0"):
            f0 = self.features(image0, key0)
        with timer("features1"):
            f1 = self.features(image1, key1)
        prep0, prep1 = self.prepared(image0, key0), self.prepared(image1, key1)
        return _Pair(key0, key1, f0, f1, prep0, prep1, {}, timer)

    def _anchors(self, pair: _Pair) -> tuple[SparseMatch | None, Anchors | None]:
        """Step 1: LightGlue on the detector's keypoints; its matches are the anchors for the
        methods that use them (its soft assignment is the dense branch of ``dense=lightglue``)."""
        cfg = self.config
        if not cfg.needs_sparse:
            return None, None
        sa, sb = pair.f0[cfg.sparse].sparse, pair.f1[cfg.sparse].sparse
        assert sa is not None and sb is not None
        with pair.timer("anchors"):
            lg = self.match_anchors(pair.key0, pair.key1, sa, sb)
        if not cfg.uses_anchors:
            return lg, None
        pair.stats["anchors"] = int(lg.idx_a.numel())
        return lg, (sa.keypoints[lg.idx_a].float(), sb.keypoints[lg.idx_b].float(), lg.scores)

    def _anchors_suffice(self, pair: _Pair, anchors: Anchors) -> MatchResult | None:
        """Step 2, the early exit: the F fitted to the anchors alone; with at least
        ``anchors_suffice`` inliers the answer is what ``sparse`` gives (the anchors and that F),
        the dense rounds being for pairs whose anchors are too few to trust."""
        with pair.timer("anchors"):
            F_anchors, inliers = _anchor_fit(anchors, self.config)
        if inliers < self.config.anchors_suffice:
            return None
        pair.stats["anchors_suffice"] = True
        return self._result(*anchors, F_anchors, pair)

    def _dense_matches(
        self, pair: _Pair, lg: SparseMatch | None, anchors: Anchors | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step 3: the dense matches (geometry-aware rounds initialised from the anchors' F for
        the methods that optimise), from LightGlue's soft assignment over a detector's keypoints
        or from the per-image dense maps (geomatch.matching.dense)."""
        cfg, stats, timer = self.config, pair.stats, pair.timer
        if cfg.dense == "lightglue":
            assert lg is not None
            sa, sb = pair.f0[cfg.sparse].sparse, pair.f1[cfg.sparse].sparse
            return from_assignment(cfg, self.device, lg, sa, sb, anchors, stats, timer)
        if cfg.dense_keypoints is not None:
            da, db = pair.f0[cfg.dense_keypoints].sparse, pair.f1[cfg.dense_keypoints].sparse
            assert da is not None and db is not None
            with timer("dense_lightglue"):
                lgd = self.match_anchors(pair.key0, pair.key1, da, db, dense=True)
            return from_assignment(cfg, self.device, lgd, da, db, anchors, stats, timer)
        return from_maps(cfg, self.dense_head, pair.f0, pair.f1, anchors, stats, timer)

    def _merge(
        self,
        pair: _Pair,
        anchors: Anchors | None,
        dense: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step 4: the anchors first, then the dense matches not within ``DEDUP_RADIUS`` of one."""
        parts_a: list[torch.Tensor] = []
        parts_b: list[torch.Tensor] = []
        parts_s: list[torch.Tensor] = []
        if anchors is not None:
            parts_a.append(anchors[0])
            parts_b.append(anchors[1])
            parts_s.append(anchors[2].float())
        if dense is not None:
            parts_a.append(dense[0].float())
            parts_b.append(dense[1].float())
            parts_s.append(dense[2])
        with pair.timer("merge"):
            return merge_parts(parts_a, parts_b, parts_s, DEDUP_RADIUS, self.device)

    def _subpixel(self, pair: _Pair, pa: torch.Tensor, pb: torch.Tensor) -> torch.Tensor:
        """Step 5: least-squares matching moves each final point in B (geomatch.features.subpixel),
        for the methods that refine (``MatcherConfig.refines_subpixel``)."""
        if not (self.config.refines_subpixel and pa.shape[0]):
            return pb
        with pair.timer("subpixel"):
            pb, moved = refine_points(pair.prep0.tensor, pair.prep1.tensor, pa, pb)
        pair.stats["subpixel_refined"] = int(moved.sum())
        return pb

    def _final_check(
        self, pair: _Pair, pa: torch.Tensor, pb: torch.Tensor, ps: torch.Tensor
    ) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step 6: the F of the final matches; the methods that optimise drop the matches farther
        than ``tau`` from it (``final_check``)."""
        cfg = self.config
        F_net, f_mask = estimate_fundamental(pa, pb, cfg.geo.f_estimator, cfg.geo.f_threshold)
        pair.stats["f_inliers"] = 0 if f_mask is None else int(f_mask.sum())
        if cfg.flags.optimise and cfg.final_check and F_net is not None:
            keep = sampson_distance(F_net, pa, pb) <= cfg.geo.tau
            pair.stats["final_check_removed"] = int((~keep).sum())
            pa, pb, ps = pa[keep], pb[keep], ps[keep]
        return F_net, pa, pb, ps

    def _anchor_support(
        self,
        pair: _Pair,
        F_net: torch.Tensor | None,
        anchors: Anchors | None,
        pa: torch.Tensor,
        pb: torch.Tensor,
        ps: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Step 7: no matches for a pair whose final F fewer than ``min_anchor_support`` anchors
        support: the optimiser shapes the dense matches to agree with an F, the anchors are the
        independent evidence that the F is right."""
        cfg = self.config
        if not (cfg.flags.optimise and anchors is not None and cfg.min_anchor_support > 0):
            return pa, pb, ps
        support = 0
        if F_net is not None and anchors[0].shape[0]:
            d = sampson_distance(F_net, anchors[0].to(F_net.device), anchors[1].to(F_net.device))
            support = int((d <= cfg.geo.tau).sum())
        pair.stats["anchor_support"] = support
        if support < cfg.min_anchor_support:
            pair.stats["rejected"] = f"{support} anchors support the pair's F"
            pa, pb, ps = pa[:0], pb[:0], ps[:0]
        return pa, pb, ps

    def _result(
        self, pa: torch.Tensor, pb: torch.Tensor, ps: torch.Tensor, F_net: torch.Tensor | None, pair: _Pair
    ) -> MatchResult:
        preps = (pair.prep0, pair.prep1)
        return pair_result(self.config.method, (pa, pb, ps), F_net, preps, pair.stats, pair.timer)


def _anchor_fit(anchors: Anchors, cfg: MatcherConfig) -> tuple[torch.Tensor | None, int]:
    """The F fitted to the anchors alone (the optimiser's own starting point, and what ``sparse``
    answers with) and its inlier count; no fit when there are fewer anchors than the threshold."""
    if anchors[0].shape[0] < cfg.anchors_suffice:
        return None, 0
    F, mask = estimate_fundamental(anchors[0], anchors[1], cfg.geo.f_estimator, cfg.geo.f_threshold)
    return F, 0 if mask is None else int(mask.sum())


_DEFAULT_MATCHERS: dict[MatcherConfig, Matcher] = {}


def match_pair(
    image0: str | Path | np.ndarray, image1: str | Path | np.ndarray, **options: Any
) -> MatchResult:
    """Match two images (paths or RGB uint8 arrays) with the default ``auto`` (two images alone are
    a plain pair: the anchors, as ``geomatch run`` matches such a pair) or a named method.

    Keyword options are :class:`MatcherConfig` fields; ``geo`` and ``refine`` fields may also be
    given directly (``tau=50``, ``iterations=5``, ``radius=5`` ...). Matchers are reused across
    calls with the same options, so weights load once per process.
    """
    config = config_from_options(**options)
    matcher = _DEFAULT_MATCHERS.get(config)
    if matcher is None:
        matcher = _DEFAULT_MATCHERS[config] = Matcher(config)
    a = image0 if isinstance(image0, np.ndarray) else read_image(image0)
    b = image1 if isinstance(image1, np.ndarray) else read_image(image1)
    return for_pair(matcher, tiled=False).match(a, b)
