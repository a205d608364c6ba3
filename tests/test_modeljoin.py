"""Joining the mapper's models through a shared image: a second model, in its own units and
frame, lands where the first model's geometry puts it, and a join the depths do not support, or
that breaks the pairs between the placed cameras and the rest, is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.sfm.joincheck import HOLD_PX, View, sampson_px
from geomatch.sfm.modeljoin import MIN_NEIGHBOURS, depth_scale, join_models, place, verify

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


def database(path: Path, pairs: list[tuple[int, int]], points: np.ndarray) -> Path:
    """A COLMAP database of the five images with, for each of ``pairs``, the true projections of
    the ``points`` both cameras see as keypoints and their matches as the pair's inliers."""
    db = pycolmap.Database.open(str(path))
    try:
        cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", FOCAL, WIDTH, HEIGHT)
        db.write_camera(cam, use_camera_id=True)
        keypoints: dict[int, list[np.ndarray]] = {i: [] for i in CAMERAS}
        matches: dict[tuple[int, int], list[tuple[int, int]]] = {pair: [] for pair in pairs}
        for a, b in pairs:
            for p in points:
                ua, ub = cam.img_from_cam(CAMERAS[a] * p), cam.img_from_cam(CAMERAS[b] * p)
                if all(0 <= u[0] < WIDTH and 0 <= u[1] < HEIGHT for u in (ua, ub)):
                    matches[(a, b)].append((len(keypoints[a]), len(keypoints[b])))
                    keypoints[a].append(ua)
                    keypoints[b].append(ub)
        for i in CAMERAS:
            db.write_image(pycolmap.Image(name=f"im{i}", camera_id=1, image_id=i + 1), use_image_id=True)
            db.write_keypoints(i + 1, np.asarray(keypoints[i], np.float32).reshape(-1, 2))
        for (a, b), m in matches.items():
            g = pycolmap.TwoViewGeometry()
            g.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            g.inlier_matches = np.asarray(m, np.uint32).reshape(-1, 2)
            db.write_two_view_geometry(a + 1, b + 1, g)
    finally:
        db.close()
    return path


def centre_error(rec: pycolmap.Reconstruction, name: str, i: int) -> float:
    truth = CAMERAS[i].inverse().translation
    return float(np.linalg.norm(rec.find_image_with_name(name).projection_center() - truth))


def test_a_second_model_in_other_units_is_placed_where_the_shared_image_says(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    first = model([0, 1, 2], plane_points(rng, 600))
    turn = pycolmap.Rotation3d(np.array([0.3, -0.2, 0.9]))
    elsewhere = pycolmap.Sim3d(0.37, turn, np.array([5.0, -2.0, 1.0]))
    second = model([2, 3, 4], plane_points(rng, 300), elsewhere)
    assert centre_error(second, "im3", 3) > 1.0  # its own frame: nowhere near
    pairs = database(tmp_path / "database.db", [(0, 3), (1, 4)], plane_points(rng, 300))

    joined = place(first, second)

    assert joined is not None and joined.via == "im2" and joined.images == ("im3", "im4")
    checked = verify(first, joined, {"im0", "im1", "im2"}, pairs)
    assert not checked.refused and checked.pairs_held > 0 and checked.pairs_contradicted == 0
    assert joined.scale == pytest.approx(1 / 0.37, rel=0.02)
    assert joined.neighbours >= MIN_NEIGHBOURS
    for name, i in (("im3", 3), ("im4", 4)):
        assert centre_error(first, name, i) < 0.05 * 15  # within 5 % of the camera's distance
    assert {im.name for im in first.images.values() if im.has_pose} == {f"im{i}" for i in range(5)}


def off_the_surface(
    seed: int, low: float, high: float
) -> tuple[pycolmap.Reconstruction, pycolmap.Reconstruction]:
    """A first model on the ground plane and a second sharing im2 whose points lie at heights drawn
    from [low, high]: depths in im2 that one scale explains only as well as those heights allow."""
    rng = np.random.default_rng(seed)
    first = model([0, 1, 2], plane_points(rng, 600))
    points = plane_points(rng, 300)
    points[:, 2] = rng.uniform(low, high, size=len(points))
    return first, model([2, 3, 4], points)


def test_depths_that_disagree_refuse_the_join() -> None:
    """The second model's points in the shared image lie at depths that no one scale explains
    (here: scattered far off the first model's surface), so no scale is trusted."""
    first, second = off_the_surface(seed=1, low=-15.0, high=10.0)
    found = depth_scale(first, second, "im2")
    assert found is not None and found[2] > 0.1
    assert place(first, second) is None
    assert first.find_image_with_name("im3") is None


def test_a_scale_from_loosely_agreeing_depths_is_not_trusted() -> None:
    """Depths a few metres off the first model's surface (log ratios spread ~0.07) still give a
    median near the truth here, but a spread like it came with a join that put an aerial camera
    14 % of the scene off: with no pair to check such a join, it is not made."""
    first, second = off_the_surface(seed=11, low=-3.0, high=3.0)
    found = depth_scale(first, second, "im2")
    assert found is not None and found[1] >= MIN_NEIGHBOURS and 0.05 < found[2] < 0.1
    assert place(first, second) is None


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


def test_a_block_whose_depths_agree_but_whose_cameras_sit_elsewhere_is_refused(tmp_path: Path) -> None:
    """The mapper's second model holds the shared image and the surface around it right but its
    other cameras too far out (one wrong pose chain, a scale the depths near the shared image do
    not see): the rotations are right, the depths agree, and only the pairs between those cameras
    and the first model's others say the join is wrong. Without such pairs the join stands."""
    rng = np.random.default_rng(4)
    first = model([0, 1, 2], plane_points(rng, 600))
    second = model([2, 3, 4], plane_points(rng, 300))
    centre2 = CAMERAS[2].inverse().translation
    for name in ("im3", "im4"):  # each centre twice as far from the shared camera, rotation kept
        image = second.find_image_with_name(name)
        pose = image.cam_from_world()
        centre = pose.inverse().translation
        far = centre2 + 2.0 * (centre - centre2)
        r = pose.rotation.matrix()
        image.frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, -r @ far)
    ground = plane_points(rng, 300)
    joined = place(first, second)
    assert joined is not None
    base = {"im0", "im1", "im2"}

    refused = verify(first, joined, base, database(tmp_path / "a.db", [(0, 3), (1, 4)], ground))
    unchecked = verify(first, joined, base, database(tmp_path / "b.db", [], ground))

    assert refused.refused and refused.pairs_contradicted > 0 and refused.pairs_held == 0
    assert not unchecked.refused  # nothing to say against it: the depths decide
    assert centre_error(first, "im3", 3) > 1.0  # what the guard keeps out of a written model


