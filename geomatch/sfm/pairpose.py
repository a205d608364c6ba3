"""Place an image the mapper left out from its pairs' relative poses, where no 3D point reaches it.

Why: COLMAP registers an image from 3D points it sees (PnP), or structure-less from 2D-2D
correspondences with registered images, but considers an image at all only once it sees as many
triangulated points as its PnP minimum. In a tiled project an aerial image's matches often end on
keypoints no registered image shares with a third view: its whole-image keypoints with the other
aerial image, its crop keypoints with each street photo (modeljoin.py says why the two never
meet), and a street photo seen only by that aerial image and one neighbour follows it out. The
pairs themselves still say where the image is: each verified pair with a registered image gives
the relative rotation and the direction of the baseline, so two or more registered partners that
agree on the rotation fix the image's orientation and, where their baselines cross, its centre.
Once placed, its matches are triangulated with every pose held, and COLMAP's mapper carries on
from the model (leftovers.register_leftovers), adjusting the placed image with the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from .pairrotations import rotation_angle

# a partner pair is used from this many inliers on: COLMAP's own verification floor
MIN_PAIR_INLIERS = 15
# partners' rotations for the image agree within this angle (a pair's two-view rotation is good to
# about a degree, view-graph loops hold at 5)
AGREE_DEG = 5.0
# the centre rests on baselines that cross at least this steeply: nearly parallel rays fix the
# centre only along their common direction
MIN_RAY_ANGLE_DEG = 5.0
# ...and each baseline passes the centre within this angle: a partner whose direction misses the
# others' crossing point is a wrong pair or a degenerate pose
MAX_RAY_MISS_DEG = 5.0


@dataclass(frozen=True)
class Placement:
    """How an image was placed, for the run's summary."""

    image: str
    partners: tuple[str, ...]  # the registered images whose pairs placed it
    inliers: int  # their inliers, together

    def as_dict(self) -> dict[str, object]:
        return {"image": self.image, "partners": list(self.partners), "inliers": self.inliers}


@dataclass(frozen=True)
class _Partner:
    name: str
    inliers: int
    rotation: np.ndarray  # the image's cam_from_world rotation this pair implies
    centre: np.ndarray  # the partner's centre
    direction: np.ndarray  # unit world direction from the partner's centre to the image's


def _partners(
    rec: pycolmap.Reconstruction, db: pycolmap.Database, image_id: int, cameras: dict[int, pycolmap.Camera]
) -> list[_Partner]:
    registered = {i: im for i, im in rec.images.items() if im.has_pose}
    kp = db.read_keypoints(image_id)[:, :2].astype(np.float64)
    out = []
    pair_ids, geometries = db.read_two_view_geometries()
    for pid, g in zip(pair_ids, geometries, strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        if image_id not in (a, b) or len(g.inlier_matches) < MIN_PAIR_INLIERS:
            continue
        other = b if a == image_id else a
        if other not in registered:
            continue
        # the pose is estimated in the pair's own order (its F, E and H are written that way)
        # and turned round where the image is the pair's second
        ka, kb = (kp, db.read_keypoints(other)[:, :2].astype(np.float64))[:: 1 if a == image_id else -1]
        geometry = g  # the copy read here: the estimate sets its pose, nothing is written
        cam_a, cam_b = cameras[db.read_image(a).camera_id], cameras[db.read_image(b).camera_id]
        if not pycolmap.estimate_two_view_geometry_pose(cam_a, ka, cam_b, kb, geometry):
            continue
        if geometry.cam2_from_cam1 is None:
            continue
        rel = geometry.cam2_from_cam1 if a == image_id else geometry.cam2_from_cam1.inverse()
        m = g.inlier_matches
        pose = registered[other].cam_from_world()
        Rp = pose.rotation.matrix()
        t = np.asarray(rel.translation, np.float64)
        if np.linalg.norm(t) < 1e-9:
            continue
        out.append(
            _Partner(
                name=registered[other].name,
                inliers=len(m),
                rotation=rel.rotation.matrix().T @ Rp,
                centre=np.asarray(registered[other].projection_center(), np.float64),
                direction=Rp.T @ (t / np.linalg.norm(t)),
            )
        )
    return out


def _centre(partners: list[_Partner]) -> np.ndarray | None:
    """The point nearest every partner's baseline ray, weighted by inliers; None where the rays
    do not cross steeply enough or one misses it or points away from it."""
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    for p in partners:
        P = np.eye(3) - np.outer(p.direction, p.direction)
        A += p.inliers * P
        rhs += p.inliers * P @ p.centre
    steepest = max(
        np.degrees(np.arccos(np.clip(abs(float(p.direction @ q.direction)), 0.0, 1.0)))
        for i, p in enumerate(partners)
        for q in partners[i + 1 :]
    )
    if steepest < MIN_RAY_ANGLE_DEG:
        return None
    c = np.linalg.solve(A, rhs)
    for p in partners:
        v = c - p.centre
        n = float(np.linalg.norm(v))
        miss = np.degrees(np.arccos(np.clip(float(v @ p.direction) / max(n, 1e-12), -1.0, 1.0)))
        if n < 1e-9 or miss > MAX_RAY_MISS_DEG:
            return None
    return c


def place(rec: pycolmap.Reconstruction, database: Path, name: str) -> Placement | None:
    """Add the unregistered image ``name`` to ``rec`` (in place) posed from its pairs with the
    model's registered images; None, and ``rec`` untouched, where they do not agree on one pose."""
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        image_id = ids.get(name)
        if image_id is None or (image_id in rec.images and rec.images[image_id].has_pose):
            return None
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        partners = _partners(rec, db, image_id, cameras)
        if len(partners) < 2:
            return None
        # the rotation most of the inliers agree on, then the partners that agree with it
        best = max(partners, key=lambda p: sum(q.inliers for q in _agreeing(p, partners)))
        agreeing = _agreeing(best, partners)
        if len(agreeing) < 2:
            return None
        centre = _centre(agreeing)
        if centre is None:
            return None
        R = _mean_rotation([q.rotation for q in agreeing], [q.inliers for q in agreeing])
        image = db.read_image(image_id)
        keypoints = db.read_keypoints(image_id)[:, :2].astype(np.float64)
    finally:
        db.close()
    cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre)
    if image.camera_id not in rec.cameras:
        return None  # a camera no registered image shares: nothing in the model to hold it to
    if image_id in rec.images:  # in the model, its pose taken away (a misplaced image)
        frame_id = rec.images[image_id].frame_id
        rec.frames[frame_id].set_cam_from_world(image.camera_id, cam_from_world)
        rec.register_frame(frame_id)
        return Placement(name, tuple(q.name for q in agreeing), sum(q.inliers for q in agreeing))
    new = pycolmap.Image(name=name, keypoints=keypoints, camera_id=image.camera_id, image_id=image_id)
    rec.add_image_with_trivial_frame(new, cam_from_world)
    return Placement(name, tuple(q.name for q in agreeing), sum(q.inliers for q in agreeing))


def _agreeing(p: _Partner, partners: list[_Partner]) -> list[_Partner]:
    return [q for q in partners if rotation_angle(p.rotation.T @ q.rotation) <= AGREE_DEG]


def _mean_rotation(rotations: list[np.ndarray], weights: list[int]) -> np.ndarray:
    """The weighted chordal mean: the rotation nearest the weighted sum of the matrices."""
    M = sum(w * R for R, w in zip(rotations, weights, strict=True))
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt
