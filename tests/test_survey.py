"""A drone survey is recognised by its GPS track when no photo says it was taken from the air."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.geo.survey import is_survey_track
from geomatch.metadata import ImageMeta
from geomatch.steps import aerial_set, captures

pytestmark = pytest.mark.unit


def lawnmower(
    lines: int = 4, per_line: int = 8, spacing: float = 12.0, gap: float = 30.0
) -> dict[str, np.ndarray]:
    """Lines flown back and forth, a photo every ``spacing`` metres, named in capture order."""
    rng = np.random.default_rng(0)
    out = {}
    i = 0
    for line in range(lines):
        xs = np.arange(per_line) * spacing
        for x in xs if line % 2 == 0 else xs[::-1]:
            out[f"IMG_{i:04d}.jpg"] = np.array([x, line * gap, 80.0]) + rng.normal(0, 1.0, 3)
            i += 1
    return out


def test_a_lawnmower_flight_is_a_survey() -> None:
    track = lawnmower()
    assert is_survey_track(list(track), track)


def test_a_walk_along_one_street_is_not() -> None:
    walk = {f"IMG_{i:04d}.jpg": np.array([i * 3.0, 0.0, 0.0]) for i in range(20)}
    assert not is_survey_track(list(walk), walk)


def test_photos_taken_from_one_place_are_not() -> None:
    rng = np.random.default_rng(1)
    here = {f"IMG_{i:04d}.jpg": rng.normal(0, 0.2, 3) for i in range(20)}
    assert not is_survey_track(list(here), here)


def test_too_few_photos_are_not() -> None:
    track = lawnmower(lines=2, per_line=4)
    assert not is_survey_track(list(track), track)


def test_a_survey_without_xmp_is_aerial_unless_the_user_says_otherwise() -> None:
    track = lawnmower()
    names = sorted(track)
    silent = {n: ImageMeta(4000, 3000) for n in names}
    assert aerial_set(captures(names), silent, track) == set(names)
    assert aerial_set(captures(names), silent, None) == set()
    # --aerial decides, even a pattern that matches nothing
    assert aerial_set(captures(names, aerial_glob="nothing*"), silent, track) == set()
    # one photo that says it is on the ground: the metadata speaks, the track does not
    ground = dict(silent, **{names[0]: ImageMeta(4000, 3000, relative_altitude_m=1.0)})
    assert aerial_set(captures(names), ground, track) == set()
