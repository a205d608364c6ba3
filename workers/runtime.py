"""What a worker keeps between steps: matchers (networks loaded once per process and thread)
and recently decoded images. Thread-local because the Matcher's caches are not thread-safe and
the embedded runner may use several threads."""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from geomatch.matcher import Matcher

    from .context import Context

_local = threading.local()
MAX_MATCHERS = 2  # distinct option sets kept per thread (each holds its own feature LRU)
MAX_IMAGES = 24


def matcher(ctx: Context, options: dict[str, Any]) -> Matcher:
    from geomatch.options import DEFAULTS
    from geomatch.steps import FeatureStore, build_matcher

    method, resize = (
        options.get("method", DEFAULTS["method"]),
        options.get("resize", DEFAULTS["resize"]) or None,
    )
    key = (method, resize, ctx.settings.device)
    cache: OrderedDict[tuple[Any, ...], Matcher] = _local.__dict__.setdefault("matchers", OrderedDict())
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    cap = ctx.settings.feature_cache_mb
    store = FeatureStore(ctx.storage.features_dir, cap * 1024 * 1024 if cap > 0 else 0)
    # the thread's memory budget, split over the matchers it may keep: 3/4 features, 1/4 anchors
    share = ctx.settings.cache_mb / MAX_MATCHERS
    m = build_matcher(
        store,
        method=method,
        resize=resize,
        device=ctx.settings.device,
        cache_features_mb=0.75 * share,
        cache_anchors_mb=0.25 * share,
    )
    cache[key] = m
    while len(cache) > MAX_MATCHERS:
        cache.popitem(last=False)
    return m


def image(path: Path) -> np.ndarray:
    from geomatch.imageio import read_image

    cache: OrderedDict[tuple[str, float], np.ndarray] = _local.__dict__.setdefault("images", OrderedDict())
    key = (str(path), path.stat().st_mtime)
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    img = read_image(path)
    cache[key] = img
    while len(cache) > MAX_IMAGES:
        cache.popitem(last=False)
    return img
