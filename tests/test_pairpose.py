"""An image the mapper left out, placed from its pairs' relative poses: on COLMAP's synthetic
dataset (exact matches, known poses) the pose comes back, a misplaced partner is outvoted rather
than followed, one partner alone places nothing, and the mapper's continuation keeps the image;
a block the first model turns is joined again from a second model that holds it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.sfm import pairpose
from geomatch.sfm.leftovers import Continuation, place_leftovers, rejoin_blocks, replace_misplaced
from geomatch.sfm.mapping import incremental_options
from geomatch.sfm.pairrotations import rotation_angle
from geomatch.sfm.viewgraph_filter import ViewGraphReport

from .colmap_synthetic import synthetic_database

pytestmark = pytest.mark.unit


def _dataset(tmp_path: Path, frames: int = 6) -> tuple[pycolmap.Reconstruction, Path]:
    path = tmp_path / "database.db"
    return synthetic_database(path, frames, 300), path


def _without(rec: pycolmap.Reconstruction, *image_ids: int) -> pycolmap.Reconstruction:
    out = pycolmap.Reconstruction(rec)
    for i in image_ids:
        out.deregister_frame(out.images[i].frame_id)
    return out


def _errors(a: pycolmap.Image, b: pycolmap.Image) -> tuple[float, float]:
    ra, rb = a.cam_from_world().rotation.matrix(), b.cam_from_world().rotation.matrix()
    return rotation_angle(ra.T @ rb), float(np.linalg.norm(a.projection_center() - b.projection_center()))


def _report(rec: pycolmap.Reconstruction) -> ViewGraphReport:
    """Every pair kept with its true rotation as its one candidate."""
    ims = sorted(rec.images.values(), key=lambda im: im.name)
    report = ViewGraphReport()
    for i, a in enumerate(ims):
        for b in ims[i + 1 :]:
            ra, rb = a.cam_from_world().rotation.matrix(), b.cam_from_world().rotation.matrix()
            report.kept_rotations[(a.name, b.name)] = [rb @ ra.T]
            report.kept_inliers[(a.name, b.name)] = 300
    return report


def test_an_image_taken_out_is_placed_back_at_its_pose(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path)
    trial = _without(rec, 3)
    placed = pairpose.place(trial, db, rec.images[3].name)
    assert placed is not None and len(placed.partners) == 5
    deg, dist = _errors(trial.images[3], rec.images[3])
    extent = np.ptp([im.projection_center() for im in rec.images.values()], axis=0).max()
    assert deg < 0.1 and dist < 1e-3 * extent


def test_a_misplaced_partner_is_outvoted(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path)
    trial = _without(rec, 3)
    # partner 1 turned 40 deg in the model: its pair implies a rotation the others contradict
    im = trial.images[1]
    pose = im.cam_from_world()
    turn = pycolmap.Rotation3d(np.array([0.0, np.sin(np.radians(20)), 0.0, np.cos(np.radians(20))]))
    trial.frames[im.frame_id].set_cam_from_world(
        im.camera_id, pycolmap.Rigid3d(turn * pose.rotation, pose.translation)
    )
    placed = pairpose.place(trial, db, rec.images[3].name)
    assert placed is not None and rec.images[1].name not in placed.partners
    deg, _ = _errors(trial.images[3], rec.images[3])
    assert deg < 0.1


def test_one_partner_alone_places_nothing(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path, frames=3)
    trial = _without(rec, 2, 3)
    # one registered partner gives a direction to the image but no distance along it
    assert pairpose.place(trial, db, rec.images[3].name) is None
    assert not trial.images[3].has_pose


def test_the_mapper_carries_on_from_a_placed_image(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path)
    trial = _without(rec, 3, 5)
    images = tmp_path / "images"
    images.mkdir()
    options = incremental_options(6, 3, 15, 0, tiled=True)
    out, placements = place_leftovers(trial, Continuation(db, images, options, 6), tmp_path / "work")
    assert out.num_reg_images() == 6
    assert {p.image for p in placements} <= {rec.images[3].name, rec.images[5].name}
    for i in (3, 5):
        deg, _ = _errors(
            next(im for im in out.images.values() if im.name == rec.images[i].name), rec.images[i]
        )
        # the model's frame is the dataset's: the placed images were adjusted with the rest
        assert deg < 0.5


def test_an_image_the_model_turns_against_its_pairs_is_placed_again(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path)
    report = _report(rec)
    bad = pycolmap.Reconstruction(rec)
    im = bad.images[4]
    pose = im.cam_from_world()
    turn = pycolmap.Rotation3d(np.array([np.sin(np.radians(25)), 0.0, 0.0, np.cos(np.radians(25))]))
    bad.frames[im.frame_id].set_cam_from_world(
        im.camera_id, pycolmap.Rigid3d(turn * pose.rotation, pose.translation)
    )
    images = tmp_path / "images"
    images.mkdir()
    options = incremental_options(6, 3, 15, 0, tiled=True)
    fixed, placed = replace_misplaced(bad, report, Continuation(db, images, options, 6), tmp_path / "work")
    assert [p.image for p in placed] == [rec.images[4].name]
    deg, _ = _errors(fixed.images[4], rec.images[4])
    assert deg < 0.5
    # a model that holds its pairs is returned as it is
    same, none = replace_misplaced(rec, report, Continuation(db, images, options, 6), tmp_path / "work2")
    assert same is rec and none == []


def test_a_block_the_first_model_turns_is_joined_again_from_the_second(tmp_path: Path) -> None:
    rec, db = _dataset(tmp_path)
    report = _report(rec)
    # the first model holds every image but turns 4 and 5 together, 130 deg about its origin
    bad = pycolmap.Reconstruction(rec)
    h = np.radians(130) / 2
    world = pycolmap.Rotation3d(np.array([0.0, np.sin(h), 0.0, np.cos(h)]))
    for i in (4, 5):
        im = bad.images[i]
        pose = im.cam_from_world()
        bad.frames[im.frame_id].set_cam_from_world(
            im.camera_id, pycolmap.Rigid3d(pose.rotation * world.inverse(), pose.translation)
        )
    # the mapper's second model holds them right, with 1 and 2, in its own units and frame
    second = _without(rec, 3, 6)
    second.transform(
        pycolmap.Sim3d(0.4, pycolmap.Rotation3d(np.array([0.3, -0.2, 0.9])), np.array([5.0, -2.0, 1.0]))
    )
    images = tmp_path / "images"
    images.mkdir()
    more = Continuation(db, images, incremental_options(6, 3, 15, 0, tiled=True), 6)
    fixed, joins = rejoin_blocks([bad, second], report, more, tmp_path / "work")
    assert [set(j.images) for j in joins] == [{rec.images[4].name, rec.images[5].name}]
    assert fixed[0].num_reg_images() == 6
    for i in (4, 5):
        deg, _ = _errors(fixed[0].find_image_with_name(rec.images[i].name), rec.images[i])
        assert deg < 0.5
    # no second model that holds the block: nothing is taken out
    alone, none = rejoin_blocks([bad, _without(rec, 4, 5)], report, more, tmp_path / "work2")
    assert alone[0] is bad and none == []
