"""The turn hint reads a quarter turn from rotation-invariant SIFT and tells overlapping photos
from photos that share nothing, so the plan scores one turned copy where it scored four."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.matching.rotation import quarter_turn
from geomatch.matching.turnhint import HINT_MIN_INLIERS, SiftHints, turn_of_angle
from geomatch.synth.photos import warped_pair

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("turned", [0, 1, 2, 3])
def test_the_hint_undoes_the_quarter_turn_between_two_views(turned: int) -> None:
    pair = warped_pair("astronaut", seed=0, strength=0.15)
    hints = SiftHints()
    h = hints.hint("a", pair.image0, f"b{turned}", quarter_turn(pair.image1, turned))
    assert h.turn == (4 - turned) % 4  # turning b back by the rest of a full turn
    assert h.inliers >= 5 * HINT_MIN_INLIERS


def test_photos_that_share_nothing_are_below_the_overlap_floor() -> None:
    a = warped_pair("astronaut", seed=0).image0
    other = warped_pair("coffee", seed=3).image0
    noise = np.random.default_rng(0).integers(0, 255, a.shape, dtype=np.uint8)
    hints = SiftHints()
    assert hints.hint("a", a, "coffee", other).inliers < HINT_MIN_INLIERS
    assert hints.hint("a", a, "noise", noise).inliers < HINT_MIN_INLIERS
    flat = np.full_like(a, 128)  # no SIFT point at all
    assert hints.hint("a", a, "flat", flat).inliers == 0


def test_features_are_kept_once_per_photo_within_the_byte_budget() -> None:
    photos = {f"p{i}": warped_pair("astronaut", seed=i).image0 for i in range(4)}
    hints = SiftHints(budget_mb=0.3)  # about one photo's points
    for name, img in photos.items():
        pts, desc = hints.features(name, img)
        assert desc.dtype == np.uint8 and len(pts) == len(desc) > 100
    assert hints.nbytes() <= 0.3 * 2**20 or hints.cached() == 1
    again = hints.features("p3", photos["p3"])
    assert again is hints.features("p3", photos["p3"])  # the newest stays, served from the cache


@pytest.mark.parametrize(
    ("degrees", "turn"), [(0, 0), (-90, 1), (180, 2), (-180, 2), (90, 3), (-80, 1), (40, 0)]
)
def test_an_angle_in_pixel_coordinates_maps_to_the_turn_that_undoes_it(degrees: float, turn: int) -> None:
    assert turn_of_angle(degrees) == turn
