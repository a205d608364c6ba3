"""SfM statistics and pose accuracy against ground truth.

Pose AUC follows the relative-pose protocol the paper reports (AUC of max(rotation error,
translation-direction error) over image pairs, at 3/5/10 degrees), computed over EVERY pair of
ground-truth images: a pair with an unregistered image counts as an infinite error, so failing
to register is penalised rather than hidden.

A registered camera is not necessarily a right one: a wrong pair that verification admits can
place a camera anywhere, and COLMAP still counts it. So each model is also aligned to the ground
truth and every camera is judged on its own:

- **Alignment**: a similarity (scale, rotation, translation) from the model to the ground truth,
  fitted on camera centres paired by image name, by RANSAC over triples of centres whose
  hypotheses are scored by the number of cameras they make correct (rule below), then refitted
  on those cameras (alignment.py says why not pycolmap's position-only RANSAC). A few badly
  placed cameras therefore cannot drag the others off: they are simply outliers.
- **Extent** of the scene: the diagonal of the axis-aligned bounding box of the ground-truth
  camera centres (all ground-truth images, registered or not), so the rule does not depend on
  what the model managed to register.
- **Correct camera**: registered, rotation error <= 3 deg and position error (centre distance
  after alignment) <= 5 % of the extent. ``correct`` counts those; ``registered`` keeps counting
  every camera with a pose.

Fewer than 3 registered images cannot be aligned: such a model has no correct camera.
"""

from __future__ import annotations

from collections.abc import Collection
from itertools import combinations
from typing import Any

import numpy as np
import pycolmap

from ..sfm.mapping import sfm_stats
from ..sfm.pairrotations import rotation_angle
from .alignment import TruthAlignment, align

AUC_THRESHOLDS = (3.0, 5.0, 10.0)
MAX_ROTATION_ERROR_DEG = 3.0
MAX_POSITION_ERROR_FRACTION = 0.05  # of the scene extent


def auc(errors: list[float] | np.ndarray, thresholds: tuple[float, ...]) -> list[float]:
    """Area under the recall-vs-error curve up to each threshold (as in SuperGlue / LoFTR)."""
    errs = np.sort(np.asarray(errors, dtype=np.float64))
    recall = (np.arange(len(errs)) + 1) / max(len(errs), 1)
    errs = np.concatenate([[0.0], errs])
    recall = np.concatenate([[0.0], recall])
    out = []
    for t in thresholds:
        last = int(np.searchsorted(errs, t))
        e = np.concatenate([errs[:last], [t]])
        r = np.concatenate([recall[:last], [recall[last - 1]]])
        out.append(float(np.trapezoid(r, x=e) / t))
    return out


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
        errs.append(max(rotation_angle(R_es.T @ R_gt), _dir_angle_deg(t_es, t_gt)))
    return np.asarray(errs, np.float64)


def _centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -R.T @ t


def scene_extent(gt: pycolmap.Reconstruction) -> float:
    """Diagonal of the bounding box of the ground-truth camera centres."""
    centres = np.array([_centre(R, t) for R, t in _poses(gt).values()]).reshape(-1, 3)
    if len(centres) < 2:
        return 0.0
    return float(np.linalg.norm(centres.max(0) - centres.min(0)))


def align_cameras(
    rec: pycolmap.Reconstruction,
    gt: pycolmap.Reconstruction,
    max_rotation_deg: float,
    max_position: float,
    leave_out: Collection[str] = (),
) -> tuple[list[str], TruthAlignment] | None:
    """The robust alignment (alignment.py) of the registered cameras the ground truth knows, but
    those in ``leave_out``, with their names in its order; None for fewer than three or no fit.
    Leaving a camera out keeps it from pulling the alignment it is judged by."""
    est, ref = _poses(rec), _poses(gt)
    common = sorted((set(est) & set(ref)) - set(leave_out))
    if len(common) < 3 or max_position <= 0:
        return None
    found = align(
        np.array([est[n][0] for n in common]),
        np.array([_centre(*est[n]) for n in common]),
        np.array([ref[n][0] for n in common]),
        np.array([_centre(*ref[n]) for n in common]),
        max_rotation_deg,
        max_position,
    )
    return None if found is None else (common, found)


def camera_errors(
    rec: pycolmap.Reconstruction,
    gt: pycolmap.Reconstruction,
    max_rotation_deg: float,
    max_position: float,
) -> dict[str, tuple[float, float]] | None:
    """Rotation error (deg) and position error (ground-truth units) of every registered camera that
    the ground truth knows, after the robust alignment of alignment.py; None when none exists."""
    aligned = align_cameras(rec, gt, max_rotation_deg, max_position)
    if aligned is None:
        return None
    common, found = aligned
    return {
        n: (float(r), float(p))
        for n, r, p in zip(common, found.rotation_errors_deg, found.position_errors, strict=True)
    }


def correctness(
    rec: pycolmap.Reconstruction,
    gt: pycolmap.Reconstruction,
    max_rotation_deg: float = MAX_ROTATION_ERROR_DEG,
    max_position_fraction: float = MAX_POSITION_ERROR_FRACTION,
) -> dict[str, Any]:
    """``registered`` and ``correct`` for one model, by the rule of the module docstring."""
    extent = scene_extent(gt)
    max_pos = max_position_fraction * extent
    registered = sorted(_poses(rec))
    errors = camera_errors(rec, gt, max_rotation_deg, max_pos)
    out: dict[str, Any] = {
        "registered": len(registered),
        "images": int(gt.num_images()),
        "aligned": errors is not None,
        "extent": extent,
        "rotation_threshold_deg": max_rotation_deg,
        "position_threshold": max_pos,
    }
    errors = errors or {}
    good = sorted(n for n, (r, p) in errors.items() if r <= max_rotation_deg and p <= max_pos)
    out.update(
        correct=len(good),
        correct_names=good,
        # every registered camera that is not correct, with its errors (None: not alignable)
        wrong={
            n: None if n not in errors else {"rotation_deg": errors[n][0], "position": errors[n][1]}
            for n in registered
            if n not in good
        },
    )
    if errors:
        rot = [r for r, _ in errors.values()]
        pos = [p for _, p in errors.values()]
        out.update(
            median_rotation_error_deg=float(np.median(rot)),
            median_position_error=float(np.median(pos)),
            max_position_error=float(np.max(pos)),
        )
    return out


def evaluate(rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction) -> dict[str, Any]:
    """Pose AUC over all pairs, per-camera correctness after robust alignment, SfM statistics."""
    errs = relative_pose_errors(rec, gt)
    out: dict[str, Any] = sfm_stats(rec, gt.num_images())
    for t, v in zip(AUC_THRESHOLDS, auc(errs, AUC_THRESHOLDS), strict=True):
        out[f"auc@{t:g}"] = 100.0 * v
    out.update(correctness(rec, gt))
    return out
