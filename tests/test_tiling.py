from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from geomatch.eval.homography import reprojection_errors
from geomatch.matching.probes import tile_crops
from geomatch.matching.tiling import SELECT_MIN_PROBE, five_crops, match_tiled, merge_matches, select_crops
from geomatch.synth.photos import warped_pair


@pytest.mark.unit
def test_crops_cover_the_image_and_map_back_exactly() -> None:
    w, h = 641, 479  # odd sizes: crops must still tile the whole frame
    crops = five_crops(w, h)
    assert [c.name for c in crops] == ["top_left", "top_right", "bottom_left", "bottom_right", "centre"]
    covered = np.zeros((h, w), bool)
    image = np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8)
    pts = np.random.default_rng(1).uniform([0, 0], [w - 1, h - 1], (500, 2))
    for c in crops[:4]:
        covered[c.y0 : c.y0 + c.height, c.x0 : c.x0 + c.width] = True
    assert covered.all()
    for c in crops:
        cut = c.cut(image)
        assert cut.shape == (c.height, c.width, 3)
        # a pixel of the crop is the same pixel of the full image after mapping back
        u, v = c.width - 1, c.height // 3
        x, y = c.to_full(np.array([[u, v]]))[0].astype(int)
        assert (cut[v, u] == image[y, x]).all()
        inside = c.contains(pts)
        np.testing.assert_allclose(c.to_full(c.from_full(pts[inside])), pts[inside], atol=1e-12)
        p = c.from_full(pts[inside])
        assert (p >= -0.5).all() and (p[:, 0] < c.width - 0.5).all() and (p[:, 1] < c.height - 0.5).all()
    centre = crops[4]
    assert abs(centre.x0 + centre.width / 2 - w / 2) <= 1 and abs(centre.y0 + centre.height / 2 - h / 2) <= 1


@pytest.mark.unit
def test_merge_drops_duplicates_keeping_the_best() -> None:
    a = np.array([[10.0, 10.0], [50.0, 50.0]])
    b = np.array([[20.0, 20.0], [60.0, 60.0]])
    part1 = (a, b, np.array([0.5, 0.9]))
    part2 = (a + 0.3, b + 0.3, np.array([0.8, 0.1]))  # same matches seen by an overlapping crop
    part3 = (np.array([[90.0, 90.0]]), np.array([[95.0, 95.0]]), np.array([0.2]))
    k0, _, s = merge_matches([part1, part2, part3], dedup_px=2.0)
    assert len(s) == 3
    np.testing.assert_allclose(s, [0.9, 0.8, 0.2])  # each duplicate resolved to its higher score
    np.testing.assert_allclose(k0[1], a[0] + 0.3)


@pytest.mark.nets
def test_tiled_matches_land_in_the_full_frame(matcher, astronaut_pair) -> None:
    """Real matcher on the five crops of a warped photo: merged matches obey the true homography
    in full-image coordinates, in both pair orders."""
    p = astronaut_pair
    r = match_tiled(matcher, p.image0, p.image1, aerial_first=True)
    assert len(r) > 300 and len(r.per_crop) == 5
    err = reprojection_errors(p.H, r.keypoints0, r.keypoints1)
    assert np.median(err) < 2.0, np.median(err)
    # matches come from every quadrant of the full frame, not from one crop's frame
    h, w = p.image0.shape[:2]
    q = (r.keypoints0[:, 0] > w / 2).astype(int) + 2 * (r.keypoints0[:, 1] > h / 2)
    assert set(np.unique(q)) == {0, 1, 2, 3}
    rev = match_tiled(matcher, p.image0, p.image1, aerial_first=False)
    np.testing.assert_allclose(rev.keypoints1, r.keypoints0)
    np.testing.assert_allclose(rev.keypoints0, r.keypoints1)


