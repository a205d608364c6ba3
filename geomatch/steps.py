"""The pipeline one piece at a time, for callers that run each image and each pair as its own task.

``pipeline.run`` does everything in one process with one in-memory feature cache. A queue runs
one image or one pair per task, in whichever process picks it up, possibly twice (a task whose
worker died is delivered again). What this module adds for that:

- :class:`FeatureStore`: features on disk, keyed by (pixel hash, backbone, resolution, options),
  so any process computes an image's features once and every later task, job or worker reads
  them back instead of running the networks again (DESIGN.md, data flow step 3);
- :class:`StoredFeaturesMatcher`: a :class:`Matcher` whose per-image features go through that
  store (the in-memory LRU stays in front of it);
- per-stage functions (:func:`plan`, :func:`extract`, :func:`match`, :func:`snap_radius`) built
  from the existing modules, with the same behaviour as ``pipeline.run``.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import pipeline
from .features.base import DenseFeatures, ImageFeatures, SparseFeatures
from .imageio import image_key
from .matcher import Matcher, MatcherConfig
from .pairs import Pair
from .tiling import five_crops, match_tiled


class FeatureStore:
    """Content-addressed feature files. Safe for many processes: files appear by atomic rename,
    and a file that cannot be read back is a miss, not an error."""

    def __init__(self, root: str | Path, max_bytes: int | None = None) -> None:
        self.root = Path(root)
        self.max_bytes = max_bytes  # None: unbounded; 0: the store is off

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
        os.utime(path)  # least recently used goes first when pruning
        return feats

    def save(self, path: Path, feats: ImageFeatures) -> None:
        if not self.enabled:
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
        self.disk_hits = 0

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
            self.disk_hits += 1
        out = super().features(image, key)
        for name in missing:
            self.store.save(paths[name], out[name])
        return out


def build_matcher(store: FeatureStore | None = None, **options: Any) -> Matcher:
    """A matcher from pipeline-style options (``method``, ``resize``, ``device``, optimizer fields)."""
    from .matcher import config_from_options

    config = config_from_options(**options)
    return StoredFeaturesMatcher(config, store) if store is not None else Matcher(config)


def plan(
    image_dir: Path,
    names: Sequence[str],
    aerial: set[str],
    spec: str = "exhaustive",
    pairs_list: list[list[str]] | None = None,
    tiling: str = "auto",
    matcher: Matcher | None = None,
) -> list[Pair]:
    """The pairs ``pipeline.run`` would match, in its cache-friendly order. ``retrieval:K``
    needs ``matcher`` (global descriptors come from its sparse features)."""
    opts = pipeline.RunOptions(pairs=spec, pairs_list=pairs_list, tiling=tiling, progress=False)
    images = pipeline._Images(Path(image_dir))
    return pipeline.plan_pairs(list(names), aerial, opts, matcher, images)


def extract(matcher: Matcher, image: np.ndarray, full: bool = True, crops: bool = False) -> int:
    """Features of an image (and of its five tiling crops when it is the aerial side of a tiled
    pair); returns how many entries that was. With a :class:`StoredFeaturesMatcher` they land
    on disk for every later task."""
    n = 0
    if full:
        matcher.features(image)
        n += 1
    if crops:
        h, w = image.shape[:2]
        for crop in five_crops(w, h):
            matcher.features(crop.cut(image))
            n += 1
    return n


def match(
    matcher: Matcher, pair: Pair, image0: np.ndarray, image1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One planned pair, tiled when the plan says so; keypoints in each image's original pixels."""
    if pair.tiled:
        if pair.aerial_first:
            r = match_tiled(matcher, image0, image1, True)
        else:
            r = match_tiled(matcher, image1, image0, False)
        return r.keypoints0, r.keypoints1, r.scores
    m = matcher.match(image0, image1)
    return m.keypoints0, m.keypoints1, m.scores


def snap_radius(radius: float, resize: int | None, image: np.ndarray) -> float:
    """Consolidation radius in original pixels, from ``radius`` in network pixels (as
    ``geomatch run --snap-radius``): a match is no more precise than the resolution it was found at."""
    if radius <= 0:
        return 0.0
    return radius * (max(image.shape[:2]) / resize if resize else 1.0)
