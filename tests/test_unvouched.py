"""Cameras a model's own pairs do not vouch for (modelagree.unvouched), and a photo localized
against them: it is not localized unless the other cameras place it on their own, since it sits
wherever they sit, right or not (geomatch/localize/answer.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.localize import LocalizeOptions, Project, judge
from geomatch.localize.absolute import Correspondences, estimate_pose
from geomatch.localize.localizer import unvouched_cameras
from geomatch.sfm.leftovers import leave_out_unvouched
from geomatch.sfm.modelagree import (
    agreement,
    misplaced,
    most_outvoted,
    outvoted,
    undecided,
    unvouched,
    weakest_tied,
)
from geomatch.sfm.viewgraph_filter import ViewGraphReport

from .colmap_synthetic import synthetic_database

pytestmark = pytest.mark.unit


# the model and pairs of tests/test_modelagree.py, and the photo of tests/test_absolute.py
def _model() -> pycolmap.Reconstruction:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, 6, 60
    return pycolmap.synthesize_dataset(opts)


def _pairs(rec: pycolmap.Reconstruction) -> tuple[dict, dict]:
    """Every pair's true rotation (x_b ~ R x_a) as its one candidate, 200 inliers each."""
    ims = sorted(rec.images.values(), key=lambda im: im.name)
    rots, inl = {}, {}
    for i, a in enumerate(ims):
        for b in ims[i + 1 :]:
            ra, rb = a.cam_from_world().rotation.matrix(), b.cam_from_world().rotation.matrix()
            rots[(a.name, b.name)] = [rb @ ra.T]
            inl[(a.name, b.name)] = 200
    return rots, inl


def _turned(rec: pycolmap.Reconstruction, image_id: int, deg: float) -> pycolmap.Reconstruction:
    out = pycolmap.Reconstruction(rec)
    im = out.images[image_id]
    pose = im.cam_from_world()
    h = np.radians(deg) / 2
    turn = pycolmap.Rotation3d(np.array([np.sin(h), 0.0, 0.0, np.cos(h)]))
    out.frames[im.frame_id].set_cam_from_world(
        im.camera_id, pycolmap.Rigid3d(turn * pose.rotation, pose.translation)
    )
    return out


def _block_turned(rec: pycolmap.Reconstruction, image_ids: list[int], deg: float) -> pycolmap.Reconstruction:
    """The images turned together about the world's origin: pairs within the block keep their
    relative rotation, pairs with the rest do not."""
    out = pycolmap.Reconstruction(rec)
    h = np.radians(deg) / 2
    world = pycolmap.Rotation3d(np.array([0.0, np.sin(h), 0.0, np.cos(h)]))
    for i in image_ids:
        im = out.images[i]
        pose = im.cam_from_world()
        out.frames[im.frame_id].set_cam_from_world(
            im.camera_id, pycolmap.Rigid3d(pose.rotation * world.inverse(), pose.translation)
        )
    return out


def _scene(n: int = 200, seed: int = 0) -> tuple[pycolmap.Camera, pycolmap.Rigid3d, np.ndarray, np.ndarray]:
    """A camera, its pose, 3D points in front of it and their projections (our convention)."""
    rng = np.random.default_rng(seed)
    camera = pycolmap.Camera.create_from_model_name(0, "SIMPLE_RADIAL", 600.0, 640, 480)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.05, -0.1, 0.02, 1.0]) / 1.0063), [0.3, -0.2, 1.0])
    cam_pts = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 9, n)])
    world = (cam_pts - np.asarray(pose.translation).reshape(3)) @ pose.rotation.matrix()
    xy = np.asarray(camera.img_from_cam(cam_pts)) - 0.5
    return camera, pose, world, xy


def test_the_true_model_vouches_for_every_camera() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    assert unvouched(rec, rots, inl) == []


def test_a_block_held_only_within_itself_is_not_vouched_for_though_it_contradicts_little() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    block = [2, 5]
    names = {rec.images[i].name for i in block}
    # the block's ties to the rest: one weak pair each, far under what misplaced_blocks takes out
    weak = {p: (10 if (p[0] in names) != (p[1] in names) else n) for p, n in inl.items()}
    bad = _block_turned(rec, block, 31.0)
    assert agreement(bad, rots, weak).clean  # the attempts' test passes such a model
    assert unvouched(bad, rots, weak) == sorted(names)
    # right, the same ties hold it
    assert unvouched(rec, rots, weak) == []


def test_an_image_held_by_one_pairs_other_rotation_is_outvoted() -> None:
    """A near-flat pair admits a homography's other decomposition; the model holds the image's
    pair with one neighbour through it and contradicts its other pairs, which the true rotation
    would all hold."""
    rec = _model()
    rots, inl = _pairs(rec)
    bad = _turned(rec, 2, 48.0)
    a, b = rec.images[2].name, rec.images[3].name
    key = (a, b) if (a, b) in rots else (b, a)
    pa, pb = (bad.find_image_with_name(n).cam_from_world().rotation.matrix() for n in key)
    rots[key] = [*rots[key], pb @ pa.T]  # the other decomposition: what the turned model holds
    inl = {p: 300 if p == key else 30 if a in p else n for p, n in inl.items()}
    # it holds 300 of its 420 inliers: more than a tenth, and the model is clean
    assert misplaced(bad, rots, inl) == [] and agreement(bad, rots, inl).clean
    assert outvoted(bad, rots, inl) == [a] and unvouched(bad, rots, inl) == [a]
    assert most_outvoted(bad, rots, inl) == a  # the other rotation holds 120 inliers more
    assert outvoted(rec, rots, inl) == [] and most_outvoted(rec, rots, inl) is None