@pytest.mark.unit
def test_select_crops_covers_where_the_probe_matched() -> None:
    """Greedy cover: points in one quadrant pick that quadrant alone; points along the right
    half pick the two right quadrants; too few points to tell pick all five."""
    w, h = 800, 600
    crops = five_crops(w, h)
    rng = np.random.default_rng(0)
    top_left = rng.uniform([10, 10], [380, 280], (200, 2))
    assert [c.name for c in select_crops(crops, top_left)] == ["top_left"]
    right = rng.uniform([420, 10], [790, 590], (200, 2))
    assert [c.name for c in select_crops(crops, right)] == ["top_right", "bottom_right"]
    assert len(select_crops(crops, right[: SELECT_MIN_PROBE - 1])) == 5
    # a few stray points outside the overlap do not buy a crop of their own (coverage 90 %)
    stray = np.vstack([top_left, rng.uniform([420, 320], [790, 590], (5, 2))])
    assert [c.name for c in select_crops(crops, stray)] == ["top_left"]


@pytest.mark.nets
def test_probe_selects_the_crop_a_close_up_sees(matcher, astronaut_pair) -> None:
    """Real networks: the 'ground' image is the aerial's top-left quadrant seen closer up (2x),
    so the probe must send the pair to the crops that hold it, never to the bottom-right one,
    and the tiled matches over those crops still obey the true map."""
    aerial = astronaut_pair.image0
    h, w = aerial.shape[:2]
    close = cv2.resize(aerial[: h // 2, : w // 2], (w, h), interpolation=cv2.INTER_LINEAR)
    crops = tile_crops(matcher, aerial, close)
    chosen = [c.name for c in crops]
    assert "top_left" in chosen and "bottom_right" not in chosen and len(chosen) <= 2, chosen
    r = match_tiled(matcher, aerial, close, crops=crops)
    assert len(r) > 200
    # pixel centres at integers: x_close = 2 * x_aerial + 0.5
    err = np.linalg.norm(r.keypoints1 - (2 * r.keypoints0 + 0.5), axis=1)
    assert np.median(err) < 2.0, np.median(err)


@pytest.mark.nets
def test_a_tiled_pair_the_probe_finds_no_overlap_in_matches_no_crop(matcher, astronaut_pair) -> None:
    """Real networks: a ground photo of another scene leaves the crop probe with a handful of
    matches, so the pair matches no crop (and gives no matches) instead of all five at full
    strength; with the floor off it falls back to all five."""
    aerial = astronaut_pair.image0
    other = warped_pair("coffee", seed=2, strength=0.1).image0
    crops = tile_crops(matcher, aerial, other)
    assert crops == []
    r = match_tiled(matcher, aerial, other, crops=crops)
    assert len(r) == 0 and r.per_crop == {}
    off = matcher.derive(tile_min_probe=0)
    assert len(tile_crops(off, aerial, other)) == 5


class _CountingMatcher:
    """Answers each crop with as many matches as the crop's first pixel says: stands in for a
    matcher whose crops see the other photo's site (many matches) or not (a few dozen)."""

    def match(self, image0: np.ndarray, image1: np.ndarray) -> _Found:
        n = int(image0[0, 0, 0])
        rng = np.random.default_rng(n)
        k = rng.uniform(0, min(image0.shape[:2]) - 1, (n, 2))
        return _Found(k, k + 1.0, np.linspace(1.0, 0.5, n))


@dataclass
class _Found:
    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray


@pytest.mark.unit
def test_a_crop_with_a_few_dozen_matches_adds_none_of_them() -> None:
    """The crops that do not see the other photo's site return a few dozen coherent wrong matches;
    merged, several of them verify under one wrong F. A crop under the floor adds nothing, and
    per_crop still says how many it found."""
    w, h = 200, 160
    aerial = np.zeros((h, w, 3), np.uint8)
    counts = {"top_left": 120, "top_right": 40, "bottom_left": 59, "bottom_right": 60}
    for c in five_crops(w, h)[:4]:
        aerial[c.y0 : c.y0 + c.height, c.x0 : c.x0 + c.width] = counts[c.name]
    crops = five_crops(w, h)[:4]
    kept = match_tiled(_CountingMatcher(), aerial, aerial, crops=crops, min_crop_matches=60, dedup_px=0.01)
    everything = match_tiled(_CountingMatcher(), aerial, aerial, crops=crops, dedup_px=0.01)
    assert kept.per_crop == everything.per_crop == counts
    assert len(kept) == 120 + 60 and len(everything) == sum(counts.values())
    inside = [c for c in crops if c.name in ("top_left", "bottom_right")]
    assert all(any(c.contains(p[None])[0] for c in inside) for p in kept.keypoints0)
