"""A large survey's matches thinned for the global mapper: each photo keeps its most matched
keypoints, the matches between kept keypoints all survive, and a project under its budget is
left as it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.sfm.colmapdb import COLMAP_OFFSET
from geomatch.sfm.thinmatches import (
    OBSERVATIONS,
    OBSERVATIONS_PER_IMAGE_FLOOR,
    kept_keypoints,
    per_image_budget,
    thin_matches,
)
from geomatch.sfm.trackrefine import Tracks

pytestmark = pytest.mark.unit


def _tracks(sizes: list[int], edges: list[tuple[int, int]]) -> Tracks:
    return Tracks(list(range(1, len(sizes) + 1)), np.cumsum([0, *sizes]), np.array(edges, np.int64))


def test_each_photo_keeps_the_keypoints_matched_in_most_pairs() -> None:
    # image 1: nodes 0-2, image 2: nodes 3-5, image 3: nodes 6-8. Node 1 is matched to both
    # other photos, node 0 to one, node 2 to none; in images 2 and 3 likewise nodes 4 and 7.
    t = _tracks([3, 3, 3], [(1, 4), (1, 7), (4, 7), (0, 3), (5, 8)])
    keep = kept_keypoints(t, per_image=1)
    assert np.flatnonzero(keep).tolist() == [1, 4, 7]
    keep = kept_keypoints(t, per_image=2)
    # ties (nodes 3 and 5 both matched once) go to the lower index; an unmatched keypoint never stays
    assert np.flatnonzero(keep).tolist() == [0, 1, 3, 4, 7, 8]
    assert not kept_keypoints(t, per_image=3)[2]


def test_the_budget_is_shared_by_the_photos_down_to_a_floor() -> None:
    assert per_image_budget(100) == OBSERVATIONS // 100
    assert per_image_budget(OBSERVATIONS // OBSERVATIONS_PER_IMAGE_FLOOR * 4) == OBSERVATIONS_PER_IMAGE_FLOOR
    assert per_image_budget(0) == OBSERVATIONS


def _database(
    path: Path, n_images: int, n_keypoints: int, seed: int = 0
) -> dict[tuple[int, int], np.ndarray]:
    """Images in a row, each matched to the next two; keypoint k of one image matched to keypoint
    k of the other where a random mask lets it (so the keypoints differ in how often they match)."""
    rng = np.random.default_rng(seed)
    db = pycolmap.Database.open(str(path))
    try:
        cam = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 500.0, 640, 480)
        cam_id = db.write_camera(cam)
        ids = []
        for i in range(n_images):
            im = pycolmap.Image(name=f"{i:03d}.jpg", camera_id=cam_id)
            ids.append(db.write_image(im))
            xy = rng.uniform(0, 600, (n_keypoints, 2)).astype(np.float32) + COLMAP_OFFSET
            db.write_keypoints(ids[-1], xy)
        written = {}
        for i in range(n_images):
            for j in (i + 1, i + 2):
                if j >= n_images:
                    continue
                k = np.flatnonzero(rng.random(n_keypoints) < 0.7)
                m = np.stack([k, k], 1).astype(np.uint32)
                g = pycolmap.TwoViewGeometry()
                g.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
                g.inlier_matches = m
                db.write_two_view_geometry(ids[i], ids[j], g)
                written[(ids[i], ids[j])] = m
    finally:
        db.close()
    return written


def _inliers(path: Path) -> dict[tuple[int, int], np.ndarray]:
    db = pycolmap.Database.open(str(path))
    try:
        ids, geometries = db.read_two_view_geometries()
        return {
            pycolmap.pair_id_to_image_pair(p): np.asarray(g.inlier_matches).reshape(-1, 2)
            for p, g in zip(ids, geometries, strict=True)
        }
    finally:
        db.close()


def test_only_matches_between_kept_keypoints_reach_the_mapper(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    written = _database(path, n_images=6, n_keypoints=200)
    stats = thin_matches(path, per_image=80)
    after = _inliers(path)
    assert stats["matches_before"] == sum(len(m) for m in written.values())
    assert stats["matches_after"] == sum(len(m) for m in after.values()) < stats["matches_before"] / 2
    # what stays is a subset of what was verified, each photo's kept keypoints at most its budget
    used: dict[int, set[int]] = {}
    for (a, b), m in after.items():
        assert {tuple(r) for r in m.tolist()} <= {tuple(r) for r in written[(a, b)].tolist()}
        used.setdefault(a, set()).update(m[:, 0].tolist())
        used.setdefault(b, set()).update(m[:, 1].tolist())
    assert max(len(s) for s in used.values()) <= 80
    # the kept keypoints are each photo's most matched ones: none matched less often than the
    # photo's 80th most matched keypoint
    counts: dict[int, np.ndarray] = {}
    for (a, b), m in written.items():
        for img, col in ((a, 0), (b, 1)):
            counts.setdefault(img, np.zeros(200, int))[m[:, col].astype(int)] += 1
    for img, kept in used.items():
        assert counts[img][list(kept)].min() >= np.sort(counts[img])[::-1][79]


def test_a_project_under_its_budget_is_left_as_it_was(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    written = _database(path, n_images=4, n_keypoints=100)
    stats = thin_matches(path, per_image=100)
    assert stats["matches_after"] == stats["matches_before"]
    after = _inliers(path)
    assert set(after) == set(written)
    for pair, m in written.items():
        assert np.array_equal(after[pair], m)
