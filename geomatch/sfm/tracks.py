"""Keypoint consolidation: one keypoint per image location, so matches of many pairs form long tracks.

Dense matches are not detections: the same scene point matched in pairs (A, B) and (A, C) lands
at slightly different sub-pixel spots of A. COLMAP only links observations that share a keypoint
index, so without consolidation every track has length two. Each image keeps an append-only list
of keypoints; a new match endpoint snaps to the nearest existing keypoint within ``radius`` pixels,
else it is appended. Append-only means indices handed out for earlier pairs never change.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def snap(existing: np.ndarray, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of ``points`` into the keypoint list after snapping, and the new list.

    ``radius <= 0`` turns consolidation off: every point is appended as its own keypoint.
    New points closer than ``radius`` to each other become one keypoint too (the first wins).
    """
    existing = np.asarray(existing, np.float32).reshape(-1, 2)
    points = np.asarray(points, np.float32).reshape(-1, 2)
    n0 = len(existing)
    if radius <= 0:
        return np.arange(n0, n0 + len(points)), np.concatenate([existing, points])
    idx = np.full(len(points), -1, np.int64)
    if n0:
        dist, nn = cKDTree(existing).query(points, k=1, distance_upper_bound=radius)
        hit = np.isfinite(dist)
        idx[hit] = nn[hit]
    rest = np.flatnonzero(idx < 0)
    cluster, first = _clusters(points[rest], radius)
    idx[rest] = n0 + cluster
    return idx, np.concatenate([existing, points[rest][first]])


def _clusters(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy clustering in input order (callers pass best first): a point not yet taken starts
    a cluster and takes every point within ``radius`` not yet taken. Each point's cluster (in
    the order they start) and the mask of the points that start one.

    Only points with a neighbour go through the Python loop (which holds the GIL): an isolated
    point is never taken by another and takes only itself, and most points are isolated (a
    pair's new keypoints; all of a prepared pair's when it is rebased)."""
    n = len(points)
    if not n:
        return np.zeros(0, np.int64), np.zeros(0, bool)
    tree = cKDTree(points)
    owner = np.full(n, -1, np.int64)  # the point that started each point's cluster
    crowded = tree.query_ball_point(points, radius, return_length=True) > 1  # itself and more
    owner[~crowded] = np.flatnonzero(~crowded)
    for k in np.flatnonzero(crowded).tolist():
        if owner[k] < 0:
            for m in tree.query_ball_point(points[k], radius):
                if owner[m] < 0:
                    owner[m] = k
    first = owner == np.arange(n)
    return (np.cumsum(first) - 1)[owner], first


def unique_matches(idx0: np.ndarray, idx1: np.ndarray) -> np.ndarray:
    """Mask keeping the first match per keypoint on either side (and no self-duplicates), since
    snapping can map two matches of one pair onto the same keypoint."""
    keep = np.zeros(len(idx0), bool)
    seen0: set[int] = set()
    seen1: set[int] = set()
    for k, (a, b) in enumerate(zip(idx0.tolist(), idx1.tolist(), strict=True)):
        if a in seen0 or b in seen1:
            continue
        seen0.add(a)
        seen1.add(b)
        keep[k] = True
    return keep
