"""What a worker keeps between steps: matchers (networks loaded once per process and thread)
and recently decoded images. Thread-local because the Matcher's caches are not thread-safe and
the embedded runner may use several threads."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from geomatch.imagefolder import PhotoScale
    from geomatch.matching.matcher import Matcher
    from geomatch.memory import CacheBudget

    from .context import StepContext

_local = threading.local()
MAX_MATCHERS = 2  # distinct option sets kept per thread (each holds its own feature LRU)


def job_options(stored: Mapping[str, Any]) -> dict[str, Any]:
    """A job's stored options (or a pair's) as the library takes them, once per step: the
    defaults of those missing, resize 0 as full size, camera as share_camera
    (``geomatch.options.resolve``)."""
    from geomatch.options import PROJECT_OPTIONS, resolve

    return resolve(stored, PROJECT_OPTIONS)


def _matchers() -> OrderedDict[tuple[Any, ...], Matcher]:
    cache: OrderedDict[tuple[Any, ...], Matcher] = _local.__dict__.setdefault("matchers", OrderedDict())
    return cache


def _matcher_key(ctx: StepContext, options: Mapping[str, Any]) -> tuple[Any, ...]:
    return (options["method"], options["resize"], ctx.settings.device)


def built_matcher(ctx: StepContext, options: Mapping[str, Any]) -> Matcher | None:
    """The thread's matcher for ``options`` if one was built, without building it (loading a
    network is the plan's to decide: prepare.plan_project)."""
    return _matchers().get(_matcher_key(ctx, options))


def matcher(ctx: StepContext, options: Mapping[str, Any]) -> Matcher:
    """The thread's matcher for resolved ``options`` (:func:`job_options`)."""
    from geomatch.features.store import FeatureStore
    from geomatch.matching.stored import build_matcher

    method, resize = options["method"], options["resize"]
    key = _matcher_key(ctx, options)
    cache = _matchers()
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    cap = ctx.settings.feature_cache_mb
    store = FeatureStore(ctx.storage.features_dir, cap * 1024 * 1024 if cap > 0 else 0)
    budget = _budget(ctx)  # the thread's GEOMATCH_CACHE_MB, shared by the matchers it may keep
    m = build_matcher(
        store,
        method=method,
        resize=resize,
        device=ctx.settings.device,
        cache_features_mb=budget.features_mb,
        cache_anchors_mb=budget.anchors_mb,
    )
    cache[key] = m
    while len(cache) > MAX_MATCHERS:
        cache.popitem(last=False)
    return m


def release() -> None:
    """Empty this thread's matcher and image caches and hand the memory back: a reconstruct step
    needs none of them, and its mapper's memory grows with the project, so the caches would only
    add to its peak. The networks stay loaded; the next match step refills the caches from the
    feature store."""
    from geomatch.memory import return_freed_memory

    for m in _local.__dict__.get("matchers", {}).values():
        m.clear_caches()
    images = getattr(_local, "images", None)
    if images is not None:
        images.clear()
    return_freed_memory()


def image(ctx: StepContext, path: Path, max_side: int | None = None) -> np.ndarray:
    """A decoded image (``max_side``: a larger photo at that size), from the thread's byte-bounded
    LRU when it was read lately (a tiled aerial image meets all its ground partners in a row)."""
    from geomatch.imageio import read_image
    from geomatch.memory import ByteLRU

    cache: ByteLRU[tuple[str, float, int | None], np.ndarray] | None = getattr(_local, "images", None)
    if cache is None:
        cache = _local.images = ByteLRU(_budget(ctx).images_mb)
    key = (str(path), path.stat().st_mtime, max_side)
    img = cache.get(key)
    if img is None:
        img = read_image(path, max_side)
        cache.put(key, img)
    return img


def frame(ctx: StepContext, path: Path) -> tuple[np.ndarray, PhotoScale | None]:
    """A photo as the pipeline matches it, at most the working size (imageio.WORKING_SIDE, as
    ``geomatch run`` reads it), and how its matches map back to the photo's own pixels."""
    from geomatch.imagefolder import photo_size, to_photo
    from geomatch.imageio import WORKING_SIDE

    return image(ctx, path, WORKING_SIDE), to_photo(photo_size(path), WORKING_SIDE)


def images_mb(ctx: StepContext) -> float:
    """The thread's budget of decoded images (part of GEOMATCH_CACHE_MB), for a plan's reads."""
    return _budget(ctx).images_mb


def _budget(ctx: StepContext) -> CacheBudget:
    from geomatch.memory import cache_budget

    return cache_budget(ctx.settings.cache_mb, MAX_MATCHERS)
