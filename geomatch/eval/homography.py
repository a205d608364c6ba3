"""HPatches-style metrics of matches on a pair related by a known homography (the warped photos of
:mod:`geomatch.synth.photos`): each match's reprojection error, and the corner error of a homography
fitted to the matches.
"""

from __future__ import annotations

import cv2
import numpy as np


def apply_h(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.concatenate([points, np.ones((len(points), 1))], 1) @ H.T
    return p[:, :2] / p[:, 2:3]


def reprojection_errors(H: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray) -> np.ndarray:
    """Distance in image1 between each match's point and where H sends its image0 point."""
    if len(kpts0) == 0:
        return np.zeros(0)
    return np.linalg.norm(apply_h(H, kpts0.astype(np.float64)) - kpts1, axis=1)


def corner_error(H_gt: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray, width: int, height: int) -> float:
    """Mean corner distance of the homography estimated from the matches (inf when it fails)."""
    if len(kpts0) < 4:
        return float("inf")
    H_est, _ = cv2.findHomography(kpts0.astype(np.float64), kpts1.astype(np.float64), cv2.USAC_MAGSAC, 3.0)
    if H_est is None:
        return float("inf")
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], np.float64)
    return float(np.linalg.norm(apply_h(H_est, corners) - apply_h(H_gt, corners), axis=1).mean())
