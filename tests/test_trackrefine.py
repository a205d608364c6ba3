"""Track refinement on the photos: points placed a pixel off land on their reference's spot."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from geomatch.eval.homography import apply_h
from geomatch.imageio import read_gray
from geomatch.metadata import read_metadata
from geomatch.sfm.colmapdb import COLMAP_OFFSET, ColmapDatabase
from geomatch.sfm.trackrefine import SURVEY, TrackRefineOptions, Tracks, references, refine_tracks, tasks
from geomatch.synth.photos import warped_pair

pytestmark = pytest.mark.unit


def _tracks(sizes: list[int], edges: list[tuple[int, int]]) -> Tracks:
    return Tracks(list(range(1, len(sizes) + 1)), np.cumsum([0, *sizes]), np.array(edges, np.int64))


def test_the_reference_is_the_observation_matched_most() -> None:
    # images 1..3 with 2 keypoints each (nodes 0-1, 2-3, 4-5); track {0, 2, 4}: node 2 has 2 edges
    t = _tracks([2, 2, 2], [(0, 2), (2, 4)])
    ref = references(t, max_track=64)
    assert ref.tolist() == [2, -1, 2, -1, 2, -1]
    assert sorted(map(tuple, tasks(t, ref).tolist())) == [(2, 0), (2, 4)]


def test_a_track_with_two_points_of_one_photo_is_left_alone() -> None:
    # nodes 0 and 1 are both in image 1, chained through image 2: two scene points merged
    t = _tracks([2, 2], [(0, 2), (1, 2)])
    assert (references(t, max_track=64) == -1).all()


def test_a_track_chained_through_two_points_of_one_photo_still_aligns_its_other_photos() -> None:
    # images 1..3; nodes 0 and 1 (image 1) both matched to node 2 (image 2), node 2 to node 4
    # (image 3): image 1's two points stay, image 2's point is the reference and image 3's moves
    t = _tracks([2, 2, 2], [(0, 2), (1, 2), (2, 4)])
    ref = references(t, max_track=64)
    assert ref.tolist() == [-1, -1, 2, -1, 2, -1]
    assert tasks(t, ref).tolist() == [[2, 4]]


def test_an_overlong_track_is_left_alone() -> None:
    t = _tracks([1, 1, 1], [(0, 1), (1, 2)])
    assert (references(t, max_track=2) == -1).all()
    assert (references(t, max_track=3) >= 0).all()


def _project(tmp: Path, noise: float, seed: int = 0) -> tuple[Path, dict[str, np.ndarray], dict[str, int]]:
    """Three photos (one package photo and two warps of it), 300 points seen in all three, each
    warp's points ``noise`` px off their true spot, matched all ways round and verified."""
    w1, w2 = warped_pair("astronaut", seed=1, strength=0.12), warped_pair("astronaut", seed=2, strength=0.12)
    images = {"a.png": w1.image0, "b.png": w1.image1, "c.png": w2.image1}
    for name, im in images.items():
        cv2.imwrite(str(tmp / name), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    rng = np.random.default_rng(seed)
    h, w = w1.image0.shape[:2]
    pa = rng.uniform([60, 60], [w - 60, h - 60], size=(600, 2))
    truth = {"a.png": pa, "b.png": apply_h(w1.H, pa), "c.png": apply_h(w2.H, pa)}
    inside = np.all([(p > 40).all(1) & (p[:, 0] < w - 40) & (p[:, 1] < h - 40) for p in truth.values()], 0)
    truth = {k: v[inside][:300] for k, v in truth.items()}
    n = len(truth["a.png"])
    db_path = tmp / "database.db"
    ids = {}
    with ColmapDatabase(db_path) as db:
        for name in images:
            ids[name] = db.add_image(name, read_metadata(tmp / name))
            pts = truth[name] + (rng.uniform(-noise, noise, (n, 2)) if name != "a.png" else 0)
            db.db.write_keypoints(ids[name], (pts + COLMAP_OFFSET).astype(np.float32))
        for x, y in (("a.png", "b.png"), ("a.png", "c.png"), ("b.png", "c.png")):
            g = pycolmap.TwoViewGeometry()
            g.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            g.inlier_matches = np.stack([np.arange(n), np.arange(n)], 1).astype(np.uint32)
            db.db.write_two_view_geometry(ids[x], ids[y], g)
    return db_path, truth, ids


def _keypoints(db_path: Path, image_id: int) -> np.ndarray:
    with ColmapDatabase(db_path) as db:
        return db.keypoints(image_id)


def test_observations_move_onto_the_reference_spot_in_every_photo(tmp_path: Path) -> None:
    db_path, truth, ids = _project(tmp_path, noise=1.5)
    before = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
    stats = refine_tracks(db_path, tmp_path, TrackRefineOptions(radius=10, sigma=0.7))
    after = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
    # every track has the same three observations, so the first photo's point is each reference
    # and stays exactly where it was
    assert stats["tracks"] == 300 and stats["observations_to_align"] == 600
    assert np.array_equal(after["a.png"], before["a.png"])
    for k in ("b.png", "c.png"):
        assert np.median(before[k]) > 0.7
        assert np.median(after[k]) < 0.2, k
    assert stats["moved"] > 0.8 * 600


def test_a_survey_brings_points_several_pixels_off_to_the_reference_spot_through_the_half_size_pass(
    tmp_path: Path,
) -> None:
    # 3.5 px off, as two observations of a point placed at 640 px on a 2000 px photo can be: beyond
    # the full-size alignment's reach on its own
    runs = {}
    for run, opts in (("full size alone", replace(SURVEY, coarse_sigma=0.0)), ("both", SURVEY)):
        (tmp_path / run).mkdir()
        db_path, truth, ids = _project(tmp_path / run, noise=3.5, seed=1)
        before = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
        refine_tracks(db_path, tmp_path / run, opts)
        runs[run] = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
    alone, after = runs["full size alone"], runs["both"]
    for k in ("b.png", "c.png"):
        assert np.median(before[k]) > 2.0
        assert np.median(after[k]) < np.median(before[k]) / 3, k
        assert np.mean(after[k] < 0.5) > np.mean(alone[k] < 0.5) + 0.08, k


def test_without_texture_nothing_moves(tmp_path: Path) -> None:
    db_path, _, ids = _project(tmp_path, noise=1.5)
    flat = np.full((512, 512, 3), 128, np.uint8)
    for name in ids:
        cv2.imwrite(str(tmp_path / name), flat)
    before = {k: _keypoints(db_path, i) for k, i in ids.items()}
    assert refine_tracks(db_path, tmp_path)["moved"] == 0
    for k, i in ids.items():
        assert np.array_equal(_keypoints(db_path, i), before[k])


def test_photos_beyond_the_working_size_are_aligned_at_it_and_answer_in_photo_pixels(tmp_path: Path) -> None:
    # the 512 px photos aligned at 384 px: each point comes back where it belongs in the photo,
    # within what half the resolution resolves
    db_path, truth, ids = _project(tmp_path, noise=1.5)
    before = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
    refine_tracks(db_path, tmp_path, TrackRefineOptions(radius=8, sigma=0.7, max_side=384))
    after = {k: np.linalg.norm(_keypoints(db_path, ids[k]) - truth[k], axis=1) for k in ids}
    for k in ("b.png", "c.png"):
        assert np.median(after[k]) < min(0.4, np.median(before[k]) / 2), k


def test_a_jpeg_is_read_grey_at_the_working_size_as_a_full_decode_and_resize_would(tmp_path: Path) -> None:
    photo = warped_pair("astronaut", seed=3, strength=0.1).image0
    big = cv2.resize(photo, (1800, 1200), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(tmp_path / "p.jpg"), cv2.cvtColor(big, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    gray, scale = read_gray(tmp_path / "p.jpg", 600)
    assert gray.shape == (400, 600) and scale == (600 / 1800, 400 / 1200)
    full = cv2.cvtColor(cv2.imread(str(tmp_path / "p.jpg")), cv2.COLOR_BGR2GRAY).astype(np.float32) / 255
    reference = cv2.resize(full, (600, 400), interpolation=cv2.INTER_AREA)
    assert np.abs(gray - reference).mean() < 0.01
    same, one = read_gray(tmp_path / "p.jpg", None)
    assert same.shape == (1200, 1800) and one == (1.0, 1.0)