def test_the_pairs_meet_their_epipolar_lines_at_the_true_poses_only() -> None:
    """The guard's measure: a pixel's noise at the true poses stays within the threshold, a
    camera moved along the baseline's side does not."""
    rng = np.random.default_rng(5)
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", FOCAL, WIDTH, HEIGHT)
    pts = plane_points(rng, 200)
    kp0 = np.array([cam.img_from_cam(CAMERAS[0] * p) for p in pts]) + rng.normal(0, 0.5, (200, 2))
    kp3 = np.array([cam.img_from_cam(CAMERAS[3] * p) for p in pts]) + rng.normal(0, 0.5, (200, 2))
    m = np.stack([np.arange(200), np.arange(200)], 1)
    a = View(cam, CAMERAS[0])
    assert sampson_px(a, View(cam, CAMERAS[3]), kp0, kp3, m) < HOLD_PX
    moved = look_at(np.array([-2.0, 14.0, 8.0]), np.zeros(3))  # six metres up, still at the scene
    assert sampson_px(a, View(cam, moved), kp0, kp3, m) > HOLD_PX


def _far_block(second: pycolmap.Reconstruction) -> None:
    """The second model's cameras other than the shared one twice as far from it, rotations kept."""
    centre2 = CAMERAS[2].inverse().translation
    for name in ("im3", "im4"):
        image = second.find_image_with_name(name)
        pose = image.cam_from_world()
        far = centre2 + 2.0 * (pose.inverse().translation - centre2)
        image.frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, -pose.rotation.matrix() @ far)


@pytest.mark.parametrize("wrong", [False, True])
def test_joined_models_keep_a_join_its_cross_pairs_hold_and_undo_one_they_break(
    tmp_path: Path, wrong: bool
) -> None:
    """Through the whole join: placed, triangulated from the database, adjusted, then verified.
    A wrong block comes back as the separate model it was, the first model untouched, and the
    refused join named for the summary."""
    rng = np.random.default_rng(6)
    first = model([0, 1, 2], plane_points(rng, 400))
    second = model([2, 3, 4], plane_points(rng, 300))
    if wrong:
        _far_block(second)
    pairs = [(0, 1), (0, 2), (1, 2), (2, 3), (2, 4), (3, 4), (0, 3), (1, 4)]
    db = database(tmp_path / "database.db", pairs, plane_points(rng, 400))
    (tmp_path / "images").mkdir()
    options = pycolmap.IncrementalPipelineOptions()

    models, joins = join_models([first, second], db, tmp_path / "images", tmp_path / "work", options)

    assert len(joins) == 1 and joins[0].via == "im2" and joins[0].refused is wrong
    if wrong:
        assert models == [first, second] and joins[0].pairs_contradicted > 0
    else:
        assert len(models) == 1 and models[0].num_reg_images() == 5
        assert joins[0].pairs_held > 0 and joins[0].pairs_contradicted == 0
        for name, i in (("im3", 3), ("im4", 4)):
            assert centre_error(models[0], name, i) < 0.05 * 15


@pytest.mark.parametrize("tiled", [False, True])
def test_a_join_nothing_but_its_shared_image_holds_stands_only_through_a_tiled_image(
    tmp_path: Path, tiled: bool
) -> None:
    """No pair between the placed cameras and the first model's others: the join rests on the
    shared image's pose in both models alone. That is what a tiled aerial image's crop keypoints
    leave (the ground photos reach the rest only through it), so through such an image it
    stands; through any other image it is refused and its block left apart, named."""
    rng = np.random.default_rng(7)
    first = model([0, 1, 2], plane_points(rng, 400))
    second = model([2, 3, 4], plane_points(rng, 300))
    pairs = [(0, 1), (0, 2), (1, 2), (2, 3), (2, 4), (3, 4)]
    db = database(tmp_path / "database.db", pairs, plane_points(rng, 400))
    (tmp_path / "images").mkdir()
    bridges = {"im2"} if tiled else {"im0"}

    models, joins = join_models(
        [first, second],
        db,
        tmp_path / "images",
        tmp_path / "work",
        pycolmap.IncrementalPipelineOptions(),
        bridges,
    )

    assert len(joins) == 1 and joins[0].pairs_held == joins[0].pairs_contradicted == 0
    assert joins[0].refused is not tiled
    assert len(models) == (1 if tiled else 2)
    assert ("reason" in joins[0].as_dict()) is not tiled
