"""Whether a join holds the pairs between the cameras it places and the rest of the first model.

Why: a join rests on one image's pose in both models and on depth ratios near it (modeljoin.py).
Neither sees a block placed at a wrong scale: its rotations stay within a few degrees, so the
rotation rules (modelagree.py) hold it, while its cameras sit a quarter of the scene from where
they belong. The matches of a verified pair between a placed camera and another camera of the
first model do see it: at the joined poses they meet their epipolar lines within a pixel or two
when the join is right, and tens to hundreds of pixels off when it is not.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import torch

from ..epipolar.geometry import sampson_distance, skew
from ..imageio import working_scale

# a pair is heard from this many inliers on: COLMAP's own verification floor
MIN_PAIR_INLIERS = 15
# a pair holds the joined poses while the median Sampson distance of its inliers stays within this
# many working pixels: the verification's own RANSAC threshold is a few pixels, and a right join
# adds the mapper's pose noise on top
HOLD_PX = 4.0


@dataclass(frozen=True)
class View:
    """A camera as a model holds it."""

    camera: pycolmap.Camera
    cam_from_world: pycolmap.Rigid3d


@dataclass(frozen=True)
class CrossPairs:
    """The verified pairs between the placed cameras and the first model's others, by inliers."""

    held: int
    contradicted: int

    @property
    def refuse(self) -> bool:
        """The pairs that contradict the join outweigh those that hold it. No pair either way
        leaves the join to its depth ratios, as a join through a tiled image needs (the ground
        photos reach the rest only through it)."""
        return self.contradicted > self.held


def sampson_px(a: View, b: View, kp_a: np.ndarray, kp_b: np.ndarray, matches: np.ndarray) -> float:
    """Median Sampson distance, in working pixels, of ``matches`` (rows of keypoint indices into
    ``kp_a``, ``kp_b``, COLMAP's pixel convention) under the two poses' essential matrix."""
    ra, ta = a.cam_from_world.rotation.matrix(), np.asarray(a.cam_from_world.translation)
    rb, tb = b.cam_from_world.rotation.matrix(), np.asarray(b.cam_from_world.translation)
    rel = rb @ ra.T
    t = tb - rel @ ta
    norm = float(np.linalg.norm(t))
    if norm == 0.0:
        return float("inf")  # one centre for two cameras: no epipolar geometry holds a pair
    essential = torch.from_numpy(skew(t / norm) @ rel)
    xa = np.asarray(a.camera.cam_from_img(kp_a[matches[:, 0]].astype(np.float64)), np.float64)
    xb = np.asarray(b.camera.cam_from_img(kp_b[matches[:, 1]].astype(np.float64)), np.float64)
    dist = np.sqrt(sampson_distance(essential, torch.from_numpy(xa), torch.from_numpy(xb)).numpy())
    focal = 0.5 * (a.camera.mean_focal_length() + b.camera.mean_focal_length())
    side = max(a.camera.width, a.camera.height, b.camera.width, b.camera.height)
    return float(np.median(dist)) * focal / working_scale(side)


def cross_pairs(database: Path, placed: Mapping[str, View], others: Mapping[str, View]) -> CrossPairs:
    """How the verified pairs of ``database`` between ``placed`` and ``others`` (by image name)
    take the poses given: the inliers of those that hold them and of those that do not. The mapper's
    copy of the database is meant, where the pairs the view graph dropped have no inliers left."""
    held = contradicted = 0
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        keypoints: dict[int, np.ndarray] = {}

        def kp(image_id: int) -> np.ndarray:
            if image_id not in keypoints:
                keypoints[image_id] = db.read_keypoints(image_id)[:, :2]
            return keypoints[image_id]

        for p, pv in sorted(placed.items()):
            for o, ov in sorted(others.items()):
                if p not in ids or o not in ids or not db.exists_two_view_geometry(ids[p], ids[o]):
                    continue
                matches = np.asarray(db.read_two_view_geometry(ids[p], ids[o]).inlier_matches)
                if len(matches) < MIN_PAIR_INLIERS:
                    continue
                if sampson_px(pv, ov, kp(ids[p]), kp(ids[o]), matches) <= HOLD_PX:
                    held += len(matches)
                else:
                    contradicted += len(matches)
    finally:
        db.close()
    return CrossPairs(held, contradicted)
