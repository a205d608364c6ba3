"""The pipeline's stages: the library's one pipeline API, as hloc's modules are.

plan -> extract -> match one pair and write it (:func:`run_pair`: :func:`match`, :func:`write`)
-> reconstruct (``geomatch.sfm.mapping.reconstruct``) -> export, each a function with explicit
inputs that returns a record.
``pipeline.run`` is a loop over them in one process; the worker steps (``workers.jobs``,
``workers.pairmatch``) call the same functions, one image or one pair per task, under their
locks. The decisions every caller shares
are made here once: which images are aerial (:func:`captures`, :func:`aerial_set`), which pairs
are tiled and in what order (:func:`plan`), which are matched already (:func:`unmatched`: a pair
stored with zero matches is matched too), how a tiled pair is matched (:func:`match`) and the snap
radius in original pixels (:func:`snap_radius`).

For queues, which run a task in whichever process picks it up, possibly twice:

- :class:`FeatureStore`: features on disk, keyed by (pixel hash, backbone, resolution, options),
  so any process computes an image's features once and every later task, job or worker reads
  them back instead of running the networks again (DESIGN.md, data flow step 3);
- :class:`StoredFeaturesMatcher`: a :class:`Matcher` whose per-image features go through that
  store (the in-memory LRU stays in front of it).
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import logging
import os
import tempfile
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from .features.base import DenseFeatures, ImageFeatures, SparseFeatures
from .geo import gps, survey
from .geo.gps import GpsFixes
from .geometry import estimate_fundamental, fundamental_from_matches
from .imageio import image_key, read_image
from .lru import ByteLRU
from .matching.matcher import Matcher, MatcherConfig, MatchResult
from .matching.rotation import PROBE_MARGIN, best_turn, points_back, quarter_turn
from .matching.tiling import SELECT_MIN_PROBE, Crop, TiledMatches, five_crops, match_tiled, select_crops
from .matching.turnhint import HINT_MIN_INLIERS, SiftHints, TurnHint
from .metadata import ImageMeta
from .options import DEFAULTS, IMAGE_SUFFIXES
from .sfm import pairs as pairing
from .sfm.colmapdb import ColmapDatabase, PairWrite, seeded_verification
from .sfm.pairs import Pair
from .sfm.retrieval import vlad

log = logging.getLogger(__name__)


class FeatureStore:
    """Content-addressed feature files. Safe for many processes: files appear by atomic rename,
    and a file that cannot be read back is a miss, not an error."""

    def __init__(self, root: str | Path, max_bytes: int | None = None, writable: bool = True) -> None:
        self.root = Path(root)
        self.max_bytes = max_bytes  # None: unbounded; 0: the store is off
        # read-only: a reader of someone else's folder (localizing against a run) takes its
        # features and leaves the folder as it found it, file times included
        self.writable = writable
        self.hits = 0  # features read back, for every matcher sharing the store

    @property
    def enabled(self) -> bool:
        return self.max_bytes != 0

    def path(self, key: str, backbone: str, dense: bool, config: MatcherConfig) -> Path:
        # every option that changes what an extractor returns is part of the address
        options = repr((config.max_keypoints, config.loftr_weights)).encode()
        digest = hashlib.sha256(options).hexdigest()[:8]
        tag = f"{backbone}{'+dense' if dense else ''}-r{config.resize}-{digest}"
        return self.root / tag / key[:2] / f"{key}.pt"

    def load(self, path: Path, device: torch.device) -> ImageFeatures | None:
        if not self.enabled or not path.is_file():
            return None
        try:
            state = torch.load(path, map_location=device, weights_only=True)
            feats = _from_state(state)
        except Exception:  # a torn or foreign file: recompute (and overwrite) rather than fail the task
            return None
        if self.writable:
            os.utime(path)  # least recently used goes first when pruning
        self.hits += 1
        return feats

    def save(self, path: Path, feats: ImageFeatures) -> None:
        if not self.enabled or not self.writable:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                torch.save(_to_state(feats), f)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        if self.max_bytes:
            self.prune(self.max_bytes)

    def prune(self, max_bytes: int) -> int:
        """Delete least recently used files until the store fits; returns how many went."""
        files = []
        for p in self.root.rglob("*.pt"):
            try:
                st = p.stat()
            except FileNotFoundError:  # pruned by another process meanwhile
                continue
            files.append((st.st_mtime, st.st_size, p))
        total = sum(s for _, s, _ in files)
        removed = 0
        for _, size, p in sorted(files):
            if total <= max_bytes:
                break
            p.unlink(missing_ok=True)
            total -= size
            removed += 1
        return removed


def _to_state(f: ImageFeatures) -> dict[str, Any]:
    state: dict[str, Any] = {}
    if f.sparse is not None:
        s = f.sparse
        state["sparse"] = {
            "keypoints": s.keypoints.cpu(),
            "descriptors": s.descriptors.cpu(),
            "scores": s.scores.cpu(),
            "image_size": list(s.image_size),
        }
    if f.dense is not None:
        d = f.dense
        state["dense"] = {
            "coarse": d.coarse.cpu(),
            "fine": None if d.fine is None else d.fine.cpu(),
            "stride": d.stride,
            "image_size": list(d.image_size),
            "heatmap": None if d.heatmap is None else d.heatmap.cpu(),
            "extra": {k: v.cpu() if isinstance(v, torch.Tensor) else v for k, v in d.extra.items()},
        }
    return state


def _from_state(state: dict[str, Any]) -> ImageFeatures:
    sparse = dense = None
    if state.get("sparse") is not None:
        s = state["sparse"]
        sparse = SparseFeatures(s["keypoints"], s["descriptors"], s["scores"], tuple(s["image_size"]))
    if state.get("dense") is not None:
        d = state["dense"]
        dense = DenseFeatures(
            coarse=d["coarse"],
            fine=d["fine"],
            stride=int(d["stride"]),
            image_size=tuple(d["image_size"]),
            heatmap=d["heatmap"],
            extra=dict(d["extra"]),
        )
    return ImageFeatures(sparse=sparse, dense=dense)


class StoredFeaturesMatcher(Matcher):
    """A Matcher whose per-image features are read from / written to a :class:`FeatureStore`.

    The Matcher's in-memory cache stays the first level; entries read from disk are put into it
    (:meth:`Matcher.put_features`), so ``match`` finds them as if computed.
    """

    def __init__(self, config: MatcherConfig, store: FeatureStore) -> None:
        super().__init__(config)
        self.store = store

    def derive(self, **overrides: Any) -> Matcher:
        """As :meth:`Matcher.derive`, still reading and writing the same store."""
        other = super().derive(**overrides)
        stored = StoredFeaturesMatcher.__new__(StoredFeaturesMatcher)
        stored.__dict__.update(other.__dict__)
        stored.store = self.store
        return stored

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


def run_feature_store(root: Path, writable: bool = True) -> FeatureStore | None:
    """The feature store a run keeps in its output folder (``OUT/features``, bounded in bytes),
    or None when GEOMATCH_RUN_FEATURES_MB is 0."""
    from .options import run_feature_store_bytes

    cap = run_feature_store_bytes()
    return FeatureStore(root, cap, writable) if cap > 0 else None


def stored(config: MatcherConfig, store: FeatureStore | None) -> Matcher:
    return StoredFeaturesMatcher(config, store) if store is not None else Matcher(config)


def build_matcher(store: FeatureStore | None = None, **options: Any) -> Matcher:
    """A matcher from pipeline-style options (``method``, ``resize``, ``device``, optimizer fields)."""
    from .matching.matcher import config_from_options

    return stored(config_from_options(**options), store)


# -- input -------------------------------------------------------------------------------------
class PipelineError(ValueError):
    """Bad input to a run: no images, unknown names, bad pair spec."""


def list_images(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise PipelineError(f"{folder}: not a directory")
    names = sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if len(names) < 2:
        raise PipelineError(f"{folder}: found {len(names)} image(s); need at least 2")
    return names


class Images:
    """Decoded images of a folder, as many as ``budget_mb`` holds (least recently used go first):
    a 12 MP photo decodes to 36 MB, so a count bound would be a gigabyte on real projects."""

    def __init__(self, folder: Path, budget_mb: float = 256.0) -> None:
        self.folder = Path(folder)
        self._cache: ByteLRU[str, np.ndarray] = ByteLRU(budget_mb)

    def __getitem__(self, name: str) -> np.ndarray:
        img = self._cache.get(name)
        if img is None:
            img = read_image(self.folder / name)
            self._cache.put(name, img)
        return img

    def nbytes(self) -> int:
        return self._cache.nbytes()

    def __len__(self) -> int:
        return len(self._cache)


# -- plan ----------------------------------------------------------------------------------------
def captures(
    names: Sequence[str], aerial_names: Sequence[str] | None = None, aerial_glob: str | None = None
) -> dict[str, str]:
    """How each image was taken (aerial, ground, auto), as ``geomatch run`` is told: an explicit
    list of aerial images, or a glob over the relative path or the file name, makes every image
    aerial or ground; neither leaves each to its metadata (auto)."""
    if aerial_names is not None:
        unknown = sorted(set(aerial_names) - set(names))
        if unknown:
            raise PipelineError(f"aerial list names images not in the folder: {', '.join(unknown[:5])}")
        chosen = set(aerial_names)
        return {n: "aerial" if n in chosen else "ground" for n in names}
    if aerial_glob is not None:
        return {
            n: "aerial"
            if fnmatch.fnmatch(n, aerial_glob) or fnmatch.fnmatch(Path(n).name, aerial_glob)
            else "ground"
            for n in names
        }
    return {n: "auto" for n in names}


def aerial_set(
    captures: Mapping[str, str],
    metas: Mapping[str, ImageMeta],
    enu: Mapping[str, np.ndarray] | None = None,
) -> set[str]:
    """The aerial images: those captured ``aerial``, and those ``auto`` whose EXIF/XMP says so
    (silent metadata means ground). ``metas`` is read for the ``auto`` images only.

    A drone survey whose camera writes GPS but no XMP (a compact camera on a drone) says nothing
    per photo, but its track does: when every image is ``auto``, none says it is on the ground,
    none says it is aerial, and the GPS fixes (``enu``) in capture order trace a survey flight
    (geomatch.geo.survey.is_survey_track), every image of the project is aerial. ``--aerial``
    (a glob or list, even one that matches nothing) decides instead."""
    out = {n for n, c in captures.items() if c == "aerial" or (c == "auto" and metas[n].aerial_hint)}
    if (
        not out
        and enu
        and all(c == "auto" for c in captures.values())
        and all(metas[n].aerial_hint is None for n in captures)
        and survey.is_survey_track(list(captures), enu)
    ):
        return set(captures)
    return out


@dataclass(frozen=True)
class PlanInputs:
    """What the planners of a plan's parts read (one spec's parts share it)."""

    names: list[str]
    kinds: set[str]  # the plan's kinds: a union's parts may leave an image to another part
    aerial: set[str]
    gps_enu: Mapping[str, np.ndarray]
    footprints: Mapping[str, np.ndarray] | None
    matcher: Matcher | None
    images: Images
    progress: bool


def _gps_planner(p: PlanInputs, k: int) -> list[tuple[str, str]]:
    unlocated_all = "retrieval" not in p.kinds  # else retrieval pairs the images without a fix
    return pairing.gps_neighbours(p.names, p.gps_enu, k, unlocated_all, footprints=p.footprints)


def _retrieval_planner(p: PlanInputs, k: int) -> list[tuple[str, str]]:
    assert p.matcher is not None  # options.PairKind.needs_matcher: the caller built one
    descriptors = global_descriptors(p.matcher, p.images, p.names, p.progress)
    return pairing.nearest_neighbours(descriptors, p.names, k) + pairing.cross_view(p.names, p.aerial)


# the planner of each kind of options.PAIR_KINDS that plans by itself (``auto`` chooses between
# the others: pairs.auto_pairs); tests/test_pair_kinds.py holds the two tables together
PLANNERS: dict[str, Callable[[PlanInputs, int], list[tuple[str, str]]]] = {
    "exhaustive": lambda p, k: pairing.exhaustive(p.names),
    "sequential": lambda p, k: pairing.sequential(p.names, k),
    "retrieval": _retrieval_planner,
    "gps": _gps_planner,
}


def plan(
    image_dir: Path,
    names: Sequence[str],
    aerial: set[str],
    spec: str = DEFAULTS["pairs"],
    pairs_list: Sequence[Sequence[str]] | None = None,
    tiling: str = DEFAULTS["tiling"],
    matcher: Matcher | None = None,
    images: Images | None = None,
    progress: bool = False,
    fixes: GpsFixes | None = None,
    metas: Mapping[str, ImageMeta] | None = None,
) -> list[Pair]:
    """The pairs to match (``pairs_list``, else ``spec``, a union of its parts), tiled where
    ``tiling`` says, in a cache-friendly order: all pairs of one aerial image (its five crops)
    together. With ``matcher`` the plain pairs with an aerial side get their quarter turn once per
    image (:func:`image_turns`), else each pair probes its own. ``retrieval:K`` needs ``matcher``
    (global descriptors come from its sparse features); ``gps:K`` pairs by the ``fixes`` (images
    without one: see pairs.gps_neighbours), by look point, and by shared ground where ``metas``
    give both images a footprint (gps.plan_points, gps.footprints); ``auto`` is exhaustive or
    ``gps:K`` by the project's size and fixes (pairs.auto_pairs)."""
    gps_enu: Mapping[str, np.ndarray] = {}
    footprints: Mapping[str, np.ndarray] | None = None
    if fixes is not None:
        gps_enu = gps.plan_points(fixes, metas) if metas is not None else fixes.enu
        footprints = gps.footprints(fixes, metas) if metas is not None else None
    names = list(names)
    if pairs_list is not None:
        raw = pairing.explicit(pairs_list, names)
    else:
        parts = pairing.parse_plan(spec)
        raw = []
        if parts == [("auto", 0)]:
            raw, _ = pairing.auto_pairs(names, gps_enu, footprints)
            parts = []
        inputs = PlanInputs(
            names,
            {kind for kind, _ in parts},
            aerial,
            gps_enu,
            footprints,
            matcher,
            images or Images(image_dir),
            progress,
        )
        for kind, k in parts:
            raw += PLANNERS[kind](inputs, k)
    planned = pairing.finalize(raw, aerial, tiling)
    # a survey (every image aerial) gets its turns once per image and its pairs the guided matcher;
    # a project with ground images keeps the per-pair probe and geo (Matcher.for_pair)
    if matcher is not None and aerial >= set(names) and any(p.rotate and not p.tiled for p in planned):
        # ranked as a plain pair of two aerial photos is first matched (auto: the guided seed)
        probe = matcher.for_pair(tiled=False, aerial_project=True, aerial_pair=True)
        guided = probe.config.light_first and probe.config.guided_keypoints > 0
        turns = image_turns(
            planned,
            probe.turn_score,
            images or Images(image_dir),
            gps_enu,
            progress,
            sure=TURN_SURE_SEED if guided else TURN_SURE,
            hint=SiftHints().hint,
        )
        planned = pairing.with_turns(planned, turns)
    return sorted(planned, key=lambda p: (not p.tiled, p.name0 if p.aerial_first else p.name1, p.key))


