"""A matcher's options (:class:`MatcherConfig`), its answer for one pair (:class:`MatchResult`) and
the per-stage timer, apart from the :class:`~geomatch.matching.matcher.Matcher` that uses them so
the steps' modules (featurecache, variants, guided, dense) can share them without importing it."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from ..epipolar.geometry import scale_fundamental
from ..features.base import ImageFeatures, SparseFeatures, SparseMatch
from ..features.refine import RefineOptions
from ..imageio import Prepared
from ..options import DEFAULTS, DENSE_BACKBONES, METHOD_FLAGS, METHODS, SPARSE_BACKBONES, Method
from .optimizer import GeoOptions


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


# ``auto``'s pairs in a project without aerial images: 1024 keypoints and LightGlue's adaptive depth
# and width. On the real tuning scenes the cameras come out as with 2048 keypoints, while LightGlue,
# most of a project's time on the CPU, runs several times faster (docs/benchmarks.md)
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
    # the quarter-turn probe (geomatch.matching.rotation) only ranks four turns, so it matches each
    # image's strongest ``probe_keypoints`` with LightGlue's adaptive depth and width on: four
    # full-strength calls per pair would dominate an aerial pair on the CPU (bench/quarter_turns.py
    # compares the two probes' choices; costs in docs/benchmarks.md)
    probe_keypoints: int = 512
    # a tiled pair (geomatch.matching.tiling): "probe" matches only the aerial crops where the cheap probe's
    # F-consistent matches lie (none when it finds too few: ``tile_min_probe``), "all" the five crops
    tile_crops: str = "probe"
    # with ``tile_crops="probe"``, a tiled pair whose crop probe finds fewer than this many
    # F-consistent matches is not matched at all (0: it matches all five crops instead). On the
    # air-to-ground tuning seeds no such pair came to a verified pair, right or wrong, while
    # matching all five crops at full strength made most of such a pair's time; every pair that
    # did verify had more (bench/tiled_probes.py; the counts: docs/benchmarks.md, "`geomatch run`
    # over many seeds")
    tile_min_probe: int = 24
    # a tiled pair keeps a crop's matches only when the crop finds at least this many: a crop
    # that does not see the other photo's site still returns a few dozen coherent matches (one
    # F fits them, and several such crops merged fit one wrong F), while a crop that sees it
    # returns more (the counts behind the floor: docs/benchmarks.md, "`geomatch run` over many seeds")
    tile_crop_min_matches: int = 60
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
    # full method on every pair. The rounds are for pairs whose anchors are too few to trust: on
    # pairs with many anchor inliers, often look-alike facades, they add matches under a wrong F and
    # cost pose accuracy (docs/benchmarks.md). Tiled aerial x ground pairs always get the full
    # method (matching.variants.for_pair): there it registers views the anchors lose.
    anchors_suffice: int = 50
    # geo: try the light anchors (``sparse`` with AUTO_PLAIN_PAIRS, what a ground-only project's
    # pairs get) first, and answer with them when they fit an F with at least ``anchors_suffice``
    # inliers; only a pair they leave weak pays for full-strength anchors and the dense rounds.
    # ``auto`` sets it only on the plain pairs of two aerial photos of a survey, with
    # ``guided_keypoints`` (matching.variants.for_pair); the other plain pairs of a project with
    # aerial images get ``geo`` without it
    light_first: bool = False
    # light_first: a pair whose light anchors fit fewer inliers than this keeps the light answer
    # (0: every weak pair gets the full method). ``auto`` sets it to ``anchors_suffice`` on pairs of
    # two aerial photos, which then never escalate: a survey's weak pairs are photos that barely
    # share ground, where the full method costs several guided pairs' time for matches the model
    # does not need (docs/benchmarks.md)
    escalate_from: int = 0
    # light_first on pairs of two aerial photos: instead of LightGlue on 1024 points, this many
    # ALIKED points per photo matched by mutual nearest neighbours, a robust F, and the matches
    # that F's epipolar lines guide (geomatch.matching.guided); 0: LightGlue's light anchors
    guided_keypoints: int = 0
    # least-squares matching of the final points in B (geomatch.features.subpixel): "auto" does it for
    # the methods that optimise (the paper's refinement stage, anchors included), "lsm" for any
    # method, "off" never
    subpixel: str = "auto"
    # recent images' features (dense maps included, the largest entries: 128 values a pixel), LRU,
    # bounded in bytes: a worker's memory must not grow with the project
    # (the split of GEOMATCH_CACHE_MB's default, memory.cache_budget)
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
        if self.tile_min_probe < 0:
            raise ValueError(f"tile_min_probe must be >= 0, got {self.tile_min_probe}")
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


class StageTimer:
    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.times: dict[str, float] = {}

    def __call__(self, name: str) -> StageTimer:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.times[self._name] = self.times.get(self._name, 0.0) + time.perf_counter() - self._t0


def pair_result(
    method: str,
    matches: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    F_net: torch.Tensor | None,
    preps: tuple[Prepared, Prepared],
    stats: dict[str, Any],
    timer: StageTimer,
) -> MatchResult:
    """Points and F from the network inputs' frames to the original images'. ``matches``: the
    points in each image and their scores."""
    pa, pb, ps = matches
    prep0, prep1 = preps
    F = np.zeros((3, 3))
    if F_net is not None:
        F = scale_fundamental(F_net.double().cpu().numpy(), prep0.from_original(), prep1.from_original())
    timer.times["total"] = sum(timer.times.values())
    return MatchResult(
        keypoints0=prep0.to_original(pa).astype(np.float32),
        keypoints1=prep1.to_original(pb).astype(np.float32),
        scores=ps.detach().float().cpu().numpy().astype(np.float32),
        F=F,
        method=method,
        image_sizes=(prep0.original_size, prep1.original_size),
        timings=timer.times,
        stats=stats,
    )


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


class MatcherParts(Protocol):
    """What a matcher's helpers (variants.py: the matchers it derives; guided.py: the guided pass)
    use of a :class:`~geomatch.matching.matcher.Matcher`, typed here so that they need not import
    matcher.py, which imports them."""

    config: MatcherConfig
    device: torch.device
    variants: dict[str, Any]  # the matchers derived for its pairs, by variant name

    def derive(self, **overrides: Any) -> Any: ...

    def features(self, image: np.ndarray, key: str | None = None) -> dict[str, ImageFeatures]: ...

    def prepared(self, image: np.ndarray, key: str) -> Prepared: ...

    def match_anchors(
        self, key0: str, key1: str, sa: SparseFeatures, sb: SparseFeatures, dense: bool = False
    ) -> SparseMatch: ...
