"""The matchers one matcher derives for its pairs, each derived once and kept in its
``variants`` (so networks and caches are built once): the project-level ``auto`` policy
(:func:`for_pair`) and ``light_first``'s two matchers (:func:`light_matcher`, :func:`full_matcher`).

:func:`for_pair` stays in matching, below the planning layer, because
:func:`geomatch.matching.matcher.match_pair` (two images alone: a plain pair) applies it too."""

from __future__ import annotations

from typing import Any, TypeVar, cast

from .config import AUTO_PLAIN_PAIRS, GUIDED_KEYPOINTS, MatcherParts

# a Matcher (or a subclass), typed by what these functions use of it: they give back its own kind
M = TypeVar("M", bound=MatcherParts)


def for_pair(matcher: M, tiled: bool, aerial_project: bool = False, aerial_pair: bool = False) -> M:
    """The matcher a planned pair gets: ``matcher`` itself, except under ``auto``, where

    - a tiled (aerial x ground) pair gets the full ``geo`` method on every crop: on the
      synthetic air-to-ground scenes it is what registers the ground views;
    - a plain pair of two aerial photos of a survey (``aerial_pair``: the plan decided their
      turns, planning.image_turns) gets ``geo`` light-first (``MatcherConfig.light_first``) by
      the guided matcher (``MatcherConfig.guided_keypoints``), never escalating to the full
      method (``escalate_from``): a fraction of the full method's cost per pair;
    - any other plain pair of a project with aerial images gets ``geo`` (the synthetic
      air-to-ground scenes' wide ground x ground baselines at low resolution need it; the light
      anchors alone lose cameras there);
    - a pair of a ground-only project gets the light anchors alone (``sparse`` with
      :data:`AUTO_PLAIN_PAIRS`): on the real tuning photos the dense rounds do not beat the
      anchors and cost more (docs/benchmarks.md, "`geo` against its anchors on ground photos").

    Outside ``auto``, a tiled pair of a method that answers with the anchors when they suffice
    gets that method with ``anchors_suffice=0`` (the full method on every crop)."""
    cfg = matcher.config
    if cfg.method == "auto":
        method = "geo" if tiled or aerial_project else "sparse"
    elif tiled and cfg.flags.optimise and cfg.anchors_suffice > 0:
        method = cfg.method
    else:
        return matcher
    light_first = cfg.method == "auto" and method == "geo" and not tiled and aerial_pair
    variant = f"{method}-tiled" if tiled and method != "sparse" else method
    variant += "-guided" if light_first else ""
    if variant not in matcher.variants:
        overrides: dict[str, Any] = dict(AUTO_PLAIN_PAIRS) if method == "sparse" else {}
        if variant.endswith("-tiled"):
            overrides["anchors_suffice"] = 0
        if light_first:
            overrides.update(
                light_first=True, escalate_from=cfg.anchors_suffice, guided_keypoints=GUIDED_KEYPOINTS
            )
        matcher.variants[variant] = matcher.derive(method=method, **overrides)
    return cast(M, matcher.variants[variant])


def light_matcher(matcher: M) -> M:
    """``light_first``'s first matcher: the light anchors of a ground-only project's pairs, or with
    ``guided_keypoints`` the guided matcher's (:func:`geomatch.matching.guided.match_guided`)."""
    if "light-first:light" not in matcher.variants:
        overrides: dict[str, Any] = dict(AUTO_PLAIN_PAIRS)
        if matcher.config.guided_keypoints:
            overrides["max_keypoints"] = matcher.config.guided_keypoints
        matcher.variants["light-first:light"] = matcher.derive(
            method="sparse", light_first=False, **overrides
        )
    return cast(M, matcher.variants["light-first:light"])


def full_matcher(matcher: M) -> M:
    """``light_first``'s matcher for the pairs the light one leaves weak: the same options at full
    strength (derived once, so its dense head is built once)."""
    if "light-first:full" not in matcher.variants:
        matcher.variants["light-first:full"] = matcher.derive(light_first=False, escalate_from=0)
    return cast(M, matcher.variants["light-first:full"])