# an image's turn is decided on its first probed pair when a turn scores at least TURN_SURE
# LightGlue matches (a wrong turn gets 10-75 on the real surveys) or TURN_SURE_SEED inliers of the
# guided matcher's seed F, else when TURN_VOTES pairs agree on a turn with PROBE_MARGIN times the
# runner-up's score; at most TURN_PROBES of its pairs to images already decided are probed
TURN_SURE = 100
TURN_SURE_SEED = 50
TURN_VOTES = 2
TURN_PROBES = 3
TURN_MIN_MATCHES = 20  # fewer probe matches on the best turn: the pair does not vote


def turn_scores(
    score: Callable[[np.ndarray, np.ndarray], int],
    fixed: np.ndarray,
    moving: np.ndarray,
    first: int,
    sure: int,
) -> list[int]:
    """``score(fixed, moving turned t)`` for the quarter turns t, ``first`` first, then a half turn
    more (a line flown back), then the other two, stopping at a ``sure`` score (the turns not
    tried score 0)."""
    scores = [0, 0, 0, 0]
    for step in (0, 2, 1, 3):
        t = (first + step) % 4
        scores[t] = score(fixed, quarter_turn(moving, t))
        if scores[t] >= sure:
            break
    return scores


def image_turns(
    planned: Sequence[Pair],
    score: Callable[[np.ndarray, np.ndarray], int],
    images: Images,
    enu: Mapping[str, np.ndarray],
    progress: bool = False,
    sure: int = TURN_SURE,
    hint: Callable[[str, np.ndarray, str, np.ndarray], TurnHint] | None = None,
) -> dict[str, int]:
    """Each aerial photo's quarter turn (np.rot90) into one frame for the project, decided once
    per image instead of once per pair: the image with the most planned partners is the frame;
    every other one is scored (``score``: Matcher.turn_score) at the four turns against its nearest
    partners already decided (the photo taken before or after it, else by GPS distance). A pair
    then matches with each image at its own turn (one turned copy per image, so features once),
    unprobed. An image whose probes do not settle keeps the per-pair probe on its pairs. With
    ``hint`` (SiftHints.hint: rotation-invariant, one cheap extraction per photo) a pair the hint
    finds no overlap in is not probed and costs the image none of its probes, and the turn the hint
    reads from the pair is scored first: the score still decides.

    Why not the photos' own headings (DJI XMP gimbal yaw, or the direction of travel between
    GPS fixes): on the real surveys they do not say how the pixels are turned. brighton_beach's
    XMP says its return lines were flown 180 deg round, but their photos are not turned at all
    (112 F-inliers at no turn, 9 at a half turn); caliterra's return lines are turned by a half
    turn on some pairs and a quarter turn on others (the camera yaws against the track)."""
    partners: dict[str, list[Pair]] = {}
    for p in planned:
        if p.rotate and not p.tiled:
            partners.setdefault(p.name0, []).append(p)
            partners.setdefault(p.name1, []).append(p)
    if not partners:
        return {}

    # file names (a camera's counter) are the capture order: a photo and the next one taken
    # overlap most and share a turn along a flight line, more surely than GPS neighbours (a
    # compact camera's fixes are tens of metres off, and the nearest fix can be on the next line)
    rank = {n: i for i, n in enumerate(sorted(partners))}

    def distance(p: Pair) -> tuple[bool, float]:
        d = float("inf")
        if p.name0 in enu and p.name1 in enu:
            d = float(np.linalg.norm(np.asarray(enu[p.name0])[:2] - np.asarray(enu[p.name1])[:2]))
        return (abs(rank[p.name0] - rank[p.name1]) != 1, d)

    # once per pair, not once per pair per decision: the loop below looks at every candidate
    # pair each time it decides an image
    order = {p.key: distance(p) for ps in partners.values() for p in ps}

    root = max(sorted(partners), key=lambda n: len(partners[n]))
    turns = {root: 0}
    tried: set[tuple[str, str]] = set()
    probed: dict[str, int] = {}  # pairs probed per image: at most TURN_PROBES
    votes: dict[str, dict[int, int]] = {n: {} for n in partners}
    bar = tqdm(total=len(partners) - 1, desc="quarter turns", disable=not progress, leave=False)
    while True:
        # the undecided image taken next to a decided one, else the nearest, goes next against
        # that partner: the frame grows outwards from the root through the pairs most likely to
        # overlap, so the partner's own turn is usually the image's and one turned copy is scored
        options = [
            (order[p.key], p.key, n, p)
            for n in partners
            if n not in turns and probed.get(n, 0) < TURN_PROBES
            for p in partners[n]
            if p.key not in tried and (p.name1 if p.name0 == n else p.name0) in turns
        ]
        if not options:
            break
        _, _, n, p = min(options)
        tried.add(p.key)
        known = p.name1 if p.name0 == n else p.name0
        first = turns[known]
        if hint is not None:
            h = hint(known, images[known], n, images[n])
            log.debug("turn hint %s -> %s: %s", known, n, h)
            if h.inliers < HINT_MIN_INLIERS:
                continue  # the two share nothing: four turned copies would score noise
            first = (turns[known] + h.turn) % 4
        probed[n] = probed.get(n, 0) + 1
        # scored in the frame: the partner as it will be matched (its features are reused), the
        # image first at the hinted turn or else the partner's, then the half turn of a line flown
        # back; a turn with a sure score is the answer without trying the rest
        counts = turn_scores(score, quarter_turn(images[known], turns[known]), images[n], first, sure)
        best, runner_up = sorted(counts, reverse=True)[:2]
        log.debug("turn probe %s -> %s: %s", known, n, counts)
        if best < TURN_MIN_MATCHES or (best < sure and best < PROBE_MARGIN * max(runner_up, 1)):
            continue
        t = int(np.argmax(counts))
        votes[n][t] = votes[n].get(t, 0) + 1
        if best >= sure or votes[n][t] >= TURN_VOTES:
            turns[n] = t
            bar.update()
    bar.close()
    return turns


