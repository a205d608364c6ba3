"""A new photo's 2D-3D correspondences and pose (geomatch/sfm/absolute.py) and the verdict on
them (geomatch.localize.judge), on exact synthetic geometry: no networks, no mapping."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial import cKDTree

from geomatch.localize import LocalizeOptions, judge
from geomatch.localize.absolute import Correspondences, Observations, estimate_pose, lift, merge

pytestmark = pytest.mark.unit


def _scene(n: int = 200, seed: int = 0) -> tuple[pycolmap.Camera, pycolmap.Rigid3d, np.ndarray, np.ndarray]:
    """A camera, its pose, 3D points in front of it and their projections (our convention)."""
    rng = np.random.default_rng(seed)
    camera = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 600.0, 640, 480)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.05, -0.1, 0.02, 1.0]) / 1.0063), [0.3, -0.2, 1.0])
    cam_pts = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 9, n)])
    world = (cam_pts - np.asarray(pose.translation).reshape(3)) @ pose.rotation.matrix()
    xy = np.asarray(camera.img_from_cam(cam_pts)) - 0.5
    return camera, pose, world, xy


def _angle_deg(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d) -> float:
    R = a.rotation.matrix() @ b.rotation.matrix().T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_pose_of_exact_correspondences_with_outliers() -> None:
    camera, truth, world, xy = _scene()
    rng = np.random.default_rng(1)
    xy = xy.copy()
    xy[:60] = rng.uniform(0, 640, (60, 2))  # 30 % wrong matches
    pose = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    assert pose is not None
    assert pose.inliers[60:].all() and pose.inliers[:60].sum() <= 2  # a random point may land near its own
    assert _angle_deg(pose.cam_from_world, truth) < 0.01
    centre = -truth.rotation.matrix().T @ np.asarray(truth.translation).reshape(3)
    assert np.linalg.norm(pose.centre - centre) < 1e-3
    assert pose.reprojection_error_px < 0.01


def test_unknown_focal_length_is_estimated() -> None:
    _, truth, world, xy = _scene()
    guess = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 900.0, 640, 480)
    pose = estimate_pose(xy, world, guess, 4.0, estimate_focal=True)
    assert pose is not None
    assert abs(pose.camera.params[0] - 600.0) < 1.0
    assert guess.params[0] == 900.0  # the caller's camera is left as it was
    assert _angle_deg(pose.cam_from_world, truth) < 0.05


def test_lift_keeps_matches_on_observed_points_and_merge_counts_each_point_once() -> None:
    xy = np.array([[10.0, 10.0], [50.0, 50.0]])
    obs = Observations("model.png", xy, np.array([7, 8]), cKDTree(xy))
    query = np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    model = np.array([[10.5, 10.0], [49.0, 50.0], [200.0, 200.0]])  # the third sees no point
    c = lift(query, model, obs, radius=2.0)
    assert c.point3D_ids.tolist() == [7, 8] and c.points2D.tolist() == [[1.0, 1.0], [2.0, 2.0]]
    other = Correspondences(np.array([[30.0, 30.0], [1.2, 1.0]]), np.array([7, 9]), ["b", "b"])
    merged = merge([c, other], radius=1.0)
    # point 7 once (its first query point), and query point (1, 1) once (its first 3D point)
    assert sorted(merged.point3D_ids.tolist()) == [7, 8]


def test_judge_never_localizes_on_few_or_scattered_inliers() -> None:
    camera, _, world, xy = _scene(n=60)
    opts = LocalizeOptions()
    corr = Correspondences(xy, np.arange(60), ["a"] * 30 + ["b"] * 30)
    pose = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    few = judge("p.png", pose, corr, opts, ["a", "b"])
    assert few.localized and few.confidence == "low"  # 60 inliers: localized, under "high"'s 100
    nothing = judge("p.png", None, Correspondences.empty(), opts, ["a"])
    assert not nothing.localized and nothing.confidence == "none" and nothing.reason
    camera, _, world, xy = _scene(n=20)
    small = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    verdict = judge("p.png", small, Correspondences(xy, np.arange(20), ["a"] * 20), opts, ["a"])
    assert not verdict.localized and verdict.confidence == "none"
    assert verdict.reason is not None and "20 of 20" in verdict.reason
    camera, _, world, xy = _scene(n=400)
    big = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    one = judge("p.png", big, Correspondences(xy, np.arange(400), ["a"] * 400), opts, ["a"])
    assert one.localized and one.confidence == "low"  # one model image alone: never "high"
    two = judge("p.png", big, Correspondences(xy, np.arange(400), ["a", "b"] * 200), opts, ["a", "b"])
    assert two.confidence == "high" and set(two.supporting_images) == {"a", "b"}
