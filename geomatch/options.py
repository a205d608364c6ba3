"""Every option of geomatch, defined once: name, type, choices, default and help.

The command line (``geomatch.cli``, ``service.cli``), the REST schemas, the use cases' checks, the gRPC
conversion and the workers all derive from this module, so adding a method or changing a default
is one edit here (``tests/test_options.py`` proves that the CLI, the REST schema and the proto
agree with it). It imports the standard library only: the API process reads it without torch.

Methods are rows of flags (:data:`METHOD_TABLE`), the paper's ablations:

``sparse``        anchors only (detector + LightGlue);
``dense``         dense mutual-NN + refinement, no optimisation;
``concat``        anchors naively concatenated to ``dense``;
``geo-noanchor``  optimisation initialised from the top half of the dense matches;
``geo``           the full method: anchors initialise F, dense matches are re-weighted;
``auto``          what benchmarks best for the project's kind: ``geo`` for every pair of a project
                  with aerial images (the synthetic air-to-ground scenes), lighter anchors for a
                  ground-only project (real ground photos, docs/benchmarks.md). Its row carries
                  the anchors' flags; ``matching.variants.for_pair`` picks the method per pair.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

# exit statuses of every ``geomatch`` command
EXIT_FAILED, EXIT_BAD_INPUT, EXIT_UNREACHABLE = 1, 2, 3


class OptionError(ValueError):
    """A value outside an option's type, range or choices; the message names the option."""


class PairSpecError(ValueError):
    """The pair specification is malformed or names unknown images."""


# -- methods -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Method:
    name: str
    anchors: bool  # sparse anchors (detector + LightGlue) are matched and kept in the output
    dense: bool  # the detector-free dense branch runs
    optimise: bool  # the geometry-aware rounds re-weight the dense matches (and the final F check)
    anchor_init: bool  # the anchors initialise F (else the top half of the dense matches do)
    help: str


METHOD_TABLE: tuple[Method, ...] = (
    Method("sparse", True, False, False, False, "anchors only (detector + LightGlue)"),
    Method("dense", False, True, False, False, "dense mutual-NN + refinement, no optimisation"),
    Method("concat", True, True, False, False, "anchors concatenated to the dense matches"),
    Method("geo-noanchor", False, True, True, False, "optimisation initialised from the dense matches"),
    Method("geo", True, True, True, True, "the full method: anchors initialise F, dense re-weighted"),
    Method("auto", True, False, False, False, "geo with aerial images, else light anchors"),
)
METHODS: tuple[str, ...] = tuple(m.name for m in METHOD_TABLE)
METHOD_FLAGS: dict[str, Method] = {m.name: m for m in METHOD_TABLE}

# -- other vocabularies ------------------------------------------------------------------------
SPARSE_BACKBONES = ("aliked", "disk")
# ``lightglue``: the anchors' own LightGlue soft assignment (keypoints as cells);
# ``disk-lightglue`` / ``aliked-lightglue``: a second detector's keypoints matched by its own
# LightGlue, whose soft assignment is the dense branch's P_c (other points than the anchors')
DENSE_BACKBONES = ("disk", "aliked", "loftr", "lightglue", "disk-lightglue", "aliked-lightglue")
MAPPERS = ("auto", "incremental", "global")
# ``auto``: COLMAP's incremental mapper below this many images, its global mapper from it on
# (sfm/mapping.pick_mapper; the measurements behind it: docs/benchmarks.md, "A thousand photos")
GLOBAL_MAPPER_IMAGES = 100
TILING = ("auto", "on", "off")
CAMERAS = ("auto", "per-image")
ORTHO = ("off", "on")  # the map (geomatch.ortho) after mapping
CAPTURES = ("aerial", "ground", "auto")  # how an uploaded image was taken (auto: EXIF/XMP decides)
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"})


# -- pair kinds: the one table ------------------------------------------------------------------
def all_pairs(n: int) -> int:
    """Pairs of every two of ``n`` images: what ``exhaustive`` plans."""
    return n * (n - 1) // 2


def _next_k(n: int, k: int) -> int:
    return all_pairs(n) if k >= n - 1 else k * n - k * (k + 1) // 2


def _k_nearest(n: int, k: int) -> int:
    """Each image with min(K, n-1) partners and a pair has two images: at least n*min(K, n-1)/2."""
    return -(-n * min(k, max(n - 1, 0)) // 2)


@dataclass(frozen=True)
class PairKind:
    """One way of choosing the pairs to match. What names the kinds derives from
    :data:`PAIR_KINDS`: the grammar and its messages, the CLI help, the REST pattern
    (service.http.schemas), the plan-size arithmetic, whether the plan needs a matcher; the planner is
    ``planning.PLANNERS[name]``; the proto's comments, the console's hint and the README are checked
    against it (tests/test_pair_kinds.py)."""

    name: str
    takes_k: bool  # written ``name:K`` (K >= 1, and may join a union); else it stands alone
    means: str  # what it plans, in a few words
    fewest: Callable[[int, int], int]  # (images, K) -> the fewest pairs its plan can have
    exact: bool  # ``fewest`` is the plan's exact count (nothing but the names decides it)
    needs_matcher: bool = False  # the plan reads the images' features


PAIR_KINDS: tuple[PairKind, ...] = (
    PairKind("auto", False, "exhaustive, or gps:K for a larger project with GPS", lambda n, k: 0, False),
    PairKind("exhaustive", False, "every two images", lambda n, k: all_pairs(n), True),
    PairKind(
        "sequential", True, "each image with the next K by name (a video, a flight line)", _next_k, True
    ),
    PairKind(
        "retrieval",
        True,
        "each image with its K nearest by appearance, and every aerial x ground pair",
        _k_nearest,
        False,
        needs_matcher=True,
    ),
    PairKind("gps", True, "each image with its K nearest by GPS", _k_nearest, False),
)
PAIR_KIND: dict[str, PairKind] = {k.name: k for k in PAIR_KINDS}
PAIR_KIND_SPELLINGS = tuple(k.name + (":K" if k.takes_k else "") for k in PAIR_KINDS)
# "auto | exhaustive | sequential:K | retrieval:K | gps:K": the proto's and the console's words
PAIR_SPEC_LIST = " | ".join(PAIR_KIND_SPELLINGS)
PAIR_SPEC_HELP = PAIR_SPEC_LIST + " | a union such as gps:K+retrieval:K"
PAIR_SPEC_WORDS = ", ".join(PAIR_KIND_SPELLINGS[:-1]) + " or " + PAIR_KIND_SPELLINGS[-1]
_SPEC = re.compile(r"([a-z][a-z0-9-]*)(?::(\d+))?")  # a kind of PAIR_KIND, looked up when read


# COLMAP registers an image from 30 PnP inliers, a count made for sparse SIFT matches. With dense
# matches a genuinely overlapping image has hundreds of 2D-3D correspondences, while a repeated
# texture gives a few dozen that agree with each other and can register an image at a wrong pose.
# A higher bar (60) makes such an image wait until its true correspondences are triangulated, but
# also leaves true views of a small scene unregistered (docs/pipeline.md, "Coherent wrong pairs on
# the air-to-ground scenes"), so the default stays COLMAP's 30 until the matcher stops producing
# those coherent wrong pairs; 60 is one option away (--min-pose-inliers 60).
MIN_POSE_INLIERS = 30
# ...except in a project with tiled aerial x ground pairs, where an image often cannot reach 30:
# an aerial image's tracks with ground photos are its crops' keypoints, its pairs with other aerial
# images are matched on the whole image, and the two share few keypoints. Its model then falls
# apart into an aerial-led half and a ground-led half, each right. 20 joins the halves of the
# synthetic sweep's split tuning scenes; 15, the inliers that verify a pair, places more cameras
# wrongly (docs/benchmarks.md, "`geomatch run` over many seeds")
TILED_MIN_POSE_INLIERS = 20
# ...and once that model is built (and joined, sfm/modeljoin.py), the images it still lacks get one
# more pass at 15: COLMAP considers an image only from as many visible points as its PnP minimum,
# structure-less registration included, and an aerial image whose whole-image keypoints meet the
# model's crop keypoints at 15-19 points is otherwise never tried; late, a weak registration no
# longer steers the rest of the model
LEFTOVER_MIN_POSE_INLIERS = 15


# -- options -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Option:
    name: str  # the key in Python, JSON and protobuf; the flag is --name-with-dashes
    type: type
    default: Any
    help: str
    choices: tuple[str, ...] = ()
    low: float | None = None  # inclusive range the service accepts (the library accepts any)
    high: float | None = None
    zero: str = ""  # when set, 0 is accepted as well and means this ("full size", "off")
    unit: str = ""

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def check(self, value: Any) -> Any:
        """The value, validated as the service accepts it; OptionError otherwise."""
        if self.name == "pairs":
            if not isinstance(value, str):
                raise OptionError(f"pairs must be a spec or a list of name pairs, not {value!r}")
            try:
                parse_plan(value)
            except PairSpecError:
                raise OptionError(
                    f"bad pairs {value!r}: use {PAIR_SPEC_WORDS} (K >= 1), a union of the kinds with "
                    "a K joined by + or a list of name pairs"
                ) from None
            return value.strip()
        if self.choices:
            if value not in self.choices:
                raise OptionError(f"{self.name} must be one of {', '.join(self.choices)}, not {value!r}")
            return str(value)
        if self.type is int:
            ok = isinstance(value, int) and not isinstance(value, bool) and self._in_range(value)
            if not ok:
                zero = f"0 ({self.zero}) or " if self.zero else ""
                raise OptionError(
                    f"{self.name} must be {zero}an integer from {self.low:g} to {self.high:g}{self.unit}, "
                    f"not {value!r}"
                )
            return value
        if self.type is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool) and self._in_range(value)
            if not ok:
                span = f"from {self.low:g} to {self.high:g}{self.unit}"
                raise OptionError(f"{self.name} must be a number {span}, not {value!r}")
            return float(value)
        return value

    def _in_range(self, value: float) -> bool:
        if self.zero and value == 0:
            return True
        return (self.low is None or value >= self.low) and (self.high is None or value <= self.high)


_OPTIONS: tuple[Option, ...] = (
    # matching
    Option(
        "method",
        str,
        "auto",
        "matching method (the paper's ablations, or auto: geo where it pays)",
        choices=METHODS,
    ),
    Option(
        "resize",
        int,
        640,
        "longer image side fed to the networks (0: keep)",
        low=64,
        high=8192,
        zero="full size",
    ),
    Option("device", str, "auto", "auto, cpu, cuda, cuda:1 ..."),
    Option("sparse", str, "aliked", "anchor backbone (+LightGlue)", choices=SPARSE_BACKBONES),
    Option("dense", str, "disk", "dense backbone", choices=DENSE_BACKBONES),
    Option("loftr_weights", str, None, "LoFTR checkpoint (for --dense loftr)"),
    # the optimizer (the paper's defaults, section 3.4)
    Option("tau", float, 10.0, "Sampson distance threshold, px^2"),
    Option("iterations", int, 10, "optimisation rounds"),
    Option("w", float, 1.2, "update weight"),
    Option("theta_iter", float, 0.01, "mutual-NN threshold inside the rounds"),
    Option("theta_c", float, 0.2, "final mutual-NN threshold"),
    Option("memory_budget_mb", float, 256.0, "working memory of one streamed block, MiB"),
    # the pipeline (geomatch run, match jobs)
    Option("pairs", str, "auto", PAIR_SPEC_HELP),
    Option("tiling", str, "auto", "tile aerial x ground pairs (auto: those pairs only)", choices=TILING),
    Option(
        "snap_radius",
        float,
        1.5,
        "keypoint consolidation radius, network px (0: off)",
        low=0,
        high=50,
        unit=" (network pixels)",
    ),
    Option("camera", str, "auto", "auto: one camera per EXIF device; per-image", choices=CAMERAS),
    # reconstruction
    Option(
        "mapper",
        str,
        "auto",
        "COLMAP mapper (auto: incremental below GLOBAL_MAPPER_IMAGES images, global from it)",
        choices=MAPPERS,
    ),
    Option(
        "min_pose_inliers",
        int,
        0,
        "2D-3D inliers the incremental mapper needs to register an image (0: COLMAP's 30, "
        "20 in a project with tiled aerial x ground pairs)",
        low=3,
        high=10000,
        zero=f"auto: COLMAP's own {MIN_POSE_INLIERS}, {TILED_MIN_POSE_INLIERS} in a project with tiled pairs",
    ),
    # the map after mapping (geomatch.ortho)
    Option(
        "ortho",
        str,
        "off",
        "the map: a DSM and an orthophoto (Cloud-Optimized GeoTIFFs) of a georeferenced model "
        "(on: made after mapping; a model without GPS or GCPs gets none, and the summary says why)",
        choices=ORTHO,
    ),
    Option(
        "ortho_gsd",
        float,
        0.0,
        "the orthophoto's pixel on the ground, metres (0: the survey's GSD at the photos' working size)",
        low=0.005,
        high=10.0,
        zero="the survey's GSD",
        unit=" m",
    ),
)
OPTIONS: dict[str, Option] = {o.name: o for o in _OPTIONS}
DEFAULTS: dict[str, Any] = {o.name: o.default for o in _OPTIONS}

# which surface offers which options (each a subset of OPTIONS, in this order)
MATCH_OPTIONS = ("method", "resize", "device", "sparse", "dense", "loftr_weights")
OPTIMIZER_OPTIONS = ("tau", "iterations", "w", "theta_iter", "theta_c", "memory_budget_mb")
RUN_OPTIONS = ("pairs", "tiling", "snap_radius", "mapper", "min_pose_inliers", "camera", "ortho", "ortho_gsd")
# a project's configuration and a match job's options (REST, gRPC, the use cases)
PROJECT_OPTIONS = (
    "pairs",
    "method",
    "resize",
    "tiling",
    "snap_radius",
    "camera",
    "mapper",
    "min_pose_inliers",
    "ortho",
    "ortho_gsd",
)
# the options a reconstruct job takes from its match job or its project (the rest are matching's)
RECONSTRUCT_OPTIONS = ("mapper", "min_pose_inliers", "ortho", "ortho_gsd")
PAIR_OPTIONS = ("method", "resize", "tiling")  # one pair matched on its own (gRPC MatchPair)


def defaults(names: Iterable[str]) -> dict[str, Any]:
    return {n: DEFAULTS[n] for n in names}


def check(name: str, value: Any) -> Any:
    """``value`` validated as option ``name``; OptionError (a ValueError) names what is wrong."""
    return OPTIONS[name].check(value)


def add_arguments(parser: Any, names: Iterable[str], server: bool = False, **help: str) -> None:
    """argparse flags for ``names``. ``server``: the value is the server's when not given (default
    None, the help says which). ``help`` overrides an option's help text on this command."""
    for name in names:
        o = OPTIONS[name]
        text = help.get(name, o.help)
        kw: dict[str, Any] = {"type": o.type, "default": None if server else o.default}
        if o.choices:
            kw["choices"] = o.choices
        if o.choices == ORTHO:  # a switch: the flag alone turns it on (geomatch run --ortho)
            kw["nargs"], kw["const"] = "?", "on"
        if server:
            text += f" (default: the server's, {o.default})"
        parser.add_argument(o.flag, help=text, **kw)


