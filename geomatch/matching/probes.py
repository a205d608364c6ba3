"""How a pair with an aerial side is matched, decided by cheap probes before the full-strength
matching: the quarter turn of its images (:func:`pair_turn`, :func:`tiled_turn`; the scoring of
turns, :func:`turn_scores`, is shared with the plan's per-image turns) and the aerial crops a
tiled pair matches (:func:`tile_crops`)."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
import torch

from ..epipolar.geometry import estimate_fundamental
from ..imageio import snap_radius
from .matcher import Matcher
from .rotation import best_turn, probe_points, quarter_turn, turn_score
from .tiling import SELECT_MIN_PROBE, Crop, five_crops, select_crops

# a turn is sure when it scores at least TURN_SURE LightGlue matches (a wrong turn gets fewer on
# the real surveys) or TURN_SURE_SEED inliers of the guided matcher's seed F: the turns not scored
# yet are not tried
TURN_SURE = 100
TURN_SURE_SEED = 50


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


def pair_turn(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> int:
    """The quarter turn of ``image1`` for a pair the plan left undecided: scored as the plan
    scores an image's turn (rotation.turn_score; upright first, then the half turn, stopping at a
    sure score) where the matcher guides, else rotation.best_turn: the guided seed costs a small
    fraction of best_turn's full-strength LightGlue calls (docs/benchmarks.md)."""
    if not (matcher.config.light_first and matcher.config.guided_keypoints):
        return best_turn(matcher, image0, image1)
    return int(np.argmax(turn_scores(partial(turn_score, matcher), image0, image1, 0, TURN_SURE_SEED)))


# the probe's matches that select a tiled pair's crops must agree with one F within this many
# network pixels (the probe runs at the working size, so its points are about that coarse)
PROBE_F_PX = 2.0


def tiled_turn(
    matcher: Matcher, aerial: np.ndarray, other: np.ndarray, rotate: bool
) -> tuple[int, list[Crop]]:
    """A tiled pair's quarter turn of the aerial image (rotation.best_turn, on the whole images)
    and the crops of the turned image to match (:func:`tile_crops`).

    The turns are ranked on the whole images, not by the crop probe: where the whole-image probe
    is not clear-cut the crop probe is not either, so it would only add crop features to those
    pairs (docs/benchmarks.md).
    """
    turn = best_turn(matcher, other, aerial) if rotate else 0
    return turn, tile_crops(matcher, quarter_turn(aerial, turn), other)


def crop_probe_points(matcher: Matcher, aerial: np.ndarray, other: np.ndarray) -> np.ndarray:
    """The cheap probe's matches of each of the aerial image's five crops against ``other``,
    those that agree with one F, as points of the aerial image's full frame.

    The probe runs on each crop, not on the whole aerial image: shrunk whole, the aerial image
    has lost the detail that tiling exists to give back, and on the demo scene's hard pairs it
    found too few matches to tell where the overlap is. A crop's probe needs only its
    sparse features (shared by all of the aerial image's partners); only the chosen crops get
    dense maps and full-strength LightGlue.
    """
    h, w = aerial.shape[:2]
    crops = five_crops(w, h)
    found = [probe_points(matcher, c.cut(aerial), other) for c in crops]
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
    the crop probe's F-consistent matches (geomatch.matching.tiling.select_crops), none when the
    probe finds fewer than ``tile_min_probe`` (MatcherConfig says why), else all five."""
    h, w = aerial.shape[:2]
    crops = five_crops(w, h)
    if matcher.config.tile_crops == "all":
        return crops
    points = crop_probe_points(matcher, aerial, other)
    if len(points) < matcher.config.tile_min_probe:
        return []
    return select_crops(crops, points)
