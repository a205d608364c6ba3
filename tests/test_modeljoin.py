"""Joining the mapper's models through a shared image: a second model, in its own units and
frame, lands where the first model's geometry puts it, and a join the depths do not support is
refused."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.sfm.modeljoin import MIN_NEIGHBOURS, depth_scale, place

pytestmark = pytest.mark.unit

WIDTH, HEIGHT, FOCAL = 640, 480, 500.0


def look_at(centre: np.ndarray, target: np.ndarray) -> pycolmap.Rigid3d:
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(r), -r @ centre)


# a ground plane seen by an aerial camera (2) that both groups share; each group has its own points
CAMERAS = {
    0: look_at(np.array([12.0, 0.0, 14.0]), np.zeros(3)),
    1: look_at(np.array([8.0, -8.0, 12.0]), np.zeros(3)),
    2: look_at(np.array([0.0, 6.0, 20.0]), np.zeros(3)),
    3: look_at(np.array([-2.0, 14.0, 2.0]), np.zeros(3)),
    4: look_at(np.array([3.0, 15.0, 2.0]), np.zeros(3)),
}


def plane_points(rng: np.random.Generator, n: int) -> np.ndarray:
    xy = rng.uniform(-4.0, 4.0, size=(n, 2))
    return np.c_[xy, rng.uniform(-0.05, 0.05, size=n)]


def model(
    images: list[int], points: np.ndarray, world_from_true: pycolmap.Sim3d | None = None
) -> pycolmap.Reconstruction:
    """A reconstruction of ``images`` seeing ``points`` (each image's keypoints are its own
    projections, so the models share no keypoint), expressed in the frame ``world_from_true``."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", FOCAL, WIDTH, HEIGHT)
    rec.add_camera_with_trivial_rig(cam)
    for i in images:
        im = pycolmap.Image()
        im.name, im.image_id, im.camera_id = f"im{i}", i + 1, 1
        uv = np.array([cam.img_from_cam(CAMERAS[i] * p) for p in points])
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv])
        rec.add_image_with_trivial_frame(im, CAMERAS[i])
    for k, p in enumerate(points):
        track = pycolmap.Track()
        for i in images:
            track.add_element(i + 1, k)
        rec.add_point3D(p, track)
    if world_from_true is not None:
        rec.transform(world_from_true)
    return rec


def centre_error(rec: pycolmap.Reconstruction, name: str, i: int) -> float:
    truth = CAMERAS[i].inverse().translation
    return float(np.linalg.norm(rec.find_image_with_name(name).projection_center() - truth))


def test_a_second_model_in_other_units_is_placed_where_the_shared_image_says() -> None:
    rng = np.random.default_rng(0)
    first = model([0, 1, 2], plane_points(rng, 600))
    turn = pycolmap.Rotation3d(np.array([0.3, -0.2, 0.9]))
    elsewhere = pycolmap.Sim3d(0.37, turn, np.array([5.0, -2.0, 1.0]))
    second = model([2, 3, 4], plane_points(rng, 300), elsewhere)
    assert centre_error(second, "im3", 3) > 1.0  # its own frame: nowhere near

    joined = place(first, second)

    assert joined is not None and joined.via == "im2" and joined.images == ("im3", "im4")
    assert joined.scale == pytest.approx(1 / 0.37, rel=0.02)
    assert joined.neighbours >= MIN_NEIGHBOURS
    for name, i in (("im3", 3), ("im4", 4)):
        assert centre_error(first, name, i) < 0.05 * 15  # within 5 % of the camera's distance
    assert {im.name for im in first.images.values() if im.has_pose} == {f"im{i}" for i in range(5)}


def test_depths_that_disagree_refuse_the_join() -> None:
    """The second model's points in the shared image lie at depths that no one scale explains
    (here: scattered far off the first model's surface), so no scale is trusted."""
    rng = np.random.default_rng(1)
    first = model([0, 1, 2], plane_points(rng, 600))
    scattered = plane_points(rng, 300)
    scattered[:, 2] = rng.uniform(-15.0, 10.0, size=len(scattered))
    second = model([2, 3, 4], scattered)
    found = depth_scale(first, second, "im2")
    assert found is not None and found[2] > 0.1
    assert place(first, second) is None
    assert first.find_image_with_name("im3") is None


def test_models_seeing_different_parts_of_the_shared_image_are_not_joined() -> None:
    rng = np.random.default_rng(2)
    left, right = plane_points(rng, 400), plane_points(rng, 200)
    left[:, 0] = -np.abs(left[:, 0]) - 0.5
    right[:, 0] = np.abs(right[:, 0]) + 0.5
    first = model([0, 1, 2], left)
    second = model([2, 3, 4], right)
    assert place(first, second) is None


def test_a_model_that_adds_no_image_is_left_alone() -> None:
    rng = np.random.default_rng(3)
    first = model([0, 1, 2], plane_points(rng, 300))
    second = model([1, 2], plane_points(rng, 300))
    assert place(first, second) is None
