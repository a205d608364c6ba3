"""Real networks with real weights on a package-shipped photo warped by a known homography."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch import METHODS, Matcher, match_pair
from geomatch.eval.homography import reprojection_errors
from geomatch.matching.variants import for_pair
from geomatch.synth.photos import WarpedPair, warped_pair


@pytest.mark.nets
@pytest.mark.parametrize("method", METHODS)
def test_every_method_matches_a_warped_photo_to_subpixel_median(
    matcher: Matcher, astronaut_pair: WarpedPair, method: str
) -> None:
    r = matcher.derive(method=method).match(astronaut_pair.image0, astronaut_pair.image1)
    assert len(r) >= 100
    err = reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)
    assert np.median(err) < 2.0, f"{method}: median reprojection error {np.median(err):.2f} px"
    assert r.keypoints0.dtype == np.float32 and r.keypoints0.shape == (len(r), 2)
    assert r.scores.shape == (len(r),) and r.F.shape == (3, 3)
    # F is expressed in the original pixel frames: the matches satisfy it
    x0 = np.c_[r.keypoints0, np.ones(len(r))]
    x1 = np.c_[r.keypoints1, np.ones(len(r))]
    Fx0 = x0 @ r.F.T
    dist = np.abs((x1 * Fx0).sum(1)) / np.linalg.norm(Fx0[:, :2], axis=1)
    assert np.median(dist) < 2.0


@pytest.mark.nets
def test_geo_finds_more_correct_matches_than_either_backbone(
    matcher: Matcher, astronaut_pair: WarpedPair
) -> None:
    correct = {}
    for method in ("sparse", "dense", "geo"):
        # the full method on every pair: this warped pair's anchors are strong enough that the
        # default would answer it with the anchors alone (the next test)
        r = matcher.derive(method=method, anchors_suffice=0).match(
            astronaut_pair.image0, astronaut_pair.image1
        )
        err = reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)
        correct[method] = int((err < 3).sum())
        if method == "geo":
            assert r.stats["init"] == "anchors"
            assert (err < 3).mean() > 0.97
    assert correct["geo"] > max(correct["sparse"], correct["dense"]), correct


@pytest.mark.nets
def test_geo_answers_a_pair_with_strong_anchors_as_sparse_does(
    matcher: Matcher, astronaut_pair: WarpedPair
) -> None:
    """Where the anchors alone are many, the rounds only tied them on real photos at twice the
    time, so geo returns exactly the anchors' answer; with fewer anchors than the threshold it runs
    the optimiser, and tiled (aerial x ground) pairs always do."""
    a, b = astronaut_pair.image0, astronaut_pair.image1
    sparse = matcher.derive(method="sparse").match(a, b)
    geo = matcher.derive(method="geo")
    strong = geo.match(a, b)
    assert strong.stats.get("anchors_suffice") is True and "init" not in strong.stats
    np.testing.assert_array_equal(strong.keypoints0, sparse.keypoints0)
    np.testing.assert_array_equal(strong.keypoints1, sparse.keypoints1)
    weak = geo.derive(anchors_suffice=len(sparse) + 1).match(a, b)
    assert "anchors_suffice" not in weak.stats and weak.stats["init"] == "anchors"
    tiled = for_pair(geo, tiled=True)
    assert tiled.config.anchors_suffice == 0 and for_pair(geo, tiled=False) is geo
    assert "init" in tiled.match(a, b).stats


@pytest.mark.nets
def test_features_are_computed_once_per_image(astronaut_pair: WarpedPair, matcher: Matcher) -> None:
    m = matcher.derive(method="geo")
    m.clear_caches(anchors=False)
    before = m.extract_calls
    third = warped_pair("astronaut", seed=2, strength=0.15).image1
    m.match(astronaut_pair.image0, astronaut_pair.image1)
    m.match(astronaut_pair.image0, third)
    m.match(astronaut_pair.image1, third)
    # three images, two backbones (aliked for anchors, disk for the dense branch)
    assert m.extract_calls - before == 6


@pytest.mark.nets
def test_feature_cache_is_bounded_in_bytes(astronaut_pair: WarpedPair, matcher: Matcher) -> None:
    """A worker's memory must not grow with the project: the LRU drops images past its byte budget
    (one DISK image with dense maps at 480 px is ~100 MB) and recomputes them when asked again."""
    m = matcher.derive(method="geo", cache_features_mb=150.0)
    m.clear_caches(anchors=False)
    third = warped_pair("astronaut", seed=2, strength=0.15).image1
    for a, b in ((astronaut_pair.image0, astronaut_pair.image1), (astronaut_pair.image0, third)):
        m.match(a, b)
        assert m.cache_nbytes() <= 150 * 2**20
    before = m.extract_calls
    r = m.match(astronaut_pair.image0, astronaut_pair.image1)
    assert m.extract_calls > before  # evicted, so computed again
    assert np.median(reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)) < 2.0


@pytest.mark.nets
def test_disk_for_both_branches_runs_one_pass_per_image(astronaut_pair: WarpedPair, matcher: Matcher) -> None:
    m = matcher.derive(method="geo", sparse="disk", dense="disk")
    m.clear_caches(anchors=False)
    before = m.extract_calls
    r = m.match(astronaut_pair.image0, astronaut_pair.image1)
    assert m.extract_calls - before == 2
    assert np.median(reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)) < 2.0


@pytest.mark.nets
def test_match_pair_api_takes_paths_and_options(tmp_path, astronaut_pair: WarpedPair) -> None:
    import cv2

    p0, p1 = tmp_path / "a.png", tmp_path / "b.jpg"
    cv2.imwrite(str(p0), astronaut_pair.image0[:, :, ::-1])
    cv2.imwrite(str(p1), astronaut_pair.image1[:, :, ::-1])
    r = match_pair(p0, p1, method="geo", resize=320, device="cpu", iterations=3, tau=50.0)
    assert len(r) > 50 and r.method == "geo"
    with pytest.raises(TypeError, match="unknown matching options: bogus"):
        match_pair(p0, p1, bogus=1)
    with pytest.raises(ValueError, match="unknown method"):
        match_pair(p0, p1, method="magic")


@pytest.mark.nets
def test_geo_gives_nothing_for_images_that_do_not_overlap(matcher: Matcher) -> None:
    """Two unrelated photos: the optimiser alone would return matches that agree with a (wrong) F
    by construction, which COLMAP's verification would then accept; the anchor gate drops them."""
    from geomatch.synth.photos import photo

    a, b = photo("coffee"), photo("rocket")
    geo = matcher.derive(method="geo")
    r = geo.match(a, b)
    assert len(r) == 0 and "rejected" in r.stats and r.stats["anchor_support"] < 15
    ungated = geo.derive(min_anchor_support=0).match(a, b)
    assert len(ungated) > 0 and "rejected" not in ungated.stats


