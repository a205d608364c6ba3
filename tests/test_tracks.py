from __future__ import annotations

import numpy as np
import pytest

from geomatch.sfm.tracks import snap, unique_matches

pytestmark = pytest.mark.unit


def test_snap_reuses_nearby_keypoints_and_appends_the_rest() -> None:
    existing = np.array([[10.0, 10.0], [100.0, 40.0]], np.float32)
    pts = np.array([[10.8, 9.5], [200.0, 200.0], [100.0, 41.2], [200.5, 200.4], [300.0, 5.0]], np.float32)
    idx, kps = snap(existing, pts, radius=1.5)
    assert idx.tolist() == [0, 2, 1, 2, 3]  # two new points within the radius become one keypoint
    np.testing.assert_array_equal(kps[:2], existing)  # append-only: earlier indices stay valid
    np.testing.assert_allclose(kps[2], [200.0, 200.0])
    assert len(kps) == 4


def test_snap_radius_zero_turns_consolidation_off() -> None:
    existing = np.array([[10.0, 10.0]], np.float32)
    idx, kps = snap(existing, np.array([[10.0, 10.0], [10.2, 10.0]], np.float32), radius=0)
    assert idx.tolist() == [1, 2] and len(kps) == 3


def test_tracks_grow_across_pairs() -> None:
    """A scene point matched in pairs (A,B), (A,C), (B,C) with sub-pixel jitter is one keypoint per image."""
    rng = np.random.default_rng(0)
    truth = {im: rng.uniform(0, 500, (50, 2)).astype(np.float32) for im in "ABC"}
    lists = {im: np.zeros((0, 2), np.float32) for im in "ABC"}
    for a, b in (("A", "B"), ("A", "C"), ("B", "C")):
        for im in (a, b):
            jitter = rng.normal(0, 0.3, truth[im].shape).astype(np.float32)
            _, lists[im] = snap(lists[im], truth[im] + jitter, radius=1.5)
    assert all(len(v) == 50 for v in lists.values())
    lists_off = {im: np.zeros((0, 2), np.float32) for im in "ABC"}
    for a, b in (("A", "B"), ("A", "C"), ("B", "C")):
        for im in (a, b):
            _, lists_off[im] = snap(lists_off[im], truth[im], radius=0)
    assert all(len(v) == 100 for v in lists_off.values())


def test_unique_matches_keeps_first_per_keypoint() -> None:
    keep = unique_matches(np.array([0, 0, 1, 2]), np.array([5, 6, 5, 7]))
    assert keep.tolist() == [True, False, False, True]


def _snap_point_by_point(
    existing: np.ndarray, points: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """The greedy snapping spelled out one point at a time: the nearest keypoint within the
    radius, else the first earlier new point within it, else a new keypoint."""
    kps = [tuple(p) for p in existing]
    starts: list[int] = []  # the new points that started a keypoint, in order
    idx = []
    for p in points:
        d = np.hypot(*(np.asarray(existing, np.float64) - p).T) if len(existing) else np.zeros(0)
        if len(d) and d.min() <= radius:
            idx.append(int(d.argmin()))
            continue
        taken = [k for k, s in enumerate(starts) if np.hypot(*(points[s] - p)) <= radius]
        if taken:
            idx.append(len(existing) + taken[0])
        else:
            idx.append(len(kps))
            starts.append(len(idx) - 1)
            kps.append(tuple(p))
    return np.array(idx), np.array(kps, np.float32).reshape(-1, 2)


@pytest.mark.parametrize("side", [6.0, 40.0, 640.0])
def test_snap_clusters_crowded_and_isolated_points_as_one_at_a_time(side: float) -> None:
    """Isolated points skip the clustering loop; crowded ones (several within the radius of each
    other, duplicates, one at exactly the radius) still go to the first that started a keypoint."""
    rng = np.random.default_rng(int(side))
    existing = rng.uniform(0, side, (30, 2)).astype(np.float32)
    points = rng.uniform(0, side, (300, 2)).astype(np.float32)
    points[100:150] = points[50:100]
    points[-1] = points[0] + np.float32([1.5, 0.0])
    idx, kps = snap(existing, points, 1.5)
    want_idx, want_kps = _snap_point_by_point(existing, points, 1.5)
    assert idx.tolist() == want_idx.tolist()
    np.testing.assert_array_equal(kps, want_kps)
