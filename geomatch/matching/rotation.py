"""Quarter turns for pairs with an aerial side: a drone's heading is arbitrary, the networks' are not.

Why: ALIKED and LightGlue are trained on upright photos and do not match an image against a
rotated copy of itself. Aerial images of a site often face each other from across it: matched
upright, such pairs give almost nothing right, and at the right quarter turn many times more
matches, nearly all right. Without those pairs the aerial images have no correct route into the
model (docs/pipeline.md, "Quarter turns"; figures in docs/benchmarks.md, "Quarter turns").

So for a pair with an aerial side, one image is tried at the four quarter turns with a cheap
LightGlue pass (``Matcher.probe_count``: each image's 512 strongest keypoints, LightGlue's adaptive
depth and width on); when its best turn is not clear-cut (``PROBE_MARGIN``) the four turns are
ranked again by the full-strength anchors; the pair is matched at the turn that gives the most.
Keypoints come back in the image's own frame. Why a cheap probe first: the full-strength anchors
alone would be four full LightGlue calls per pair, on the CPU half of a tiled pair's time.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

TURNS = (0, 1, 2, 3)  # counter-clockwise quarter turns, as np.rot90


# the cheap probe decides alone only when its best turn has at least this many times the matches
# of the runner-up; otherwise the four turns are ranked again by the full-strength anchors. Where
# the probe and the anchors disagree, the probe's margin is small; at this margin they agree
# (docs/pipeline.md, "Quarter turns")
PROBE_MARGIN = 2.0


class _Matcher(Protocol):
    def probe_count(self, image0: np.ndarray, image1: np.ndarray) -> int: ...

    def anchor_count(self, image0: np.ndarray, image1: np.ndarray) -> int: ...


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


def best_turn(matcher: _Matcher, fixed: np.ndarray, moving: np.ndarray) -> int:
    """The quarter turn of ``moving`` that gives the most matches against ``fixed`` (ties: fewer
    turns, so an upright pair stays upright): by the cheap probe when it is clear-cut, else by the
    full-strength anchors (cached, so the chosen turn's are reused by the match)."""
    counts = [matcher.probe_count(fixed, quarter_turn(moving, t)) for t in TURNS]
    best, runner_up = sorted(counts, reverse=True)[:2]
    if best >= PROBE_MARGIN * max(runner_up, 1):
        return int(np.argmax(counts))
    counts = [matcher.anchor_count(fixed, quarter_turn(moving, t)) for t in TURNS]
    return int(np.argmax(counts))
