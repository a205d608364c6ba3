"""Which verified pairs of a run are wrong, judged by the ground truth's epipolar geometry.

A camera counted correct says the model came out right; it does not say how close it came to
going wrong. Repeated and mirror-symmetric facades give pairs of views that share nothing a few
hundred geometrically consistent matches; they pass two-view verification and, when enough of
them reach the mapper, glue different parts of the scene together. Counting them tells whether a
right model was a robust one and whether a filter does its job.

A verified pair is *wrong* when most of its inliers lie off the ground truth's epipolar geometry:
the ground-truth fundamental matrix (from both surveyed cameras, so it carries their relative
rotation and translation direction) leaves fewer than half of the inliers within
``max(4 px, 0.4 % of the image diagonal)`` of their epipolar lines (symmetric distance). On the
surveyed scenes a right pair keeps nearly all its inliers within that band, a wrong one almost none.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..epipolar.geometry import skew

MIN_INLIERS = 15  # COLMAP's min_num_inliers: pairs below it do not reach the mapper
MAX_DISTANCE_PX = 4.0
MAX_DISTANCE_DIAGONAL = 0.004
MIN_AGREEING = 0.5


@dataclass(frozen=True)
class PairVerdict:
    name0: str
    name1: str
    inliers: int
    agreeing: float  # share of the inliers within the band of the ground truth's epipolar lines
    wrong: bool
    used: bool  # reached the mapper (not dropped by the view-graph checks)


def gt_fundamental(gt: pycolmap.Reconstruction, name0: str, name1: str) -> np.ndarray | None:
    """F with x1^T F x0 = 0 in COLMAP pixel coordinates; None when an image is unknown or the
    two surveyed centres coincide (no epipolar geometry)."""
    ims = {im.name: im for im in gt.images.values() if im.has_pose}
    if name0 not in ims or name1 not in ims:
        return None
    T0, T1 = ims[name0].cam_from_world(), ims[name1].cam_from_world()
    rel = T1 * T0.inverse()
    t = np.asarray(rel.translation, np.float64)
    if np.linalg.norm(t) < 1e-9:
        return None
    K0 = gt.cameras[ims[name0].camera_id].calibration_matrix()
    K1 = gt.cameras[ims[name1].camera_id].calibration_matrix()
    E = skew(t) @ rel.rotation.matrix()
    return np.linalg.inv(K1).T @ E @ np.linalg.inv(K0)


def epipolar_distances(F: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Symmetric point-to-line distance in pixels, the larger of the two images' distances."""
    h0 = np.c_[p0, np.ones(len(p0))]
    h1 = np.c_[p1, np.ones(len(p1))]
    l1 = h0 @ F.T  # lines in image 1
    l0 = h1 @ F  # lines in image 0
    num = np.abs(np.sum(h1 * l1, axis=1))
    d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
    d0 = num / np.maximum(np.hypot(l0[:, 0], l0[:, 1]), 1e-12)
    return np.maximum(d0, d1)


def judge_pairs(
    database: str | Path, gt: pycolmap.Reconstruction, dropped: Iterable[tuple[str, str]] = ()
) -> list[PairVerdict]:
    """Every verified pair of ``database`` with at least :data:`MIN_INLIERS` inliers whose images
    the ground truth knows. ``dropped``: name pairs the view-graph checks kept from the mapper."""
    gone = {frozenset(p) for p in dropped}
    db = pycolmap.Database.open(str(database))
    try:
        images = {im.image_id: im for im in db.read_all_images()}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        pair_ids, geometries = db.read_two_view_geometries()
        keypoints: dict[int, np.ndarray] = {}
        out: list[PairVerdict] = []
        for pid, g in zip(pair_ids, geometries, strict=True):
            m = g.inlier_matches
            if len(m) < MIN_INLIERS:
                continue
            a, b = pycolmap.pair_id_to_image_pair(pid)
            n0, n1 = images[a].name, images[b].name
            F = gt_fundamental(gt, n0, n1)
            if F is None:
                continue
            for i in (a, b):
                if i not in keypoints:
                    keypoints[i] = db.read_keypoints(i)[:, :2].astype(np.float64)
            cam = cameras[images[a].camera_id]
            limit = max(MAX_DISTANCE_PX, MAX_DISTANCE_DIAGONAL * float(np.hypot(cam.width, cam.height)))
            d = epipolar_distances(F, keypoints[a][m[:, 0]], keypoints[b][m[:, 1]])
            agree = float(np.mean(d <= limit))
            out.append(
                PairVerdict(n0, n1, len(m), agree, agree < MIN_AGREEING, frozenset((n0, n1)) not in gone)
            )
    finally:
        db.close()
    return out


def summary(verdicts: list[PairVerdict]) -> dict[str, object]:
    """The counts a run's summary and ``geomatch eval`` report."""
    wrong = [v for v in verdicts if v.wrong]
    return {
        "verified_pairs": len(verdicts),
        "wrong_pairs": len(wrong),
        "wrong_pairs_admitted": sum(v.used for v in wrong),
        "right_pairs_dropped": sum(not v.used and not v.wrong for v in verdicts),
        "wrong": [
            {
                "pair": [v.name0, v.name1],
                "inliers": v.inliers,
                "agreeing": round(v.agreeing, 3),
                "used": v.used,
            }
            for v in sorted(wrong, key=lambda v: -v.inliers)
        ],
    }
