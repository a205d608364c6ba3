"""SfM statistics and pose accuracy against ground truth.

Pose AUC follows the relative-pose protocol the paper reports (AUC of max(rotation error,
translation-direction error) over image pairs, at 3/5/10 degrees), computed over EVERY pair of
ground-truth images: a pair with an unregistered image counts as an infinite error, so failing
to register is penalised rather than hidden. The model is also aligned to the ground truth
(a similarity fitted on camera centres, robust to outliers) to report absolute errors:
rotation in degrees and camera position in ground-truth units.
"""

from __future__ import annotations

from itertools import combinations
from typing import Any

import numpy as np
import pycolmap

from .homography import auc

AUC_THRESHOLDS = (3.0, 5.0, 10.0)


def sfm_stats(rec: pycolmap.Reconstruction, n_images: int) -> dict[str, Any]:
    return {
        "registered": int(rec.num_reg_images()),
        "images": int(n_images),
        "points3D": int(rec.num_points3D()),
        "observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0,
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image())
        if rec.num_reg_images()
        else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error())
        if rec.num_points3D()
        else 0.0,
    }


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def _dir_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return 180.0
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _poses(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            T = im.cam_from_world()
            out[im.name] = (T.rotation.matrix(), np.asarray(T.translation))
    return out


def relative_pose_errors(rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction) -> np.ndarray:
    """max(rotation, translation-direction) error in degrees for every ground-truth pair."""
    est, ref = _poses(rec), _poses(gt)
    errs = []
    for a, b in combinations(sorted(ref), 2):
        if a not in est or b not in est:
            errs.append(np.inf)
            continue
        (Ra, ta), (Rb, tb) = ref[a], ref[b]
        (Ea, sa), (Eb, sb) = est[a], est[b]
        R_gt, t_gt = Rb @ Ra.T, tb - Rb @ Ra.T @ ta
        R_es, t_es = Eb @ Ea.T, sb - Eb @ Ea.T @ sa
        errs.append(max(_angle_deg(R_es.T @ R_gt), _dir_angle_deg(t_es, t_gt)))
    return np.asarray(errs, np.float64)


def evaluate(
    rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction, max_center_error: float = 1.0
) -> dict[str, Any]:
    """Pose AUC over all pairs, absolute errors after similarity alignment, SfM statistics."""
    errs = relative_pose_errors(rec, gt)
    out: dict[str, Any] = sfm_stats(rec, gt.num_images())
    for t, v in zip(AUC_THRESHOLDS, auc(errs, AUC_THRESHOLDS), strict=True):
        out[f"auc@{t:g}"] = 100.0 * v
    aligned = pycolmap.Reconstruction(rec)
    sim = (
        pycolmap.align_reconstructions_via_proj_centers(aligned, gt, max_center_error)
        if rec.num_reg_images() >= 3
        else None
    )
    if sim is not None:
        aligned.transform(sim)
        est, ref = _poses(aligned), _poses(gt)
        common = sorted(set(est) & set(ref))
        rot = [_angle_deg(est[n][0] @ ref[n][0].T) for n in common]
        pos = [float(np.linalg.norm(-est[n][0].T @ est[n][1] + ref[n][0].T @ ref[n][1])) for n in common]
        out.update(
            aligned=True,
            median_rotation_error_deg=float(np.median(rot)),
            median_position_error=float(np.median(pos)),
            max_position_error=float(np.max(pos)),
        )
    else:
        out["aligned"] = False
    return out