@pytest.mark.nets
def test_lightglue_assignment_branch_and_pruning_settings(
    matcher: Matcher, astronaut_pair: WarpedPair
) -> None:
    """dense=lightglue reads LightGlue's soft assignment (one LightGlue call serves anchors and the
    dense branch, no dense-map pass); a matcher with pruning does not reuse unpruned anchors, and
    the lightglue branch refuses pruning with a clear error instead of a silent partial P_c."""
    m = matcher.derive(method="geo", dense="lightglue", anchors_suffice=0)
    assert m.needed_extractors() == [("aliked", False)]
    r = m.match(astronaut_pair.image0, astronaut_pair.image1)
    err = reprojection_errors(astronaut_pair.H, r.keypoints0, r.keypoints1)
    assert r.stats["init"] == "anchors"
    assert len(r) + r.stats.get("final_check_removed", 0) >= r.stats["anchors"]
    assert (err < 3).mean() > 0.97
    pruned = m.derive(lightglue_depth_confidence=0.95, lightglue_width_confidence=0.99)
    assert pruned.anchor_cache is not m.anchor_cache
    with pytest.raises(ValueError, match="lightglue_width_confidence=-1"):
        pruned.match(astronaut_pair.image0, astronaut_pair.image1)
    same = m.derive(method="sparse")
    assert same.anchor_cache is m.anchor_cache


@pytest.mark.unit
def test_the_method_flags_are_the_old_name_tests() -> None:
    """Matcher.match reads the method's flags; for the five methods they say what the names did."""
    from geomatch.matching.matcher import MatcherConfig

    for method in METHODS:
        cfg = MatcherConfig(method=method)
        assert cfg.uses_anchors == (method in ("sparse", "concat", "geo", "auto")), method
        assert cfg.needs_dense == (method not in ("sparse", "auto")), method
        assert cfg.flags.optimise == (method in ("geo", "geo-noanchor")), method
        assert (not cfg.flags.optimise) == (method in ("sparse", "dense", "concat", "auto")), method
        assert cfg.flags.anchor_init == (method == "geo"), method
        assert (cfg.flags.optimise and cfg.uses_anchors) == (method == "geo"), method


@pytest.mark.unit
def test_a_stored_matcher_derives_stored_matchers(tmp_path) -> None:
    """A matcher derived from one over a feature store (a method per pair, the light-first pair)
    reads and writes the same store and shares the in-memory cache: features once per image."""
    from geomatch.features.store import FeatureStore
    from geomatch.matching.stored import StoredFeaturesMatcher, build_matcher

    m = build_matcher(FeatureStore(tmp_path), method="geo", resize=320, device="cpu")
    d = for_pair(m, tiled=True, aerial_project=True)
    assert isinstance(m, StoredFeaturesMatcher) and isinstance(d, StoredFeaturesMatcher)
    assert d.store is m.store and d.feature_cache is m.feature_cache
    assert d.config.anchors_suffice == 0 and m.config.anchors_suffice != 0
