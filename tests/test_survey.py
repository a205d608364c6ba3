"""A drone survey is recognised by its GPS track when no photo says it was taken from the air."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geomatch.geo.survey import is_survey_track
from geomatch.imagefolder import Images
from geomatch.matching.rotation import quarter_turn
from geomatch.matching.turnhint import TurnHint
from geomatch.metadata import ImageMeta
from geomatch.pipeline.aerial import aerial_set, captures
from geomatch.pipeline.pair_sources import exhaustive, finalize
from geomatch.pipeline.plan import image_turns

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


def _shot(i: int, turned: int) -> np.ndarray:
    """A 16x16 photo that says which it is (its centre, unchanged by a quarter turn) and how it is
    turned (a marked corner); ``turned``: quarter turns the camera applied to the frame's view."""
    a = np.zeros((16, 16, 3), np.uint8)
    a[0, 0] = 200
    a[7:9, 7:9] = i + 1
    return quarter_turn(a, turned)


def _read(a: np.ndarray) -> tuple[int, int]:
    """(photo, quarter turns from the frame) of a shot, as turned by the plan's probes."""
    corners = {(0, 0): 0, (15, 0): 1, (15, 15): 2, (0, 15): 3}  # where np.rot90 takes the mark
    turn = next(t for (r, c), t in corners.items() if a[r, c, 0] == 200)
    return int(a[7, 7, 0]) - 1, turn


def test_turns_grow_along_the_capture_order_so_each_photo_is_turned_about_once(tmp_path: Path) -> None:
    """Two lines flown in opposite directions, the second with its photos turned by a half turn,
    and the lines closer to each other (1 m) than photos along a line (2 m), as a compact
    camera's GPS can put them: the nearest fix is on the other line, whose photo shares nothing.
    The photo taken just before or after overlaps: probing it first scores one turned copy of
    each photo, plus the half turn where the line turns (a quarter-turn probe's cost per copy
    is a feature extraction)."""
    n = 12
    true_turn = {i: 0 if i < 6 else 2 for i in range(n)}
    names = [f"IMG_{i:04d}.png" for i in range(n)]  # lossless: the marks survive
    enu = {}
    for i, name in enumerate(names):
        x = 2.0 * i if i < 6 else 2.0 * (n - 1 - i)
        enu[name] = np.array([x, 0.0 if i < 6 else 1.0, 80.0])
        Image.fromarray(_shot(i, true_turn[i])).save(tmp_path / name)
    scored: set[tuple[int, int]] = set()

    def score(fixed: np.ndarray, moving: np.ndarray) -> int:
        (i, ti), (j, tj) = _read(fixed), _read(moving)
        scored.add((j, tj))
        in_frame = ti == 0 and tj == 0  # both turned back into the frame
        return 500 if abs(i - j) == 1 and in_frame else 15

    plan = finalize(exhaustive(names), set(names))
    turns = image_turns(plan, score, Images(tmp_path), enu)
    assert turns == {name: (4 - true_turn[i]) % 4 for i, name in enumerate(names)}
    # one copy per photo but the root (it is the frame), and the half turn of the line's first
    assert len(scored) == (n - 1) + 1, sorted(scored)


def _two_lines(tmp_path: Path, n: int = 12) -> tuple[list[str], dict[str, np.ndarray], dict[int, int]]:
    """The survey of the test above: two lines, the second turned by a half turn, its fixes on the
    other line's photos."""
    true_turn = {i: 0 if i < n // 2 else 2 for i in range(n)}
    names = [f"IMG_{i:04d}.png" for i in range(n)]
    enu = {}
    for i, name in enumerate(names):
        x = 2.0 * i if i < n // 2 else 2.0 * (n - 1 - i)
        enu[name] = np.array([x, 0.0 if i < n // 2 else 1.0, 80.0])
        Image.fromarray(_shot(i, true_turn[i])).save(tmp_path / name)
    return names, enu, true_turn


def _line_mates_score(scored: list[tuple[int, int, int]]) -> Callable[[np.ndarray, np.ndarray], int]:
    """A seed score that is high only for photos taken one after the other, both in the frame;
    every scored (photo, partner, partner's turn) is appended to ``scored``."""

    def score(fixed: np.ndarray, moving: np.ndarray) -> int:
        (i, ti), (j, tj) = _read(fixed), _read(moving)
        scored.append((i, j, tj))
        return 500 if abs(i - j) == 1 and ti == 0 and tj == 0 else 15

    return score


@pytest.mark.parametrize("hint_right", [True, False])
def test_a_turn_hint_skips_pairs_that_share_nothing_and_orders_the_turns_but_the_score_decides(
    tmp_path: Path, hint_right: bool
) -> None:
    """Where every photo's line-mate is its only overlap, and the hint (SIFT in the plan) sees
    that: the pairs across lines are never scored, and each photo is scored at one turned copy,
    the line's first photo too, whose turn only the hint knows. A hint that reads the wrong turn
    costs more copies, not a wrong turn."""
    names, enu, true_turn = _two_lines(tmp_path)
    scored: list[tuple[int, int, int]] = []
    score = _line_mates_score(scored)

    def hint(name0: str, image0: np.ndarray, name1: str, image1: np.ndarray) -> TurnHint:
        (i, ti), (j, tj) = _read(image0), _read(image1)
        overlap = (abs(i - j) == 1 and (i < 6) == (j < 6)) or {i, j} == {5, 6}
        turn = (ti - tj) % 4 if hint_right else (ti - tj + 1) % 4
        return TurnHint(turn, 300 if overlap else 4)

    plan = finalize(exhaustive(names), set(names))
    turns = image_turns(plan, score, Images(tmp_path), enu, hint=hint)
    assert turns == {name: (4 - true_turn[i]) % 4 for i, name in enumerate(names)}
    assert all(abs(i - j) == 1 for i, j, _ in scored)  # no pair across the lines was scored
    if hint_right:
        assert len(scored) == len(names) - 1  # one turned copy per photo but the root
    else:
        assert len(scored) > len(names) - 1


def test_photos_taken_one_after_the_other_are_scored_though_the_hint_finds_nothing(tmp_path: Path) -> None:
    """Over low-texture fields SIFT's similarity fits a handful of matches where the network's
    seed fits a thousand: a hint that sees no overlap anywhere still lets each photo be scored
    against the one taken before or after it, so every turn is decided, and no other pair is."""
    names, enu, true_turn = _two_lines(tmp_path)
    scored: list[tuple[int, int, int]] = []
    score = _line_mates_score(scored)

    def blind(name0: str, image0: np.ndarray, name1: str, image1: np.ndarray) -> TurnHint:
        return TurnHint(0, 3)

    plan = finalize(exhaustive(names), set(names))
    turns = image_turns(plan, score, Images(tmp_path), enu, hint=blind)
    assert turns == {name: (4 - true_turn[i]) % 4 for i, name in enumerate(names)}
    assert all(abs(i - j) == 1 for i, j, _ in scored)
