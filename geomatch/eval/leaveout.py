"""Leave-one-out for localization: a model without one of its images, and a localized camera's
error against ground truth.

The model without an image is the full model with that image's frame deregistered (COLMAP drops
its observations, and the 3D points left with fewer than two): mapping the project again
without it, once per image, would cost a mapping each. What stays is that the remaining points
were triangulated with its observations too; their positions are no more than a bundle adjustment
away from what the other images alone give, while the localization itself sees neither its
keypoints, nor its tracks, nor its pose (its matches to the model are made afresh).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pycolmap

from .alignment import align
from .metrics import scene_extent


def without_image(model: Path, name: str, dest: Path) -> Path:
    """``model`` written to ``dest`` without ``name`` (binary); returns ``dest``."""
    rec = pycolmap.Reconstruction(str(model))
    image = rec.find_image_with_name(name)
    if image is not None and image.has_pose:
        rec.deregister_frame(image.frame_id)
    dest.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(dest))
    return dest


def _poses(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            out[im.name] = (im.cam_from_world().rotation.matrix(), np.asarray(im.projection_center()))
    return out


def pose_error(
    model: pycolmap.Reconstruction,
    gt: pycolmap.Reconstruction,
    name: str,
    R: np.ndarray,
    centre: np.ndarray,
    max_rotation_deg: float = 3.0,
    max_position_share: float = 0.05,
) -> tuple[float, float, float] | None:
    """(rotation error deg, position error in ground-truth units, the same in % of the scene
    extent) of a camera localized in ``model`` (cam_from_world rotation ``R``, ``centre``), after
    the robust alignment of the model's OTHER cameras to the ground truth (eval/alignment.py), so
    the camera judged does not pull the alignment its way. None when no alignment is found."""
    est: Mapping[str, tuple[np.ndarray, np.ndarray]] = _poses(model)
    ref = _poses(gt)
    common = sorted(n for n in set(est) & set(ref) if n != name)
    extent = scene_extent(gt)
    if len(common) < 3 or name not in ref:
        return None
    found = align(
        np.array([est[n][0] for n in common]),
        np.array([est[n][1] for n in common]),
        np.array([ref[n][0] for n in common]),
        np.array([ref[n][1] for n in common]),
        max_rotation_deg,
        max_position_share * extent,
    )
    if found is None:
        return None
    c = found.scale * found.rotation @ np.asarray(centre, np.float64) + found.translation
    position = float(np.linalg.norm(c - ref[name][1]))
    R_gt_frame = np.asarray(R) @ found.rotation.T  # cam_from_gt = cam_from_model @ model_from_gt
    cos = (np.trace(R_gt_frame @ ref[name][0].T) - 1) / 2
    rotation = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return rotation, position, 100 * position / extent
