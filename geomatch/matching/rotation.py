"""Quarter turns for pairs with an aerial side: a drone's heading is arbitrary, the networks' are not.

Why: ALIKED and LightGlue are trained on upright photos and do not match an image against a
rotated copy of itself. In the demo scene the three aerial images face each other from across the
site: aerial x aerial pairs gave 43-61 LightGlue matches with 0-1 right, and the same pairs with
one image turned by the right quarter turn 226-1043 matches with 196-1004 right (the nadir image
against a ground view: 25 matches, 0 right, against 93, 44 right). Without those pairs the aerial
images had no correct route into the model (docs/pipeline.md).

So for a pair with an aerial side, one image is tried at the four quarter turns with a cheap
LightGlue pass (``Matcher.probe_count``: each image's 512 strongest keypoints, LightGlue's adaptive
depth and width on); when its best turn is not clear-cut (``PROBE_MARGIN``) the four turns are
ranked again by the full-strength anchors; the pair is matched at the turn that gives the most.
Keypoints come back in the image's own frame. Why a cheap probe first: the full-strength anchors
alone would be four ~8-10 s LightGlue calls per pair on the 2-core CPU, half of a tiled pair's time.
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

TURNS = (0, 1, 2, 3)  # counter-clockwise quarter turns, as np.rot90


# the cheap probe decides alone only when its best turn has at least this many times the matches
# of the runner-up; otherwise the four turns are ranked again by the full-strength anchors. On the
# service test scene at 480 px the cheap probe disagreed with the anchors on 3 of 9 pairs, all with
# margins under 1.3x; where the margin was 2x or more it agreed on every pair measured (demo scene
# at 640 px and that scene)
PROBE_MARGIN = 2.0


class _Matcher(Protocol):
    def probe_count(self, image0: np.ndarray, image1: np.ndarray) -> int: ...

    def anchor_count(self, image0: np.ndarray, image1: np.ndarray) -> int: ...


# np.rot90's k -> OpenCV's code for the same turn
_CV2_TURNS = {1: cv2.ROTATE_90_COUNTERCLOCKWISE, 2: cv2.ROTATE_180, 3: cv2.ROTATE_90_CLOCKWISE}


def quarter_turn(image: np.ndarray, turns: int) -> np.ndarray:
    """``np.rot90(image, turns)`` as a contiguous array. A photo of up to 4 channels of bytes is
    turned by OpenCV: the same pixels 6-8x faster than numpy's strided copy (7 ms against 1 ms for
    a 1600x1200 photo), and a survey turns one of the two photos of most pairs it matches."""
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
