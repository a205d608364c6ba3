"""Quarter turns for pairs with an aerial side: a drone's heading is arbitrary, the networks' are not.

Why: ALIKED and LightGlue are trained on upright photos and do not match an image against a
rotated copy of itself. Aerial images of a site often face each other from across it: matched
upright, such pairs give almost nothing right, and at the right quarter turn many times more
matches, nearly all right. Without those pairs the aerial images have no correct route into the
model (docs/pipeline.md, "Quarter turns"; figures in docs/benchmarks.md, "Quarter turns").

So for a pair with an aerial side, one image is tried at the four quarter turns with a cheap
LightGlue pass (:func:`probe_count`: each image's ``probe_keypoints`` strongest keypoints,
LightGlue's adaptive depth and width on); when its best turn is not clear-cut (``PROBE_MARGIN``)
the four turns are ranked again by the full-strength anchors; the pair is matched at the turn that
gives the most. Keypoints come back in the image's own frame. Why a cheap probe first: the
full-strength anchors alone would be four full LightGlue calls per pair, on the CPU half of a tiled
pair's time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from ..imageio import image_key
from .guided import seed_inliers, strongest
from .variants import light_matcher

if TYPE_CHECKING:
    from .matcher import Matcher

TURNS = (0, 1, 2, 3)  # counter-clockwise quarter turns, as np.rot90


# the cheap probe decides alone only when its best turn has at least this many times the matches
# of the runner-up; otherwise the four turns are ranked again by the full-strength anchors. Where
# the probe and the anchors disagree, the probe's margin is small; at this margin they agree
# (docs/pipeline.md, "Quarter turns")
PROBE_MARGIN = 2.0


# np.rot90's k -> OpenCV's code for the same turn
_CV2_TURNS = {1: cv2.ROTATE_90_COUNTERCLOCKWISE, 2: cv2.ROTATE_180, 3: cv2.ROTATE_90_CLOCKWISE}


def quarter_turn(image: np.ndarray, turns: int) -> np.ndarray:
    """``np.rot90(image, turns)`` as a contiguous array. A photo of up to 4 channels of bytes is
    turned by OpenCV: the same pixels several times faster than numpy's strided copy, and a survey
    turns one of the two photos of most pairs it matches."""
    t = turns % 4
    if t and image.dtype == np.uint8 and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] <= 4)):
        return np.asarray(cv2.rotate(image, _CV2_TURNS[t]))
    return np.ascontiguousarray(np.rot90(image, t))


def points_back(points: np.ndarray, turns: int, width: int, height: int) -> np.ndarray:
    """Pixels (centres at integers) of ``quarter_turn(image, turns)`` -> the same points in the
    unturned image of ``width`` x ``height``."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    t = turns % 4
    if t == 0:
        out = p.copy()
    elif t == 1:
        out = np.stack([width - 1 - y, x], 1)
    elif t == 2:
        out = np.stack([width - 1 - x, height - 1 - y], 1)
    else:
        out = np.stack([y, height - 1 - x], 1)
    return out.astype(np.asarray(points).dtype, copy=False)


def turn_score(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> int:
    """How well ``image1`` matches ``image0`` as given, to rank quarter turns: the guided
    matcher's seed F inliers (geomatch.matching.guided.seed_inliers) where ``matcher`` guides,
    else the LightGlue matches (:func:`anchor_count`)."""
    if matcher.config.light_first and matcher.config.guided_keypoints:
        return seed_inliers(light_matcher(matcher), image0, image1)
    return anchor_count(matcher, image0, image1)


def score_features(matcher: Matcher, image: np.ndarray) -> None:
    """Extract (and store, for a matcher over a feature store) the features :func:`turn_score`
    reads of ``image``, ahead of the scoring: how a queued plan spreads a survey's extraction over
    its workers before it decides the turns in one step."""
    if matcher.config.light_first and matcher.config.guided_keypoints:
        light_matcher(matcher).features(image)
    else:
        probe = matcher if matcher.config.method == "sparse" else matcher.derive(method="sparse")
        probe.features(image)


@torch.inference_mode()
def anchor_count(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> int:
    """How many matches LightGlue alone finds (features and result cached like the anchors, so
    a later match of the same pair reuses them): how a quarter-turn probe ranks turns."""
    probe = matcher if matcher.config.method == "sparse" else matcher.derive(method="sparse")
    key0, key1 = image_key(image0), image_key(image1)
    sa = probe.features(image0, key0)[matcher.config.sparse].sparse
    sb = probe.features(image1, key1)[matcher.config.sparse].sparse
    assert sa is not None and sb is not None
    return int(probe.match_anchors(key0, key1, sa, sb).idx_a.numel())


def probe_count(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> int:
    """LightGlue matches among each image's ``probe_keypoints`` strongest keypoints, pruned: a
    cheap rank of the quarter turns. Only the sparse features are extracted (a turned image the
    probe rejects never gets dense maps); nothing is cached beyond those features."""
    return int(probe_points(matcher, image0, image1)[0].shape[0])


@torch.inference_mode()
def probe_points(matcher: Matcher, image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cheap probe's matches (see :func:`probe_count`) in each image's original pixels:
    where two images overlap, at a fraction of a full-strength LightGlue call's cost."""
    cfg = matcher.config
    probe = matcher if cfg.method == "sparse" else matcher.derive(method="sparse")
    key0, key1 = image_key(image0), image_key(image1)
    sa = strongest(probe.features(image0, key0)[cfg.sparse].sparse, cfg.probe_keypoints)
    sb = strongest(probe.features(image1, key1)[cfg.sparse].sparse, cfg.probe_keypoints)
    m = matcher.probe_matcher.match(sa, sb)
    return (
        probe.prepared(image0, key0).to_original(sa.keypoints[m.idx_a].float()),
        probe.prepared(image1, key1).to_original(sb.keypoints[m.idx_b].float()),
    )


def best_turn(matcher: Matcher, fixed: np.ndarray, moving: np.ndarray) -> int:
    """The quarter turn of ``moving`` that gives the most matches against ``fixed`` (ties: fewer
    turns, so an upright pair stays upright): by the cheap probe when it is clear-cut, else by the
    full-strength anchors (cached, so the chosen turn's are reused by the match)."""
    return ranked_turns(matcher, fixed, moving)[0]


def ranked_turns(
    matcher: Matcher, fixed: np.ndarray, moving: np.ndarray
) -> tuple[int, list[int], list[int] | None]:
    """:func:`best_turn`'s turn with the counts that chose it: the probe's per turn, and the
    anchors' per turn (None where the probe was clear-cut and no anchors were counted)."""
    probes = [probe_count(matcher, fixed, quarter_turn(moving, t)) for t in TURNS]
    best, runner_up = sorted(probes, reverse=True)[:2]
    if best >= PROBE_MARGIN * max(runner_up, 1):
        return int(np.argmax(probes)), probes, None
    anchors = [anchor_count(matcher, fixed, quarter_turn(moving, t)) for t in TURNS]
    return int(np.argmax(anchors)), probes, anchors