def test_an_image_tied_by_one_pair_that_admits_two_rotations_is_not_vouched_for() -> None:
    """Its only pair with the model is near-flat: the true rotation and the homography's other
    decomposition hold it alike, so the model cannot say which the mapper took; with a second pair
    the true rotation holds both and the twin only one."""
    rec = _model()
    rots, inl = _pairs(rec)
    a, b, c = (rec.images[i].name for i in (2, 3, 4))
    bad = _turned(rec, 2, 60.0)
    only = {(x, y) for x, y in rots if a not in (x, y) or b in (x, y)}  # a's one pair: with b
    rots1 = {p: r for p, r in rots.items() if p in only}
    inl1 = {p: n for p, n in inl.items() if p in only}
    key = (a, b) if (a, b) in rots1 else (b, a)
    pa, pb = (bad.find_image_with_name(n).cam_from_world().rotation.matrix() for n in key)
    rots1[key] = [*rots1[key], pb @ pa.T]  # the twin the turned model holds
    for model in (bad, rec):  # placed on either rotation, nothing tells which is right
        assert outvoted(model, rots1, inl1) == [] and undecided(model, rots1, inl1) == [a]
        assert a in unvouched(model, rots1, inl1) and misplaced(model, rots1, inl1) == []
        assert weakest_tied(model, rots1, inl1) == a
    # one strong pair (hundreds of inliers) pins the essential matrix with points off the plane: its
    # listed twin is no second place
    strong = {**inl1, key: 800}
    assert undecided(bad, rots1, strong) == [] and undecided(rec, rots1, strong) == []
    # candidates a few degrees from the truth on every pair (one pair's estimators disagreeing a
    # little) are no second place
    near = _turned(rec, 2, 6.0).find_image_with_name(a).cam_from_world().rotation.matrix()
    rots_near = {
        p: [
            *r,
            (rec.find_image_with_name(p[1]).cam_from_world().rotation.matrix() @ near.T)
            if p[0] == a
            else (near @ rec.find_image_with_name(p[0]).cam_from_world().rotation.matrix().T),
        ]
        if a in p
        else r
        for p, r in rots.items()
    }
    assert undecided(rec, rots_near, inl) == []
    # a second pair (with c) decides: the true rotation holds both, the twin one
    key2 = (a, c) if (a, c) in rots else (c, a)
    rots2, inl2 = {**rots1, key2: rots[key2]}, {**inl1, key2: inl[key2]}
    assert undecided(rec, rots2, inl2) == []
    assert a in outvoted(bad, rots2, inl2)


def test_localize_reads_which_cameras_the_projects_pairs_vouch_for(tmp_path: Path) -> None:
    rec = synthetic_database(tmp_path / "database.db", 6, 200)
    project = Project(tmp_path / "database.db", tmp_path, tmp_path, {})
    assert unvouched_cameras(project, rec) == frozenset()
    ids = sorted(rec.images)
    bad = _block_turned(rec, [ids[1], ids[4]], 60.0)
    assert unvouched_cameras(project, bad) == {rec.images[ids[1]].name, rec.images[ids[4]].name}


def test_a_photo_placed_against_unvouched_cameras_alone_is_not_localized() -> None:
    camera, _, world, xy = _scene(n=400)
    opts = LocalizeOptions()
    pose = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    corr = Correspondences(xy, np.arange(400), ["a", "b"] * 200)
    assert judge("p.png", pose, corr, opts, ["a", "b"]).confidence == "high"
    doubtful = judge("p.png", pose, corr, opts, ["a", "b"], unvouched={"a", "b"})
    assert not doubtful.localized and doubtful.confidence == "none"
    assert doubtful.reason is not None and "vouch" in doubtful.reason and "a, b" in doubtful.reason
    # one vouched camera places it on its own: localized, but one image is never "high"
    half = judge("p.png", pose, corr, opts, ["a", "b"], unvouched={"b"})
    assert half.localized and half.confidence == "low"
    # a vouched camera with too few inliers of its own does not carry it
    few = Correspondences(xy, np.arange(400), ["a"] * 20 + ["b"] * 380)
    assert not judge("p.png", pose, few, opts, ["a", "b"], unvouched={"b"}).localized


def test_the_mapping_leaves_out_what_its_pairs_do_not_vouch_for(tmp_path: Path) -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    block = [2, 5]
    names = sorted(rec.images[i].name for i in block)
    weak = {p: (10 if (p[0] in names) != (p[1] in names) else n) for p, n in inl.items()}
    report = ViewGraphReport(kept_rotations=rots, kept_inliers=weak)
    kept, out = leave_out_unvouched(_block_turned(rec, block, 31.0), report, tmp_path)
    assert out == names
    assert sorted(im.name for im in kept.images.values() if im.has_pose) == sorted(
        im.name for im in rec.images.values() if im.name not in names
    )
    same, none = leave_out_unvouched(rec, report, tmp_path / "right")
    assert none == [] and same.num_reg_images() == rec.num_reg_images()
