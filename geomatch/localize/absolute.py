"""A new photo's pose in a model: its matches to the model's images lifted to 2D-3D, then PnP.

A match of the photo to a model image lands somewhere on that image; it becomes a 2D-3D
correspondence when it lands on one of the image's observations of a 3D point. The observations
are looked up by position, within a radius in the model image's pixels, not through the
database's keypoint indices: the model was mapped from a copy of the database whose keypoints
track refinement moved (sfm/trackrefine.py), so the positions the model holds are the ones its
points were triangulated from, and a project stored by the service has no other record of them.

The pose is pycolmap's LO-RANSAC over P3P (P4Pf when the focal length is unknown), refined on
its inliers: COLMAP's own image registration, given correspondences the matcher found.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

COLMAP_OFFSET = 0.5  # COLMAP pixel centres sit at +0.5 of ours (OpenCV's)


@dataclass(frozen=True)
class Observations:
    """One model image's observations of 3D points: positions in our convention (pixel centres at
    integers) and their 3D point ids, with a tree over the positions for the lookup."""

    name: str
    xy: np.ndarray  # (N, 2)
    point3D_ids: np.ndarray  # (N,) int64
    tree: cKDTree

    @classmethod
    def of(cls, image: pycolmap.Image) -> Observations:
        pts = [p for p in image.points2D if p.has_point3D()]
        xy = np.array([p.xy for p in pts], np.float64).reshape(-1, 2) - COLMAP_OFFSET
        ids = np.array([p.point3D_id for p in pts], np.int64)
        return cls(image.name, xy, ids, cKDTree(xy if len(xy) else np.zeros((1, 2))))


@dataclass(frozen=True)
class Correspondences:
    """2D-3D correspondences of one photo: its points (our convention), the 3D points' ids, and
    the model image each came through."""

    points2D: np.ndarray  # (N, 2)
    point3D_ids: np.ndarray  # (N,) int64
    images: list[str]

    def __len__(self) -> int:
        return len(self.point3D_ids)

    @classmethod
    def empty(cls) -> Correspondences:
        return cls(np.zeros((0, 2)), np.zeros(0, np.int64), [])


def lift(query_xy: np.ndarray, model_xy: np.ndarray, obs: Observations, radius: float) -> Correspondences:
    """The matches (query point, model image point) whose model point lies within ``radius``
    pixels of an observation of a 3D point, as 2D-3D correspondences (matches in the order given:
    best first is kept by :func:`merge`)."""
    query_xy = np.asarray(query_xy, np.float64).reshape(-1, 2)
    if not len(obs.point3D_ids) or not len(query_xy):
        return Correspondences.empty()
    dist, nn = obs.tree.query(
        np.asarray(model_xy, np.float64).reshape(-1, 2), k=1, distance_upper_bound=radius
    )
    hit = np.isfinite(dist)
    return Correspondences(query_xy[hit], obs.point3D_ids[nn[hit]], [obs.name] * int(hit.sum()))


def merge(parts: Sequence[Correspondences], radius: float) -> Correspondences:
    """All images' correspondences as one set: a 3D point is kept once (its first query point),
    and so is a query point (within ``radius``: the first 3D point), since the same point seen
    through several model images would otherwise count several times in RANSAC's consensus and
    a photo point can only see one 3D point."""
    if not parts:
        return Correspondences.empty()
    xy = np.concatenate([p.points2D for p in parts]).reshape(-1, 2)
    ids = np.concatenate([p.point3D_ids for p in parts]).astype(np.int64)
    names = [n for p in parts for n in p.images]
    keep = np.zeros(len(ids), bool)
    seen_ids: set[int] = set()
    taken = np.zeros(len(ids), bool)
    tree = cKDTree(xy) if len(xy) else None
    for k in range(len(ids)):
        if int(ids[k]) in seen_ids or taken[k]:
            continue
        keep[k] = True
        seen_ids.add(int(ids[k]))
        if tree is not None and radius > 0:
            for m in tree.query_ball_point(xy[k], radius):
                taken[m] = True
    return Correspondences(xy[keep], ids[keep], [n for n, k in zip(names, keep, strict=True) if k])


@dataclass(frozen=True)
class Pose:
    cam_from_world: pycolmap.Rigid3d
    camera: pycolmap.Camera  # with the focal length refined when it was estimated
    inliers: np.ndarray  # (N,) bool over the correspondences
    errors_px: np.ndarray  # (N,) reprojection error of every correspondence (inf behind the camera)

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def reprojection_error_px(self) -> float:
        """Mean over the inliers, in the photo's pixels."""
        e = self.errors_px[self.inliers]
        return float(e.mean()) if len(e) else float("inf")

    @property
    def centre(self) -> np.ndarray:
        """The camera centre in the model's frame."""
        return np.asarray(self.cam_from_world.inverse().translation, np.float64).reshape(3)


def reprojection_errors(
    cam_from_world: pycolmap.Rigid3d, camera: pycolmap.Camera, points2D: np.ndarray, points3D: np.ndarray
) -> np.ndarray:
    """Pixels between each observed point (our convention) and its 3D point's projection; inf for
    points behind the camera."""
    R = cam_from_world.rotation.matrix()
    t = np.asarray(cam_from_world.translation, np.float64).reshape(3)
    in_cam = points3D @ R.T + t
    front = in_cam[:, 2] > 1e-9
    errors = np.full(len(points3D), np.inf)
    if front.any():
        projected = np.asarray(camera.img_from_cam(in_cam[front]), np.float64) - COLMAP_OFFSET
        errors[front] = np.linalg.norm(projected - points2D[front], axis=1)
    return errors


def estimate_pose(
    points2D: np.ndarray,
    points3D: np.ndarray,
    camera: pycolmap.Camera,
    max_error_px: float,
    estimate_focal: bool,
    seed: int = 0,
) -> Pose | None:
    """The photo's pose from 2D-3D correspondences (points in our convention), or None when
    RANSAC finds none. ``estimate_focal``: the photo's focal length is unknown (no EXIF), so it
    is estimated (P4Pf) and refined along with the pose. A fixed seed: one photo against one
    model gives one answer."""
    if len(points2D) < 4:
        return None
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.estimate_focal_length = estimate_focal
    est.ransac.max_error = max_error_px
    est.ransac.random_seed = seed
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.refine_focal_length = estimate_focal
    camera = copy.copy(camera)  # the refinement writes the focal length into it
    found = pycolmap.estimate_and_refine_absolute_pose(
        np.asarray(points2D, np.float64) + COLMAP_OFFSET, np.asarray(points3D, np.float64), camera, est, ref
    )
    if found is None:
        return None
    cam_from_world = found["cam_from_world"]
    errors = reprojection_errors(cam_from_world, camera, np.asarray(points2D, np.float64), points3D)
    inliers = np.asarray(found["inlier_mask"], bool) & (errors <= max_error_px)
    return Pose(cam_from_world, camera, inliers, errors)