def plan_in_words(
    spec: str, names: Sequence[str], fixes: GpsFixes | None, metas: Mapping[str, ImageMeta] | None
) -> str:
    """The plan :func:`plan` makes of ``spec``, in words: ``auto``'s choice (pairs.auto_pairs)."""
    if spec.strip() != "auto":
        return spec.strip()
    enu = gps.plan_points(fixes, metas) if fixes is not None and metas is not None else {}
    footprints = gps.footprints(fixes, metas) if fixes is not None and metas is not None else None
    return pairing.auto_pairs(list(names), enu, footprints)[1]


def global_descriptors(
    matcher: Matcher, images: Images, names: Sequence[str], progress: bool = True
) -> np.ndarray:
    sparse = matcher.derive(method="sparse")
    local = []
    for n in tqdm(names, desc="retrieval", disable=not progress, leave=False):
        feats = sparse.features(images[n])[sparse.config.sparse].sparse
        assert feats is not None
        local.append(feats.descriptors.float().cpu().numpy())
    return vlad(local)


def register(
    db: ColmapDatabase, names: Sequence[str], metas: Mapping[str, ImageMeta], share_camera: bool | None
) -> dict[str, int]:
    """Every image in the COLMAP database (a no-op for those there); their ids by name."""
    return {n: db.add_image(n, metas[n], share_camera) for n in names}


def unmatched(db: ColmapDatabase, ids: Mapping[str, int], planned: Sequence[Pair]) -> list[Pair]:
    """The planned pairs not in the database yet (a pair stored with zero matches is matched)."""
    return [p for p in planned if not db.has_pair(ids[p.name0], ids[p.name1])]


# -- extract -------------------------------------------------------------------------------------
def extract(matcher: Matcher, image: np.ndarray, full: bool = True, crops: bool = False) -> int:
    """Features of an image (and of its five tiling crops when it is the aerial side of a tiled
    pair); returns how many entries that was. With a :class:`StoredFeaturesMatcher` the image's
    land on disk for every later task. With ``tile_crops="probe"`` a crop gets its sparse
    features only, in memory (what the crop probe needs, ~0.5 s each at 640 px): its dense maps,
    ~1.4 s and ~90 MB each, are made by the pair step for the crops the probe chooses."""
    n = 0
    if full:
        matcher.features(image)
        n += 1
    if crops:
        # with the crop probe only the chosen crops get dense maps (in the pair step, which stores
        # them for the image's other partners); every crop needs its sparse features for the probe
        crop_matcher = matcher.derive(method="sparse") if matcher.config.tile_crops == "probe" else matcher
        h, w = image.shape[:2]
        for crop in five_crops(w, h):
            crop_matcher.features(crop.cut(image))
            n += 1
    return n


# -- match one pair and write it ----------------------------------------------------------------
@dataclass
class PairMatches:
    """One pair's matches, in each image's original pixels (pixel centres at integers)."""

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray
    sizes: tuple[tuple[int, int], tuple[int, int]]  # (width, height) of image0 and image1
    tiled: bool = False
    source: MatchResult | TiledMatches | None = None  # None: read back from a match cache
    crops: int = 0  # aerial crops matched (tiled pairs; 0 when read back from a match cache)

    def __len__(self) -> int:
        return int(self.keypoints0.shape[0])

    @property
    def F(self) -> np.ndarray:
        """x1^T F x0 = 0 in original pixels: the matcher's (a tiled pair's is fitted over its
        merged matches on first use; so is a pair read back from a match cache)."""
        if self.source is None:
            return fundamental_from_matches(self.keypoints0, self.keypoints1)
        return self.source.F


def match(
    matcher: Matcher,
    pair: Pair,
    image0: np.ndarray,
    image1: np.ndarray,
    cache: str | Path | None = None,
    aerial_project: bool = False,
    survey: bool = False,
) -> PairMatches:
    """One planned pair, tiled when the plan says so. ``cache``: a folder of raw pair matches
    shared by runs (benchmarks, variants), keyed by the pixels, the plan and the matcher's config.
    Under ``auto`` the pair and whether its project has aerial images decide the method
    (:meth:`Matcher.for_pair`)."""
    # two aerial photos of a survey (every image aerial): the guided matcher, turned or not yet
    aerial_pair = pair.rotate and not pair.tiled and (survey or pair.turns is not None)
    matcher = matcher.for_pair(pair.tiled, aerial_project, aerial_pair=aerial_pair)
    sizes = ((image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0]))
    path = None
    if cache:
        h = hashlib.sha256(
            repr(
                (
                    image_key(image0),
                    image_key(image1),
                    pair.tiled,
                    pair.aerial_first,
                    pair.rotate,
                    pair.turns,
                    matcher.config,
                )
            ).encode()
        )
        path = Path(cache) / f"{h.hexdigest()[:32]}.npz"
        if path.is_file():
            with np.load(path) as z:
                return PairMatches(z["k0"], z["k1"], z["scores"], sizes, pair.tiled)
    k0, k1, scores, source, crops = _match_turned(matcher, pair, image0, image1)
    out = PairMatches(k0, k1, scores, sizes, pair.tiled, source, crops)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, k0=out.keypoints0, k1=out.keypoints1, scores=out.scores)
        tmp.replace(path)
    return out


def _match_turned(
    matcher: Matcher, pair: Pair, image0: np.ndarray, image1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, MatchResult | TiledMatches | None, int]:
    """(keypoints0, keypoints1, scores, source, aerial crops matched) of the pair; with
    ``pair.turns`` (a survey) each image is matched turned into the project's frame, else with
    ``pair.rotate`` the aerial side (image1 of an untiled pair) at its best quarter turn
    (geomatch.matching.rotation); keypoints are mapped back, and the source is dropped when
    anything was turned (its F is in the turned frames)."""
    if pair.tiled:
        aerial, other = (image0, image1) if pair.aerial_first else (image1, image0)
        turns, crops = tiled_turn(matcher, aerial, other, pair.rotate)
        t = match_tiled(matcher, quarter_turn(aerial, turns), other, pair.aerial_first, crops=crops)
        if not turns:
            return t.keypoints0, t.keypoints1, t.scores, t, len(crops)
        h, w = aerial.shape[:2]
        if pair.aerial_first:
            return points_back(t.keypoints0, turns, w, h), t.keypoints1, t.scores, None, len(crops)
        return t.keypoints0, points_back(t.keypoints1, turns, w, h), t.scores, None, len(crops)
    if pair.turns is not None:  # each image in the project's frame: one turned copy, features once
        t0, t1 = pair.turns
    else:
        t0, t1 = 0, (pair_turn(matcher, image0, image1) if pair.rotate else 0)
    r = matcher.match(quarter_turn(image0, t0), quarter_turn(image1, t1))
    if not (t0 or t1):
        return r.keypoints0, r.keypoints1, r.scores, r, 0
    (h0, w0), (h1, w1) = image0.shape[:2], image1.shape[:2]
    k0, k1 = points_back(r.keypoints0, t0, w0, h0), points_back(r.keypoints1, t1, w1, h1)
    return k0, k1, r.scores, None, 0


