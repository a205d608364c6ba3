"""A survey photo's quarter turn against a partner from rotation-invariant SIFT, before any network.

Why: the plan decides each aerial photo's quarter turn by scoring the guided matcher's seed F at
the four turns (planning.image_turns), and every turn it scores is an ALIKED extraction of a turned
copy that is thrown away unless it wins. A pair that does not overlap at all (GPS neighbours on
adjacent lines, a compact camera's fixes tens of metres off) costs all four. SIFT is invariant to
in-plane rotation, so one extraction per photo (far cheaper than an ALIKED one) says both whether a pair
overlaps (inliers of a similarity fitted to its matches) and, from that similarity's angle, which
quarter turn the ALIKED score should try first. The networks still decide the turn: the hint only
orders the turns tried and skips the pairs that share nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from ..memory import ByteLRU

# SIFT points per photo and the long side they are found at: the hint needs the relative rotation
# and whether a pair overlaps, not accuracy
HINT_POINTS = 2048
HINT_LONG_SIDE = 640
HINT_RATIO = 0.8  # Lowe's ratio test on the two nearest descriptors
HINT_RANSAC_PX = 8.0  # the similarity's inlier threshold at HINT_LONG_SIDE
# below this many similarity inliers a pair is taken not to overlap (its probe is skipped)
HINT_MIN_INLIERS = 20


@dataclass(frozen=True)
class TurnHint:
    """``turn``: the quarter turn (np.rot90) of the second photo into the first's frame;
    ``inliers``: how many SIFT matches a similarity fits, the evidence that the two overlap."""

    turn: int
    inliers: int


class SiftHints:
    """SIFT per photo, once (cached, bounded in bytes), and the turn hint of a pair of them."""

    def __init__(self, budget_mb: float = 128.0) -> None:
        self._sift = cv2.SIFT.create(nfeatures=HINT_POINTS)
        self._matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._cache: ByteLRU[str, tuple[np.ndarray, np.ndarray]] = ByteLRU(
            budget_mb, lambda v: int(v[0].nbytes + v[1].nbytes)
        )

    def features(self, name: str, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points (N, 2) in the photo's own pixels, descriptors (N, 128) uint8)."""
        cached = self._cache.get(name)
        if cached is not None:
            return cached
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        scale = min(1.0, HINT_LONG_SIDE / max(gray.shape[:2]))
        if scale < 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        kps, desc = self._sift.detectAndCompute(np.ascontiguousarray(gray), None)
        if desc is None or not kps:
            out = (np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
        else:
            pts = np.array([k.pt for k in kps], np.float32) / scale
            # OpenCV's SIFT descriptors are whole numbers in 0..255: uint8 keeps them exactly
            out = (pts, np.clip(desc, 0, 255).astype(np.uint8))
        self._cache.put(name, out)
        return out

    def nbytes(self) -> int:
        return self._cache.nbytes()

    def cached(self) -> int:
        return len(self._cache)

    def hint(self, name0: str, image0: np.ndarray, name1: str, image1: np.ndarray) -> TurnHint:
        (p0, d0), (p1, d1) = self.features(name0, image0), self.features(name1, image1)
        if len(p0) < 2 or len(p1) < 2:
            return TurnHint(0, 0)
        knn = self._matcher.knnMatch(d1.astype(np.float32), d0.astype(np.float32), k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < HINT_RATIO * m[1].distance]
        if len(good) < 3:
            return TurnHint(0, 0)
        src = p1[[m.queryIdx for m in good]]
        dst = p0[[m.trainIdx for m in good]]
        scale = HINT_LONG_SIDE / max(*image0.shape[:2], *image1.shape[:2])
        model, mask = cv2.estimateAffinePartial2D(
            src, dst, method=cv2.RANSAC, ransacReprojThreshold=HINT_RANSAC_PX / min(scale, 1.0)
        )
        if model is None or mask is None:
            return TurnHint(0, 0)
        return TurnHint(turn_of_angle(math.degrees(math.atan2(model[1, 0], model[0, 0]))), int(mask.sum()))


def turn_of_angle(degrees: float) -> int:
    """The quarter turn (np.rot90's k) that undoes a rotation of ``degrees`` in pixel coordinates
    (y down) from the second photo to the first: np.rot90 by k maps pixels by -90 k degrees."""
    return round(-degrees / 90.0) % 4


class KnownHints:
    """The hints of pairs hinted before (a queued plan's guess of its turns, made in an earlier step:
    geomatch.pipeline.plan_photos), SiftHints' for any other pair: the same answers, without
    extracting and matching SIFT a second time."""

    def __init__(self, known: Mapping[tuple[str, str], TurnHint]) -> None:
        self.known = dict(known)
        self._sift = SiftHints()

    def hint(self, name0: str, image0: np.ndarray, name1: str, image1: np.ndarray) -> TurnHint:
        found = self.known.get((name0, name1))
        return found if found is not None else self._sift.hint(name0, image0, name1, image1)
