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
in a small in-memory LRU, so matching one image against many runs each network once. The LRU's
public interface (:meth:`Matcher.has_features`, :meth:`Matcher.put_features`,
:meth:`Matcher.clear_caches`) lets a store in front of it (``matching.stored.StoredFeaturesMatcher``) fill it.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..features.base import DenseHead, Extractor, ImageFeatures, SparseFeatures, SparseMatch, SparseMatcher
from ..features.refine import RefineOptions
from ..features.registry import build_dense_head, build_extractor, build_sparse_matcher
from ..features.subpixel import refine_points
from ..geometry import estimate_fundamental, sampson_distance, scale_fundamental
from ..imageio import Prepared, image_key, prepare, read_image
from ..lru import trim_lru
from ..options import DEFAULTS, DENSE_BACKBONES, METHOD_FLAGS, METHODS, SPARSE_BACKBONES, Method
from .guided import mutual_ratio
from .optimizer import (
    Assignment,
    GeoOptions,
    dense_mutual_nn,
    first_unique,
    geometry_aware_matching,
    mutual_nn,
    optimise,
)

log = logging.getLogger(__name__)


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` picks CUDA when present; asking for CUDA on a machine without it is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise ValueError(f"unknown device {name!r} ({e})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available here (use --device cpu)")
    return device


# ``auto``'s pairs in a project without aerial images: 1024 keypoints and LightGlue's adaptive depth and
# width. On the real tuning scenes this kept every camera correct, with camera errors close to those
# of 2048 keypoints with the same pruning, while LightGlue ran 2.7x faster (5.7x faster than 2048
# at full strength) on the CPU, where it is most of a project's time (docs/benchmarks.md)
AUTO_PLAIN_PAIRS: dict[str, Any] = {
    "max_keypoints": 1024,
    "lightglue_depth_confidence": 0.95,
    "lightglue_width_confidence": 0.99,
}


# ``auto``'s pairs of two aerial photos (MatcherConfig.guided_keypoints): ALIKED points per photo;
# the seed's ratio test over all points and the guided pass's among those on an epipolar line;
# LightGlue's points where the nearest neighbours seed too weak an F
GUIDED_KEYPOINTS = 4096
SEED_RATIO = 0.9
GUIDED_RATIO = 0.95
GUIDED_LIGHTGLUE_POINTS = 1024

# px at network input: a dense match this close to an anchor (or to a match merged before it) is
# the same match
DEDUP_RADIUS = 2.0


@dataclass(frozen=True)
class MatcherConfig:
    method: str = DEFAULTS["method"]
    resize: int | None = DEFAULTS["resize"]
    device: str = DEFAULTS["device"]
    sparse: str = DEFAULTS["sparse"]
    dense: str = DEFAULTS["dense"]
    max_keypoints: int = 2048
    lightglue_threshold: float = 0.1
    # LightGlue's adaptive depth (early exit) and width (point pruning) confidences: speed settings
    # that cost the anchors accuracy on hard pairs; -1 turns them off (LightGlue's own defaults are
    # 0.95 / 0.99). Without point pruning LightGlue's soft assignment covers every keypoint, which
    # the ``lightglue`` dense branch needs. Chosen by measurement: docs/benchmarks.md.
    lightglue_depth_confidence: float = -1.0
    lightglue_width_confidence: float = -1.0
    # the quarter-turn probe (geomatch.matching.rotation) only ranks four turns, so it matches each image's
    # strongest ``probe_keypoints`` with LightGlue's adaptive depth and width on: on the 2-core CPU
    # a full-strength call on 2048 + 2048 points takes ~8 s, four of them per pair dominated an
    # aerial pair (bench/quarter_turns.py compares the two probes' choices)
    probe_keypoints: int = 512
    # a tiled pair (geomatch.matching.tiling): "probe" matches only the aerial crops where the cheap probe's
    # F-consistent matches lie (all five when it finds too few to tell), "all" the five crops
    tile_crops: str = "probe"
    loftr_weights: str | None = DEFAULTS["loftr_weights"]
    geo: GeoOptions = field(default_factory=GeoOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    final_check: bool = True  # geo methods: drop final matches farther than tau from the fitted F
    # geo: a pair whose final F is supported by fewer anchors than this gives no matches (0: off).
    # The optimiser makes the dense matches agree with an F by construction, so on a pair that does
    # not overlap they agree with a wrong F and pass any later verification; the anchors, which the
    # optimiser does not shape, are the independent evidence. 15 is COLMAP's min_num_inliers.
    min_anchor_support: int = 15
    # geo: a pair whose anchors alone fit an F with at least this many inliers is answered by the
    # anchors, as ``sparse`` would answer it (no dense rounds, no least-squares matching); 0: the
    # full method on every pair. The rounds are for pairs whose anchors are too few to trust.
    # Measured on real photos with the view-graph drops held fixed (castle-P19): rounds on the
    # pairs with 50-299 anchor inliers cost 0.07 AUC@10, and most of those pairs are look-alike
    # facades to which the rounds add ~20 % more matches under their wrong F; from 50 down they cost
    # 0.01. Tiled aerial x ground pairs always get the full method (Matcher.for_pair): that is where
    # it was measured to register views the anchors lose.
    anchors_suffice: int = 50
    # geo: try the light anchors (``sparse`` with AUTO_PLAIN_PAIRS, what a ground-only project's
    # pairs get) first, and answer with them when they fit an F with at least ``anchors_suffice``
    # inliers; only a pair they leave weak pays for full-strength anchors and the dense rounds.
    # ``auto`` sets it on the plain pairs of a project with aerial images (Matcher.for_pair)
    light_first: bool = False
    # light_first: a pair whose light anchors fit fewer inliers than this keeps the light answer
    # (0: every weak pair gets the full method). ``auto`` sets it to ``anchors_suffice`` on pairs of
    # two aerial photos, which then never escalate: on brighton_beach half the exhaustive plan's
    # pairs (77 of 153) seed 15-49 inliers, photos that barely share ground, and the full method
    # cost 3.3 s on each (8x a guided pair) for 0-100 matches the model did not need
    escalate_from: int = 0
    # light_first on pairs of two aerial photos: instead of LightGlue on 1024 points, this many
    # ALIKED points per photo matched by mutual nearest neighbours, a robust F, and the matches
    # that F's epipolar lines guide (geomatch.matching.guided); 0: LightGlue's light anchors
    guided_keypoints: int = 0
    # least-squares matching of the final points in B (geomatch.features.subpixel): "auto" does it for the
    # methods that optimise (the paper's refinement stage, anchors included), "lsm" for any
    # method, "off" never
    subpixel: str = "auto"
    # recent images' features (dense maps included: a 640 px DISK fine map alone is ~150 MB), LRU,
    # bounded in bytes: a worker's memory must not grow with the project
    # (the split of GEOMATCH_CACHE_MB's default, options.cache_budget)
    cache_features_mb: float = 1024.0
    cache_anchors_mb: float = 256.0  # recent pairs' LightGlue output (soft assignments included)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose from {', '.join(METHODS)}")
        if self.sparse not in SPARSE_BACKBONES:
            raise ValueError(f"unknown sparse backbone {self.sparse!r}; choose from {SPARSE_BACKBONES}")
        if self.dense not in DENSE_BACKBONES:
            raise ValueError(f"unknown dense backbone {self.dense!r}; choose from {DENSE_BACKBONES}")
        if self.tile_crops not in ("probe", "all"):
            raise ValueError(f"unknown tile_crops {self.tile_crops!r}; choose from probe, all")
        if self.subpixel not in ("auto", "lsm", "off"):
            raise ValueError(f"unknown subpixel mode {self.subpixel!r}; choose from auto, lsm, off")

    @property
    def flags(self) -> Method:
        """The method's row in ``options.METHOD_TABLE``."""
        return METHOD_FLAGS[self.method]

    @property
    def refines_subpixel(self) -> bool:
        return self.subpixel == "lsm" or (self.subpixel == "auto" and self.flags.optimise)

    @property
    def uses_anchors(self) -> bool:
        return self.flags.anchors

    @property
    def needs_sparse(self) -> bool:
        """A LightGlue pass: for the anchors, or as the dense branch itself (``dense=lightglue``)."""
        return self.uses_anchors or (self.needs_dense and self.dense == "lightglue")

    @property
    def needs_dense(self) -> bool:
        return self.flags.dense

    @property
    def dense_keypoints(self) -> str | None:
        """The detector whose own LightGlue soft assignment is the dense branch (``disk-lightglue``
        and ``aliked-lightglue``), else None."""
        if self.needs_dense and self.dense.endswith("-lightglue"):
            return self.dense.removesuffix("-lightglue")
        return None

    @property
    def dense_maps(self) -> bool:
        """Whether the dense branch needs per-image dense maps (all dense backbones but the
        LightGlue soft assignments, which are computed per pair from keypoints)."""
        return self.needs_dense and self.dense != "lightglue" and self.dense_keypoints is None


@dataclass
class MatchResult:
    """Matches in ORIGINAL image pixels, pixel centres at integer coordinates (x right, y down).

    COLMAP puts pixel centres at +0.5: add 0.5 to both coordinates before writing keypoints there.
    """

    keypoints0: np.ndarray  # (N, 2) float32
    keypoints1: np.ndarray  # (N, 2) float32
    scores: np.ndarray  # (N,) float32
    F: np.ndarray  # (3, 3) x1^T F x0 = 0 in original pixels; zeros when fewer than 8 matches
    method: str
    image_sizes: tuple[tuple[int, int], tuple[int, int]]
    timings: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.keypoints0.shape[0])

    def save_npz(self, path: str | Path) -> None:
        np.savez(
            path,
            keypoints0=self.keypoints0,
            keypoints1=self.keypoints1,
            scores=self.scores,
            F=self.F,
            method=np.array(self.method),
            image_size0=np.array(self.image_sizes[0]),
            image_size1=np.array(self.image_sizes[1]),
        )


class _Timer:
    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.times: dict[str, float] = {}

    def __call__(self, name: str) -> _Timer:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.times[self._name] = self.times.get(self._name, 0.0) + time.perf_counter() - self._t0


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
        self._cache: OrderedDict[tuple[str, str, int | None], tuple[ImageFeatures, Prepared]] = OrderedDict()
        self.extract_calls = 0
        # anchors of recent pairs: re-matching a pair with other optimizer options (ablations,
        # a retried task) does not run LightGlue again
        self._anchors: OrderedDict[tuple[str, str, int | None, str | None], SparseMatch] = OrderedDict()
        self._variants: dict[str, Matcher] = {}  # ``auto``'s per-pair methods (for_pair)
        self._light: Matcher | None = None  # light_first's anchors (for_pair shares its variant's)
        self._full: Matcher | None = None  # light_first's matcher for the pairs the light ones leave weak

    def for_pair(self, tiled: bool, aerial_project: bool = False, aerial_pair: bool = False) -> Matcher:
        """The matcher a planned pair gets: itself, except under ``auto``, where

        - a tiled (aerial x ground) pair gets the full ``geo`` method on every crop: on the
          synthetic air-to-ground scenes it is what registers the ground views;
        - a plain pair of two aerial photos of a survey (``aerial_pair``: the plan decided their
          turns, planning.image_turns) gets ``geo`` light-first (``MatcherConfig.light_first``) by
          the guided matcher (``MatcherConfig.guided_keypoints``), never escalating to the full
          method (``escalate_from``): ~0.4 s a pair instead of ~6 s;
        - any other plain pair of a project with aerial images gets ``geo`` (the synthetic
          air-to-ground scenes' wide ground x ground baselines at low resolution need it: taking
          the light anchors first there lost 2 of 6 cameras of the test scene);
        - a pair of a ground-only project gets the light anchors alone (``sparse`` with
          :data:`AUTO_PLAIN_PAIRS`): on the real tuning photos the dense rounds tie the anchors at
          about twice their cost (docs/benchmarks.md).

        Derived once, sharing this matcher's networks and caches where the settings allow."""
        cfg = self.config
        if cfg.method == "auto":
            method = "geo" if tiled or aerial_project else "sparse"
        elif tiled and cfg.flags.optimise and cfg.anchors_suffice > 0:
            method = cfg.method
        else:
            return self
        light_first = cfg.method == "auto" and method == "geo" and not tiled and aerial_pair
        variant = f"{method}-tiled" if tiled and method != "sparse" else method
        variant += "-guided" if light_first else ""
        if variant not in self._variants:
            overrides: dict[str, Any] = dict(AUTO_PLAIN_PAIRS) if method == "sparse" else {}
            if variant.endswith("-tiled"):
                overrides["anchors_suffice"] = 0
            if light_first:
                overrides.update(
                    light_first=True, escalate_from=cfg.anchors_suffice, guided_keypoints=GUIDED_KEYPOINTS
                )
            self._variants[variant] = self.derive(method=method, **overrides)
        return self._variants[variant]

    def light(self) -> Matcher:
        """``light_first``'s matcher: the light anchors of a ground-only project's pairs, or with
        ``guided_keypoints`` the guided matcher's (:meth:`match_guided`)."""
        if self._light is None:
            overrides: dict[str, Any] = dict(AUTO_PLAIN_PAIRS)
            if self.config.guided_keypoints:
                overrides["max_keypoints"] = self.config.guided_keypoints
            self._light = self.derive(method="sparse", light_first=False, **overrides)
        return self._light

    def turn_score(self, image0: np.ndarray, image1: np.ndarray) -> int:
        """How well ``image1`` matches ``image0`` as given, to rank quarter turns: the guided
        matcher's seed F inliers (:meth:`seed_inliers`) where this matcher guides, else the
        LightGlue matches (:meth:`anchor_count`)."""
        if self.config.light_first and self.config.guided_keypoints:
            return self.light().seed_inliers(image0, image1)
        return self.anchor_count(image0, image1)

    def _seed(
        self, key0: str, key1: str, sa: SparseFeatures, sb: SparseFeatures, lightglue: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, int, str]:
        """The guided matcher's seed: (inliers in A, inliers in B, F, how many, which seed): mutual
        nearest neighbours with the ratio test, and where they fit fewer than ``anchors_suffice``
        inliers (and ``lightglue``) LightGlue on each photo's 1024 strongest points, the better.
        Only the F's inliers come back: on a weak pair they are its answer, and the rest (most of
        the matches of photos that share little) cost COLMAP's verification its longest RANSAC."""
        cfg = self.config

        def fit(
            pa: torch.Tensor, pb: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, int]:
            F, mask = estimate_fundamental(pa, pb, cfg.geo.f_estimator, cfg.geo.f_threshold)
            if mask is None:
                return pa[:0], pb[:0], F, 0
            return pa[mask], pb[mask], F, int(mask.sum())

        ia, ib, _ = mutual_ratio(sa.descriptors, sb.descriptors, SEED_RATIO)
        pa, pb, F, n = fit(sa.keypoints[ia].float(), sb.keypoints[ib].float())
        if n >= cfg.anchors_suffice or not lightglue:
            return pa, pb, F, n, "nn"
        a, b = _strongest(sa, GUIDED_LIGHTGLUE_POINTS), _strongest(sb, GUIDED_LIGHTGLUE_POINTS)
        lg = self._match_anchors(key0, key1, a, b)
        qa, qb, F2, n2 = fit(a.keypoints[lg.idx_a].float(), b.keypoints[lg.idx_b].float())
        return (qa, qb, F2, n2, "lightglue") if n2 > n else (pa, pb, F, n, "nn")

    @torch.inference_mode()
    def seed_inliers(self, image0: np.ndarray, image1: np.ndarray) -> int:
        """The inliers of the mutual-nearest-neighbour seed's F alone (no LightGlue): a cheap,
        sharp rank of a pair's quarter turns (a wrong turn fits a handful)."""
        key0, key1 = image_key(image0), image_key(image1)
        sa = self.features(image0, key0)[self.config.sparse].sparse
        sb = self.features(image1, key1)[self.config.sparse].sparse
        assert sa is not None and sb is not None
        return self._seed(key0, key1, sa, sb, lightglue=False)[3]

    @torch.inference_mode()
    def match_guided(self, image0: np.ndarray, image1: np.ndarray) -> MatchResult:
        """The pair by geomatch.matching.guided: a seed F, then the matches its epipolar lines
        guide. ``stats["f_inliers"]`` is the seed's: below ``anchors_suffice`` the seed's matches
        are the answer (no guided pass), and the caller decides whether the full method runs."""
        cfg = self.config
        timer = _Timer(self.device)
        key0, key1 = image_key(image0), image_key(image1)
        with timer("features0"):
            sa = self.features(image0, key0)[cfg.sparse].sparse
        with timer("features1"):
            sb = self.features(image1, key1)[cfg.sparse].sparse
        assert sa is not None and sb is not None
        prep0, prep1 = self._prepared(image0, key0), self._prepared(image1, key1)
        with timer("seed"):
            pa, pb, F, n, how = self._seed(key0, key1, sa, sb, lightglue=True)
        stats: dict[str, Any] = {"f_inliers": n, "seed": how}
        if F is None or n < cfg.anchors_suffice:
            return self._result(pa, pb, torch.ones(pa.shape[0]), F, prep0, prep1, stats, timer)
        with timer("guided"):
            ia, ib, sim = mutual_ratio(
                sa.descriptors, sb.descriptors, GUIDED_RATIO, (F, sa.keypoints, sb.keypoints, cfg.geo.tau)
            )
            ga, gb = sa.keypoints[ia].float(), sb.keypoints[ib].float()
        with timer("merge"):
            F_guided, _ = estimate_fundamental(ga, gb, cfg.geo.f_estimator, cfg.geo.f_threshold)
        stats["guided"] = int(ia.numel())
        return self._result(ga, gb, sim, F if F_guided is None else F_guided, prep0, prep1, stats, timer)

    def derive(self, **overrides: Any) -> Matcher:
        """A matcher with other options that shares this one's networks and feature cache.

        Sharing is valid because cached features depend only on the image, the backbone and
        the resolution, all part of the cache key; the sparse matcher is shared only when its
        own options are unchanged.
        """
        other = Matcher(self.config, **overrides)
        a, b = self.config, other.config
        if other.device != self.device or (a.max_keypoints, a.loftr_weights) != (
            b.max_keypoints,
            b.loftr_weights,
        ):
            return other  # networks built differently: nothing to share
        other._extractors = self._extractors
        other._cache = self._cache
        if (a.sparse, a.lightglue_threshold) == (b.sparse, b.lightglue_threshold):
            other._probe = self._probe

        def lightglue(c: MatcherConfig) -> tuple[object, ...]:
            return (
                c.sparse,
                c.lightglue_threshold,
                c.lightglue_depth_confidence,
                c.lightglue_width_confidence,
            )

        if lightglue(a) == lightglue(b):
            other._sparse = self._sparse
            other._anchors = self._anchors
            if a.dense_keypoints == b.dense_keypoints:
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

    # -- the caches' public interface ---------------------------------------------------------
    def _feature_key(self, key: str, backbone: str, dense: bool) -> tuple[str, str, int | None]:
        return (key, f"{backbone}+dense" if dense else backbone, self.config.resize)

    def has_features(self, key: str, backbone: str, dense: bool) -> bool:
        """Whether the in-memory cache holds ``backbone``'s features (``dense``: with dense maps)
        of the image whose pixel hash is ``key``, at this matcher's resolution."""
        return self._feature_key(key, backbone, dense) in self._cache

    def put_features(
        self, key: str, backbone: str, dense: bool, feats: ImageFeatures, image: np.ndarray
    ) -> None:
        """Put features computed elsewhere (a store on disk) into the in-memory cache, as if
        :meth:`features` had computed them from ``image`` (pixel hash ``key``)."""
        self._cache[self._feature_key(key, backbone, dense)] = (
            feats,
            prepare(image, self.config.resize, self.device),
        )
        self._evict()

    def clear_caches(self, features: bool = True, anchors: bool = True) -> None:
        """Empty the per-image feature cache and / or the recent pairs' anchors (shared with the
        matchers :meth:`derive` made)."""
        if features:
            self._cache.clear()
        if anchors:
            self._anchors.clear()

    # -- features, once per image -------------------------------------------------------------
    def features(self, image: np.ndarray, key: str | None = None) -> dict[str, ImageFeatures]:
        key = key or image_key(image)
        out: dict[str, ImageFeatures] = {}
        prepared: Prepared | None = None
        for name, dense in self.needed_extractors():
            ck = self._feature_key(key, name, dense)
            if ck in self._cache:
                self._cache.move_to_end(ck)
                out[name] = self._cache[ck][0]
                continue
            if prepared is None:
                prepared = prepare(image, self.config.resize, self.device)
            with torch.inference_mode():
                feats = self.extractor(name).extract(prepared.tensor, dense=dense)
            self.extract_calls += 1
            self._cache[ck] = (feats, prepared)
            self._evict()
            out[name] = feats
        return out

    def cache_nbytes(self) -> int:
        """Bytes the feature cache holds (features and the prepared network inputs)."""
        return sum(_entry_nbytes(*e) for e in self._cache.values())

    def _evict(self) -> None:
        trim_lru(self._cache, self.config.cache_features_mb, lambda e: _entry_nbytes(*e), keep=1)

    def _prepared(self, image: np.ndarray, key: str) -> Prepared:
        for (k, _, r), (_, prep) in self._cache.items():
            if k == key and r == self.config.resize:
                return prep
        return prepare(image, self.config.resize, self.device)

    def _match_anchors(
        self, key0: str, key1: str, sa: SparseFeatures, sb: SparseFeatures, dense: bool = False
    ) -> SparseMatch:
        """One LightGlue pass, cached per pair: the anchors' (``dense`` False) or the dense
        branch's second detector's (``dense`` True)."""
        ak = (key0, key1, self.config.resize, self.config.dense_keypoints if dense else None)
        if ak in self._anchors:
            self._anchors.move_to_end(ak)
            return self._anchors[ak]
        out = (self.dense_lightglue if dense else self.sparse_matcher).match(sa, sb)
        self._anchors[ak] = out
        trim_lru(self._anchors, self.config.cache_anchors_mb, lambda m: m.nbytes(), keep=0)
        return out

    # -- one pair --------------------------------------------------------------------------
    @torch.inference_mode()
    def anchor_count(self, image0: np.ndarray, image1: np.ndarray) -> int:
        """How many matches LightGlue alone finds (features and result cached like the anchors, so
        a later :meth:`match` of the same pair reuses them): how a quarter-turn probe ranks turns."""
        probe = self if self.config.method == "sparse" else self.derive(method="sparse")
        key0, key1 = image_key(image0), image_key(image1)
        sa = probe.features(image0, key0)[self.config.sparse].sparse
        sb = probe.features(image1, key1)[self.config.sparse].sparse
        assert sa is not None and sb is not None
        return int(probe._match_anchors(key0, key1, sa, sb).idx_a.numel())

    def probe_count(self, image0: np.ndarray, image1: np.ndarray) -> int:
        """LightGlue matches among each image's ``probe_keypoints`` strongest keypoints, pruned: a
        cheap rank of the quarter turns. Only the sparse features are extracted (a turned image the
        probe rejects never gets dense maps); nothing is cached beyond those features."""
        return int(self.probe_points(image0, image1)[0].shape[0])

    @torch.inference_mode()
    def probe_points(self, image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cheap probe's matches (see :meth:`probe_count`) in each image's original pixels:
        where two images overlap, at a fraction of a full-strength LightGlue call's cost."""
        probe = self if self.config.method == "sparse" else self.derive(method="sparse")
        key0, key1 = image_key(image0), image_key(image1)
        sa = _strongest(probe.features(image0, key0)[self.config.sparse].sparse, self.config.probe_keypoints)
        sb = _strongest(probe.features(image1, key1)[self.config.sparse].sparse, self.config.probe_keypoints)
        m = self.probe_matcher.match(sa, sb)
        return (
            probe._prepared(image0, key0).to_original(sa.keypoints[m.idx_a].float()),
            probe._prepared(image1, key1).to_original(sb.keypoints[m.idx_b].float()),
        )

    @torch.inference_mode()
    def match(self, image0: np.ndarray, image1: np.ndarray) -> MatchResult:
        cfg = self.config
        if cfg.light_first and cfg.flags.optimise and cfg.anchors_suffice > 0:
            lm = self.light()
            light = lm.match_guided(image0, image1) if cfg.guided_keypoints else lm.match(image0, image1)
            inliers = light.stats.get("f_inliers", 0)
            if inliers >= cfg.anchors_suffice or inliers < cfg.escalate_from:
                light.stats["anchors_suffice"] = "light"
                return light
            if self._full is None:  # derived once: the dense head is built once
                self._full = self.derive(light_first=False, escalate_from=0)
            full = self._full.match(image0, image1)
            full.timings = {"light": light.timings.get("total", 0.0), **full.timings}
            full.timings["total"] += full.timings["light"]
            return full
        timer = _Timer(self.device)
        key0, key1 = image_key(image0), image_key(image1)
        with timer("features0"):
            f0 = self.features(image0, key0)
        with timer("features1"):
            f1 = self.features(image1, key1)
        prep0, prep1 = self._prepared(image0, key0), self._prepared(image1, key1)
        stats: dict[str, Any] = {}

        parts_a: list[torch.Tensor] = []
        parts_b: list[torch.Tensor] = []
        parts_s: list[torch.Tensor] = []
        anchors = None
        lg: SparseMatch | None = None
        if cfg.needs_sparse:
            sa, sb = f0[cfg.sparse].sparse, f1[cfg.sparse].sparse
            assert sa is not None and sb is not None
            with timer("anchors"):
                lg = self._match_anchors(key0, key1, sa, sb)
            if cfg.uses_anchors:
                anchors = (sa.keypoints[lg.idx_a].float(), sb.keypoints[lg.idx_b].float(), lg.scores)
                stats["anchors"] = int(lg.idx_a.numel())
        if anchors is not None and cfg.flags.optimise and cfg.anchors_suffice > 0:
            with timer("anchors"):
                F_anchors, inliers = _anchor_fit(anchors, cfg)
            if inliers >= cfg.anchors_suffice:  # the answer sparse gives: the anchors and their F
                stats["anchors_suffice"] = True
                return self._result(*anchors, F_anchors, prep0, prep1, stats, timer)

        if cfg.needs_dense and cfg.dense == "lightglue":
            assert lg is not None
            dense_a, dense_b, dense_s = self._dense_from_assignment(
                lg, f0[cfg.sparse].sparse, f1[cfg.sparse].sparse, anchors, stats, timer
            )
        elif cfg.dense_keypoints is not None:
            da, db = f0[cfg.dense_keypoints].sparse, f1[cfg.dense_keypoints].sparse
            assert da is not None and db is not None
            with timer("dense_lightglue"):
                lgd = self._match_anchors(key0, key1, da, db, dense=True)
            dense_a, dense_b, dense_s = self._dense_from_assignment(lgd, da, db, anchors, stats, timer)
        elif cfg.needs_dense:
            dense_a, dense_b, dense_s = self._dense_from_maps(f0, f1, anchors, stats, timer)
        if cfg.uses_anchors and anchors is not None:
            parts_a.append(anchors[0])
            parts_b.append(anchors[1])
            parts_s.append(anchors[2].float())
        if cfg.needs_dense:
            parts_a.append(dense_a.float())
            parts_b.append(dense_b.float())
            parts_s.append(dense_s)

        with timer("merge"):
            pa, pb, ps = _merge(parts_a, parts_b, parts_s, DEDUP_RADIUS, self.device)
        if cfg.refines_subpixel and pa.shape[0]:
            with timer("subpixel"):
                pb, moved = refine_points(prep0.tensor, prep1.tensor, pa, pb)
            stats["subpixel_refined"] = int(moved.sum())
        with timer("merge"):
            F_net, f_mask = estimate_fundamental(pa, pb, cfg.geo.f_estimator, cfg.geo.f_threshold)
            stats["f_inliers"] = 0 if f_mask is None else int(f_mask.sum())
            if cfg.flags.optimise and cfg.final_check and F_net is not None:
                keep = sampson_distance(F_net, pa, pb) <= cfg.geo.tau
                stats["final_check_removed"] = int((~keep).sum())
                pa, pb, ps = pa[keep], pb[keep], ps[keep]
            if cfg.flags.optimise and anchors is not None and cfg.min_anchor_support > 0:
                support = 0
                if F_net is not None and anchors[0].shape[0]:
                    d = sampson_distance(F_net, anchors[0].to(F_net.device), anchors[1].to(F_net.device))
                    support = int((d <= cfg.geo.tau).sum())
                stats["anchor_support"] = support
                if support < cfg.min_anchor_support:
                    stats["rejected"] = f"{support} anchors support the pair's F"
                    pa, pb, ps = pa[:0], pb[:0], ps[:0]
        return self._result(pa, pb, ps, F_net, prep0, prep1, stats, timer)

    def _result(
        self,
        pa: torch.Tensor,
        pb: torch.Tensor,
        ps: torch.Tensor,
        F_net: torch.Tensor | None,
        prep0: Prepared,
        prep1: Prepared,
        stats: dict[str, Any],
        timer: _Timer,
    ) -> MatchResult:
        """Points and F from the network inputs' frames to the original images'."""
        F = np.zeros((3, 3))
        if F_net is not None:
            F = scale_fundamental(F_net.double().cpu().numpy(), prep0.from_original(), prep1.from_original())
        timer.times["total"] = sum(timer.times.values())
        return MatchResult(
            keypoints0=prep0.to_original(pa).astype(np.float32),
            keypoints1=prep1.to_original(pb).astype(np.float32),
            scores=ps.detach().float().cpu().numpy().astype(np.float32),
            F=F,
            method=self.config.method,
            image_sizes=(prep0.original_size, prep1.original_size),
            timings=timer.times,
            stats=stats,
        )

    def _dense_from_maps(
        self,
        f0: dict[str, ImageFeatures],
        f1: dict[str, ImageFeatures],
        anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
        stats: dict[str, Any],
        timer: _Timer,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Detector-free branch on per-image dense maps: coarse cells, rounds, window refinement."""
        cfg = self.config
        da, db = f0[cfg.dense].dense, f1[cfg.dense].dense
        assert da is not None and db is not None
        head = self.dense_head
        F_prior = None
        with timer("dense_coarse"):
            pair = head.coarse_pair(da, db)
        stats["coarse_cells"] = (int(pair.feats_a.shape[0]), int(pair.feats_b.shape[0]))
        if not cfg.flags.optimise:
            with timer("dense_coarse"):
                ci, cj, conf = dense_mutual_nn(
                    pair.feats_a, pair.feats_b, pair.temperature, cfg.geo.theta_c, cfg.geo.memory_budget_mb
                )
        else:
            geo = cfg.geo if cfg.flags.anchor_init else replace(cfg.geo, use_anchors=False)
            with timer("optimizer"):
                cm = geometry_aware_matching(
                    pair.feats_a, pair.feats_b, pair.grid_a, pair.grid_b, pair.temperature, anchors, geo
                )
            ci, cj, conf = cm.idx_a, cm.idx_b, cm.confidence
            # the refinement's epipolar prior needs a precise F: the anchors' (keypoint
            # precision), not a fit on 8-px cell centres
            if cm.init == "anchors":
                F_prior = cm.initial_fundamental
            stats.update(
                init=cm.init, history=cm.history, candidates=cm.candidates, refits=cm.refits_accepted
            )
        stats["coarse_matches"] = int(ci.numel())
        with timer("refine"):
            ref = head.refine(da, db, pair, ci, cj, F_prior)
        return ref.points_a, ref.points_b, conf.float()

    def _dense_from_assignment(
        self,
        lg: SparseMatch,
        sa: SparseFeatures | None,
        sb: SparseFeatures | None,
        anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
        stats: dict[str, Any],
        timer: _Timer,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Keypoints as cells: LightGlue's soft assignment over every keypoint is P_c. The rounds
        recover matches LightGlue was unsure of (repeated patterns, weak texture) that the
        geometry confirms, at keypoint precision, so there is nothing to refine."""
        cfg = self.config
        assert sa is not None and sb is not None
        if lg.assignment is None:
            if sa.keypoints.shape[0] and sb.keypoints.shape[0]:
                raise ValueError(
                    "dense='lightglue' needs LightGlue's full soft assignment: "
                    "set lightglue_width_confidence=-1 (no point pruning)"
                )
            z = torch.zeros(0, 2, device=self.device)
            return z, z.clone(), torch.zeros(0, device=self.device)
        source = Assignment(lg.assignment)
        ga, gb = sa.keypoints.float(), sb.keypoints.float()
        stats["coarse_cells"] = (source.n, source.m)
        with timer("optimizer"):
            if not cfg.flags.optimise:
                ci, cj, conf = mutual_nn(source, cfg.geo.theta_c)
            else:
                geo = cfg.geo if cfg.flags.anchor_init else replace(cfg.geo, use_anchors=False)
                cm = optimise(source, ga, gb, anchors, geo, geo.f_threshold)
                ci, cj, conf = cm.idx_a, cm.idx_b, cm.confidence
                stats.update(
                    init=cm.init, history=cm.history, candidates=cm.candidates, refits=cm.refits_accepted
                )
        stats["coarse_matches"] = int(ci.numel())
        return ga[ci], gb[cj], conf.float()


def _anchor_fit(
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor], cfg: MatcherConfig
) -> tuple[torch.Tensor | None, int]:
    """The F fitted to the anchors alone (the optimiser's own starting point, and what ``sparse``
    answers with) and its inlier count; no fit when there are fewer anchors than the threshold."""
    if anchors[0].shape[0] < cfg.anchors_suffice:
        return None, 0
    F, mask = estimate_fundamental(anchors[0], anchors[1], cfg.geo.f_estimator, cfg.geo.f_threshold)
    return F, 0 if mask is None else int(mask.sum())


def _strongest(f: SparseFeatures | None, n: int) -> SparseFeatures:
    assert f is not None
    if f.keypoints.shape[0] <= n:
        return f
    idx = torch.topk(f.scores, n).indices
    return SparseFeatures(f.keypoints[idx], f.descriptors[idx], f.scores[idx], f.image_size)


def _entry_nbytes(feats: ImageFeatures, prep: Prepared) -> int:
    return feats.nbytes() + prep.tensor.numel() * prep.tensor.element_size()


def _merge(
    parts_a: list[torch.Tensor],
    parts_b: list[torch.Tensor],
    parts_s: list[torch.Tensor],
    radius: float,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Concatenate in priority order; a later match whose point in A or in B falls in an
    already-used ``radius`` cell is a duplicate of an earlier one and is dropped."""
    if not parts_a:
        z = torch.zeros(0, 2, device=device)
        return z, z.clone(), torch.zeros(0, device=device)
    pa, pb, ps = torch.cat(parts_a), torch.cat(parts_b), torch.cat(parts_s)
    if len(parts_a) == 1 or radius <= 0 or pa.shape[0] == 0:
        return pa, pb, ps
    keep = torch.arange(pa.shape[0], device=pa.device)
    for pts in (pa, pb):
        q = torch.floor(pts[keep] / radius).long()
        _, first = first_unique(q[:, 0] * 1_000_003 + q[:, 1])
        keep = keep[torch.sort(first).values]
    return pa[keep], pb[keep], ps[keep]


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
    return matcher.for_pair(tiled=False).match(a, b)


def config_from_options(**options: Any) -> MatcherConfig:
    geo_fields = set(GeoOptions.__dataclass_fields__)
    refine_fields = set(RefineOptions.__dataclass_fields__)
    geo_kw = {k: options.pop(k) for k in list(options) if k in geo_fields}
    refine_kw = {k: options.pop(k) for k in list(options) if k in refine_fields}
    unknown = set(options) - set(MatcherConfig.__dataclass_fields__)
    if unknown:
        raise TypeError(f"unknown matching options: {', '.join(sorted(unknown))}")
    base = MatcherConfig(**options)
    return replace(base, geo=replace(base.geo, **geo_kw), refine=replace(base.refine, **refine_kw))
