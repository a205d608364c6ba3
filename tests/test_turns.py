"""An aerial project's quarter turns are decided once per image, and its plain pairs take the light
anchors first: the two things that make a drone survey cost what a ground project costs."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from geomatch import Matcher
from geomatch.epipolar.geometry import sampson_distance
from geomatch.eval.homography import reprojection_errors
from geomatch.imagefolder import Images
from geomatch.matching.guided import KEEP_SAMPSON
from geomatch.matching.matcher import MatcherConfig
from geomatch.matching.rotation import anchor_count, quarter_turn
from geomatch.matching.variants import for_pair
from geomatch.pipeline.pair_sources import exhaustive, finalize, with_turns
from geomatch.pipeline.plan import image_turns
from geomatch.synth.photos import WarpedPair, warped_pair

pytestmark = pytest.mark.nets


def test_each_image_gets_its_turn_once_and_pairs_their_relative_turn(
    matcher: Matcher, astronaut_pair: WarpedPair, tmp_path: Path
) -> None:
    shots = {
        "a.png": astronaut_pair.image0,
        "b.png": quarter_turn(astronaut_pair.image1, 1),
        "c.png": quarter_turn(astronaut_pair.image1, 2),
    }
    for name, img in shots.items():
        Image.fromarray(img).save(tmp_path / name)
    plan = finalize(exhaustive(sorted(shots)), set(shots))
    light = matcher.derive(method="sparse", max_keypoints=1024)
    turns = image_turns(plan, partial(anchor_count, light), Images(tmp_path), {})
    # into a's frame: b was turned once, three more make four; c twice, two more
    assert turns == {"a.png": 0, "b.png": 3, "c.png": 2}
    turned = {p.key: p.turns for p in with_turns(plan, turns)}
    assert turned == {("a.png", "b.png"): (0, 3), ("a.png", "c.png"): (0, 2), ("b.png", "c.png"): (3, 2)}
    # in the frame, b and c are the same photo
    b_framed, c_framed = quarter_turn(shots["b.png"], 3), quarter_turn(shots["c.png"], 2)
    assert np.array_equal(b_framed, c_framed)


def test_an_image_whose_probes_find_nothing_keeps_the_per_pair_probe(
    matcher: Matcher, astronaut_pair: WarpedPair, tmp_path: Path
) -> None:
    other = warped_pair("coffee", seed=3).image0
    noise = np.random.default_rng(0).integers(0, 255, other.shape, dtype=np.uint8)
    for name, img in {"a.png": astronaut_pair.image0, "n.png": noise}.items():
        Image.fromarray(img).save(tmp_path / name)
    plan = finalize(exhaustive(["a.png", "n.png"]), {"a.png", "n.png"})
    turns = image_turns(
        plan, partial(anchor_count, matcher.derive(method="sparse", max_keypoints=1024)), Images(tmp_path), {}
    )
    assert turns == {"a.png": 0}
    assert with_turns(plan, turns)[0].turns is None


def test_two_aerial_photos_of_a_survey_are_matched_guided_and_other_pairs_keep_geo(
    astronaut_pair: WarpedPair,
) -> None:
    auto = Matcher(MatcherConfig(method="auto", resize=480, device="cpu"))
    aerial = for_pair(auto, tiled=False, aerial_project=True, aerial_pair=True)
    assert aerial.config.method == "geo" and aerial.config.light_first and aerial.config.guided_keypoints
    r = aerial.match(astronaut_pair.image0, astronaut_pair.image1)
    assert r.stats["anchors_suffice"] == "light" and r.stats["f_inliers"] >= aerial.config.anchors_suffice
    # the epipolar lines guide more matches than the seed had, and they are right
    assert r.stats["guided"] > 1.2 * r.stats["f_inliers"]
    err = reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)
    assert np.median(err) < 1.5 and np.mean(err < 5.0) > 0.9
    assert "dense_coarse" not in r.timings  # no dense maps for this pair
    # what goes on to COLMAP's verification lies near the F the guided matches fit (the rest
    # would not verify and would only make its RANSAC long)
    scale = max(astronaut_pair.image0.shape[:2]) / 480
    d = sampson_distance(
        torch.from_numpy(r.F),
        torch.from_numpy(r.keypoints0).double(),
        torch.from_numpy(r.keypoints1).double(),
    )
    assert float(d.max()) <= KEEP_SAMPSON * scale**2 * 1.01

    other = warped_pair("coffee", seed=3).image0
    # two aerial photos that share nothing: the seed's answer stands, no full method
    r = aerial.match(astronaut_pair.image0, other)
    assert r.stats["f_inliers"] < aerial.config.anchors_suffice and "guided" not in r.stats
    assert "light" not in r.timings
    # any other pair of a project with aerial images keeps geo
    ground = for_pair(auto, tiled=False, aerial_project=True, aerial_pair=False)
    assert ground.config.method == "geo" and not ground.config.light_first
