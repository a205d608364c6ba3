"""Features on disk, keyed by (pixel hash, backbone, resolution, options), so that any process
computes an image's features once and every later task, job or worker reads them back instead of
running the networks again (DESIGN.md, data flow step 3).

A queue runs a task in whichever process picks it up, possibly twice: the store is safe for many
processes at once. The matcher that reads and writes it is
``geomatch.matching.stored.StoredFeaturesMatcher``.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Any, Protocol

import torch

from ..memory import run_feature_store_bytes
from .base import DenseFeatures, ImageFeatures, SparseFeatures


class ExtractionOptions(Protocol):
    """The matcher options that change what an extractor returns (``MatcherConfig``'s)."""

    @property
    def max_keypoints(self) -> int: ...

    @property
    def loftr_weights(self) -> str | None: ...

    @property
    def resize(self) -> int | None: ...


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
        self.saved = 0  # features computed and written, likewise

    @property
    def enabled(self) -> bool:
        return self.max_bytes != 0

    def path(self, key: str, backbone: str, dense: bool, config: ExtractionOptions) -> Path:
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
        self.saved += 1
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


def run_feature_store(root: Path, writable: bool = True) -> FeatureStore | None:
    """The feature store a run keeps in its output folder (``OUT/features``, bounded in bytes),
    or None when GEOMATCH_RUN_FEATURES_MB is 0."""
    cap = run_feature_store_bytes()
    return FeatureStore(root, cap, writable) if cap > 0 else None