def resolve(values: Mapping[str, Any], names: Iterable[str] = ()) -> dict[str, Any]:
    """Option values as the library takes them, made here once for every surface (the CLI,
    ``pipeline.RunOptions.of``, a worker's job options): the default of each of ``names`` that
    ``values`` lacks; ``resize`` 0 as None, full size (the service stores and echoes 0 as the
    client sent it); ``camera`` as ``share_camera`` (None: one camera per EXIF device, False: one
    per image), the argument of ``ColmapDatabase.add_image``. Other keys pass as they are."""
    out = {n: DEFAULTS[n] for n in names if n not in values} | dict(values)
    if "resize" in out:
        out["resize"] = out["resize"] or None
    if "camera" in out:
        out["share_camera"] = False if out.pop("camera") == "per-image" else None
    return out


def given(args: argparse.Namespace, names: Iterable[str]) -> dict[str, Any]:
    """The values of ``names`` in parsed arguments, by option name."""
    return {n: getattr(args, n) for n in names}


# -- the pair-spec grammar ---------------------------------------------------------------------
def parse_plan(spec: str) -> list[tuple[str, int]]:
    """A plan: one spec, or a union of parts with a K joined by ``+`` (``gps:10+retrieval:5``: a
    drone project's neighbours by position plus those by appearance); a kind without a K
    (``exhaustive``, ``auto``) stands alone. A kind named twice is the union of both, which is its
    larger K (``gps:3+gps:4`` is ``gps:4``): the service's published pattern cannot tell repeats
    apart, so the library gives them a meaning rather than refusing what the schema allows."""
    parts = [parse_spec(p) for p in spec.strip().split("+")] if spec.strip() else [parse_spec(spec)]
    if len(parts) > 1:
        for kind, _ in parts:
            if not PAIR_KIND[kind].takes_k:
                raise PairSpecError(f"bad pair spec {spec!r}: {kind} stands alone, not in a union")
    largest: dict[str, int] = {}
    for kind, k in parts:
        largest[kind] = max(k, largest.get(kind, 0))
    return list(largest.items())


def parse_spec(spec: str) -> tuple[str, int]:
    """One part of a plan (:func:`parse_plan` reads unions): a kind without a K -> (kind, 0);
    ``kind:K`` -> (kind, K >= 1)."""
    m = _SPEC.fullmatch(spec.strip())
    kind = PAIR_KIND.get(m.group(1)) if m else None
    if m is None or kind is None or kind.takes_k != (m.group(2) is not None):
        raise PairSpecError(f"bad pair spec {spec!r}: use {PAIR_SPEC_WORDS}")
    if not kind.takes_k:
        return kind.name, 0
    k = int(m.group(2))
    if k < 1:
        raise PairSpecError(f"bad pair spec {spec!r}: K must be at least 1")
    return kind.name, k


def plan_needs_matcher(spec: str) -> bool:
    """Whether planning ``spec`` reads the images' features (a worker then loads its networks)."""
    return any(PAIR_KIND[kind].needs_matcher for kind, _ in parse_plan(spec))


# -- the size of a plan, before it is made ------------------------------------------------------
def fewest_pairs(spec: str, n: int) -> tuple[int, bool]:
    """The fewest pairs a plan of ``spec`` can have over ``n`` images, by arithmetic alone (no
    image read), and whether that is the plan's exact count (``PairKind.fewest``, ``.exact``;
    ``auto`` depends on the images' GPS, pairs.auto_pairs: 0 here). A union has at least what its
    largest part has."""
    parts = parse_plan(spec)
    fewest = max((PAIR_KIND[kind].fewest(n, k) for kind, k in parts), default=0)
    exact = len(parts) == 1 and PAIR_KIND[parts[0][0]].exact
    return fewest, exact