def pair_turn(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> int:
    """The quarter turn of ``image1`` for a pair the plan left undecided: scored as the plan
    scores an image's turn (Matcher.turn_score; upright first, then the half turn, stopping at a
    sure score) where the matcher guides, else rotation.best_turn. The guided seed costs ~0.2 s a
    turn; best_turn's full-strength LightGlue calls cost ~12 s a pair on caliterra's photos."""
    if not (matcher.config.light_first and matcher.config.guided_keypoints):
        return best_turn(matcher, image0, image1)
    return int(np.argmax(turn_scores(matcher.turn_score, image0, image1, 0, TURN_SURE_SEED)))


# the probe's matches that select a tiled pair's crops must agree with one F within this many
# network pixels (the probe runs at the working size, so its points are about that coarse)
PROBE_F_PX = 2.0


def tiled_turn(
    matcher: Matcher, aerial: np.ndarray, other: np.ndarray, rotate: bool
) -> tuple[int, list[Crop]]:
    """A tiled pair's quarter turn of the aerial image (rotation.best_turn, on the whole images)
    and the crops of the turned image to match (:func:`tile_crops`).

    Ranking the turns by the crop probe instead was measured and dropped: on the demo scene it
    was not clear-cut where the whole-image probe was not either (so it only added ~15 s of crop
    features to those pairs) and once chose another turn than the anchors.
    """
    turn = best_turn(matcher, other, aerial) if rotate else 0
    return turn, tile_crops(matcher, quarter_turn(aerial, turn), other)


def crop_probe_points(matcher: Matcher, aerial: np.ndarray, other: np.ndarray) -> np.ndarray:
    """The cheap probe's matches of each of the aerial image's five crops against ``other``,
    those that agree with one F, as points of the aerial image's full frame.

    The probe runs on each crop, not on the whole aerial image: shrunk whole, the aerial image
    has lost the detail that tiling exists to give back, and on the demo scene's hard pairs it
    found too few matches (28-43) to tell where the overlap is. A crop's probe needs only its
    sparse features (shared by all of the aerial image's partners); only the chosen crops get
    dense maps and full-strength LightGlue.
    """
    h, w = aerial.shape[:2]
    crops = five_crops(w, h)
    found = [matcher.probe_points(c.cut(aerial), other) for c in crops]
    pa = np.concatenate([c.to_full(f[0]) for c, f in zip(crops, found, strict=True)])
    po = np.concatenate([f[1] for f in found])
    if len(pa) < SELECT_MIN_PROBE:
        return pa
    # threshold: PROBE_F_PX network pixels in the coarser image's original pixels, never below
    # PROBE_F_PX (an image smaller than the working size is upsampled, not made more precise)
    long_side = max(*aerial.shape[:2], *other.shape[:2])
    threshold = max(snap_radius(PROBE_F_PX, matcher.config.resize, long_side), PROBE_F_PX)
    _, mask = estimate_fundamental(torch.from_numpy(pa), torch.from_numpy(po), "magsac", threshold)
    return pa if mask is None else pa[mask.numpy()]


def tile_crops(matcher: Matcher, aerial: np.ndarray, other: np.ndarray) -> list[Crop]:
    """The aerial image's crops a tiled pair matches: with ``tile_crops="probe"`` those holding
    the crop probe's F-consistent matches (geomatch.matching.tiling.select_crops), else all five."""
    h, w = aerial.shape[:2]
    crops = five_crops(w, h)
    if matcher.config.tile_crops == "all":
        return crops
    return select_crops(crops, crop_probe_points(matcher, aerial, other))


def snap_radius(radius: float, resize: int | None, long_side: int) -> float:
    """Consolidation radius in original pixels, from ``radius`` in network pixels (as
    ``geomatch run --snap-radius``): it grows with the downscale, since a match is no more precise
    than the resolution it was found at. ``long_side``: the image's longer side."""
    if radius <= 0:
        return 0.0
    return radius * (long_side / resize if resize else 1.0)


# a tiled pair verified with fewer inliers is written without a geometry (matches kept, nothing
# for the mapper): an aerial image's crops against a street photo find a few dozen coherent wrong
# matches where the two share nothing (real drone x street pairs: 19-31 F-inliers, wrong by eye;
# synthetic scenes: 23-68), while tiled pairs that are right have had 77 and more (one right pair
# with 48 had 44 % of them wrong). COLMAP's own floor, 15, is for detector matches of plain pairs
TILED_MIN_INLIERS = 60


def write(
    db: ColmapDatabase, id0: int, id1: int, m: PairMatches, radius: float, resize: int | None
) -> PairWrite:
    """The pair into the COLMAP database (snapped within ``radius`` network pixels, verified,
    one transaction); a no-op when it is there."""
    options = seeded_verification()
    if m.tiled:
        options.min_num_inliers = TILED_MIN_INLIERS
    return db.write_pair(
        id0,
        id1,
        m.keypoints0,
        m.keypoints1,
        m.scores,
        snap_radius(radius, resize, max(m.sizes[0])),
        snap_radius(radius, resize, max(m.sizes[1])),
        options,
    )


@dataclass(frozen=True)
class PairTarget:
    """Where a matched pair is written: ``open`` opens the COLMAP database for the write, under
    whatever locks its caller holds, and yields None when the pair must not be written any more
    (a worker's job cancelled while the pair was matched); the images' ids there; the snap radius
    in network pixels."""

    open: Callable[[], AbstractContextManager[ColmapDatabase | None]]
    id0: int
    id1: int
    radius: float


@dataclass
class PairRun:
    matches: PairMatches
    written: PairWrite | None  # None: no target, or its ``open`` refused the write
    match_s: float
    write_s: float


def run_pair(
    matcher: Matcher,
    pair: Pair,
    image0: np.ndarray,
    image1: np.ndarray,
    target: PairTarget | None = None,
    cache: str | Path | None = None,
    aerial_project: bool = False,
    survey: bool = False,
) -> PairRun:
    """One planned pair matched (:func:`match`) and written into ``target`` (:func:`write`, at
    the matcher's working size): the sequence of ``geomatch run``, a worker's pair step and the
    service's two-image match (no target: nothing is kept)."""
    t0 = time.perf_counter()
    m = match(matcher, pair, image0, image1, cache, aerial_project, survey)
    t1 = time.perf_counter()
    written = None
    if target is not None:
        with target.open() as db:
            if db is not None:
                written = write(db, target.id0, target.id1, m, target.radius, matcher.config.resize)
    return PairRun(m, written, t1 - t0, time.perf_counter() - t1)


# -- export ------------------------------------------------------------------------------------------
def export(out: Path, summary: dict[str, Any], archive: bool = False) -> None:
    """``out/summary.json``; ``archive``: also ``out/model.zip`` (sparse/<i>/, COLMAP binary, and
    text for sparse/0; points.ply; summary.json)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if not archive:
        return
    tmp = out / "model.zip.tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted((out / "sparse").rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(out).as_posix())
        for name in ("points.ply", "summary.json"):
            if (out / name).is_file():
                z.write(out / name, name)
    tmp.rename(out / "model.zip")
