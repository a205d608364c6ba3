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

from collections.abc import Collection
from pathlib import Path

import numpy as np
import pycolmap

from ..sfm.pairrotations import rotation_angle
from .metrics import align_cameras, scene_extent


def without_image(model: Path, name: str | Collection[str], dest: Path) -> Path:
    """``model`` written to ``dest`` without the image ``name`` (or each of several names;
    binary); returns ``dest``."""
    rec = pycolmap.Reconstruction(str(model))
    for n in [name] if isinstance(name, str) else name:
        image = rec.find_image_with_name(n)
        if image is not None and image.has_pose:
            rec.deregister_frame(image.frame_id)
    dest.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(dest))
    return dest


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
    truth = gt.find_image_with_name(name)
    if truth is None or not truth.has_pose:
        return None
    extent = scene_extent(gt)
    aligned = align_cameras(model, gt, max_rotation_deg, max_position_share * extent, leave_out=(name,))
    if aligned is None:
        return None
    found = aligned[1]
    c = found.scale * found.rotation @ np.asarray(centre, np.float64) + found.translation
    position = float(np.linalg.norm(c - np.asarray(truth.projection_center())))
    R_gt_frame = np.asarray(R) @ found.rotation.T  # cam_from_gt = cam_from_model @ model_from_gt
    rotation = rotation_angle(R_gt_frame @ truth.cam_from_world().rotation.matrix().T)
    return rotation, position, 100 * position / extent
