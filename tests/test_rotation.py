"""Quarter turns: the geometry of mapping points back, and the probe on a real rotated pair."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch import Matcher
from geomatch.eval.homography import reprojection_errors
from geomatch.matching.rotation import best_turn, points_back, quarter_turn
from geomatch.pipeline.match_pairs import match
from geomatch.pipeline.pair_sources import Pair, finalize
from geomatch.synth.photos import WarpedPair


@pytest.mark.unit
@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_points_come_back_to_the_same_pixel(turns: int) -> None:
    rng = np.random.default_rng(turns)
    img = rng.integers(0, 255, size=(7, 11, 3), dtype=np.uint8)
    turned = quarter_turn(img, turns)
    h, w = turned.shape[:2]
    pts = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(np.float64)
    back = points_back(pts, turns, img.shape[1], img.shape[0]).round().astype(int)
    assert np.array_equal(turned[pts[:, 1].astype(int), pts[:, 0].astype(int)], img[back[:, 1], back[:, 0]])


@pytest.mark.unit
@pytest.mark.parametrize("turns", [-1, 0, 1, 2, 3, 5])
@pytest.mark.parametrize(
    ("shape", "dtype"),
    [
        ((9, 13, 3), np.uint8),
        ((9, 13), np.uint8),
        ((9, 13, 4), np.uint8),
        ((9, 13, 5), np.uint8),
        ((9, 13, 3), np.float32),
    ],
)
def test_a_turned_copy_is_numpys_quarter_turn_whichever_library_turns_it(
    turns: int, shape: tuple[int, ...], dtype: type
) -> None:
    # OpenCV turns photos of bytes, numpy the rest: the pixels must not depend on which
    img = np.random.default_rng(turns % 4).integers(0, 255, size=shape).astype(dtype)
    turned = quarter_turn(img, turns)
    assert turned.flags.c_contiguous and turned.dtype == img.dtype
    assert np.array_equal(turned, np.rot90(img, turns))
    assert np.array_equal(quarter_turn(img[:, ::2], turns), np.rot90(img[:, ::2], turns))


@pytest.mark.unit
def test_pairs_with_an_aerial_side_are_turned() -> None:
    plan = {(p.name0, p.name1): p.rotate for p in finalize([("a", "b"), ("a", "g"), ("g", "h")], {"a", "b"})}
    assert plan == {("a", "b"): True, ("a", "g"): True, ("g", "h"): False}


@pytest.mark.nets
def test_a_turned_image_is_matched_at_its_turn_and_mapped_back(
    matcher: Matcher, astronaut_pair: WarpedPair
) -> None:
    sparse = matcher.derive(method="sparse", max_keypoints=1024)  # 4 turns x LightGlue: keep it light
    turned = quarter_turn(astronaut_pair.image1, 1)
    assert best_turn(sparse, astronaut_pair.image0, turned) == 3  # three more make four
    assert best_turn(sparse, astronaut_pair.image0, astronaut_pair.image1) == 0
    upright = match(sparse, Pair("a", "b"), astronaut_pair.image0, turned)
    m = match(sparse, Pair("a", "b", rotate=True), astronaut_pair.image0, turned)
    assert len(m) > 3 * max(len(upright), 1)
    # keypoints1 are in the frame of the image as given (turned once): undo that turn to compare
    h, w = astronaut_pair.image1.shape[:2]
    k1 = points_back(m.keypoints1, 1, w, h)
    err = reprojection_errors(astronaut_pair.H, m.keypoints0, k1)
    assert np.median(err) < 1.5
