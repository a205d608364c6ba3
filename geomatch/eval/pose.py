"""Relative-pose error from matches, by the SuperGlue / LoFTR protocol, so our numbers compare with theirs.

Keypoints follow geomatch's convention (pixel centres at integer coordinates, x right, y down), so
the intrinsics K apply to ``pixel + 0.5``. The essential matrix is fitted with OpenCV's RANSAC at a
threshold of ``threshold_px`` divided by the mean focal length (the normalised-coordinate
equivalent), every returned candidate is decomposed with ``recoverPose`` and the one with most
cheirality inliers wins. The pose error is max(rotation error, translation-direction error), the
latter folded to [0, 90] degrees because an essential matrix fixes t only up to sign.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from .metrics import auc


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_error_deg(R: np.ndarray, R_gt: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R.T @ R_gt) - 1) / 2, -1.0, 1.0))))


def estimate_relative_pose(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    threshold_px: float = 0.5,
    prob: float = 0.99999,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R, t, inlier mask) of cam1_from_cam0, or None with fewer than 5 matches or no solution."""
    kpts0 = np.asarray(kpts0, np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, np.float64).reshape(-1, 2)
    if len(kpts0) < 5:
        return None
    f_mean = float(np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]]))
    n0 = (kpts0 + 0.5 - K0[[0, 1], [2, 2]]) / K0[[0, 1], [0, 1]]
    n1 = (kpts1 + 0.5 - K1[[0, 1], [2, 2]]) / K1[[0, 1], [0, 1]]
    E, mask = cv2.findEssentialMat(
        n0, n1, np.eye(3), method=cv2.RANSAC, prob=prob, threshold=threshold_px / f_mean
    )
    if E is None or mask is None:
        return None
    best, best_n = None, 0
    for E_i in np.split(E, len(E) // 3):
        # OpenCV binds the positional 1e9 to the output R of the 4-result overload (a scalar converts
        # to a Mat), not to distanceThresh: no distance limit is set here and OpenCV's default (50)
        # applies to the cheirality count; the stubs pick the 5-result distanceThresh overload
        n, R, t, _ = cv2.recoverPose(E_i, n0, n1, np.eye(3), 1e9, mask=mask.copy())  # type: ignore[misc]
        if n > best_n:
            best_n, best = n, (R, t.ravel(), mask.ravel() > 0)
    return best


def relative_pose_error(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    threshold_px: float = 0.5,
) -> tuple[float, float]:
    """(rotation error, translation-direction error) in degrees; (inf, inf) when no pose comes out."""
    est = estimate_relative_pose(kpts0, kpts1, K0, K1, threshold_px)
    if est is None:
        return float("inf"), float("inf")
    R, t, _ = est
    err_t = _angle_deg(t, np.asarray(t_gt, np.float64).ravel())
    return rotation_error_deg(R, R_gt), min(err_t, 180.0 - err_t)


def pose_auc(errors: list[float] | np.ndarray, thresholds: tuple[float, ...] = (5, 10, 20)) -> list[float]:
    """AUC of the pose-error recall curve up to each threshold (degrees); infinite errors count as misses."""
    return auc(errors, thresholds)


def shuffled_errors(
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    error: Callable[[np.ndarray, np.ndarray], float],
    runs: int,
    seed: int = 0,
) -> list[float]:
    """``error`` of the same matches under ``runs`` orderings (the first is the given order).

    OpenCV's RANSAC is deterministic for one input order, but which minimal samples it draws
    depends on that order, so adding or removing a single match re-draws every sample, and one
    ordering against another moves AUC@10 as much as the differences between methods
    (docs/benchmarks.md, "Relative pose"). Averaging the AUC over orderings measures
    the matches, not the draw.
    """
    k0, k1 = np.asarray(kpts0), np.asarray(kpts1)
    rng = np.random.default_rng(seed)
    out = []
    for r in range(max(1, runs)):
        order = np.arange(len(k0)) if r == 0 else rng.permutation(len(k0))
        out.append(float(error(k0[order], k1[order])))
    return out


def auc_over_runs(
    errors: np.ndarray | list[list[float]], thresholds: tuple[float, ...] = (5, 10, 20)
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation over runs of the pose AUC (fractions, as :func:`pose_auc`);
    ``errors`` is (pairs, runs)."""
    e = np.asarray(errors, np.float64).reshape(len(errors), -1)
    per_run = np.array([[a for a in pose_auc(e[:, r], thresholds)] for r in range(e.shape[1])])
    return per_run.mean(0), per_run.std(0)
