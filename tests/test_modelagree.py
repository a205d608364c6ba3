"""A model held to its pairs' rotations: the true model holds every pair, an image turned away
from its pairs is found and the model is no longer clean, and a block of images turned as one is
found though each of its images holds its pairs within the block; what decides which mapping
attempt a tiled project keeps, and what it takes out to join again (mapping.py)."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.sfm.modelagree import agreement, misplaced, misplaced_blocks
from geomatch.sfm.viewgraph_filter import filter_database

from .colmap_synthetic import synthetic_database

pytestmark = pytest.mark.unit


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


def test_the_true_model_holds_every_pair() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    a = agreement(rec, rots, inl)
    assert a.contradicted == 0 and a.held == 200 * 15 and a.clean
    assert misplaced(rec, rots, inl) == []
    assert misplaced_blocks(rec, rots, inl) == []


def test_a_block_turned_as_one_is_found_where_each_image_holds_a_pair() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    bad = _block_turned(rec, [2, 5], 130.0)
    a = agreement(bad, rots, inl)
    # the block's own pair holds; its eight pairs with the other four images do not
    assert a.contradicted == 200 * 8 and a.held == 200 * 7
    # each block image holds one pair of its five, more than the single-image rule allows
    assert misplaced(bad, rots, inl) == []
    assert misplaced_blocks(bad, rots, inl) == [{rec.images[2].name, rec.images[5].name}]


def test_a_block_with_too_few_inliers_against_the_rest_is_left_alone() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    weak = {pair: 10 for pair in inl}
    assert misplaced_blocks(_block_turned(rec, [2, 5], 130.0), rots, weak) == []


def test_an_image_turned_from_its_pairs_is_found() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    bad = _turned(rec, 2, 30.0)
    a = agreement(bad, rots, inl)
    # its five pairs turn against it; the other ten still hold
    assert a.contradicted == 200 * 5 and a.held == 200 * 10 and not a.clean
    assert a.score < agreement(rec, rots, inl).score
    assert misplaced(bad, rots, inl) == [rec.images[2].name]


def test_a_turn_within_a_pairs_precision_is_held() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    assert agreement(_turned(rec, 2, 2.0), rots, inl).contradicted == 0


def test_pairs_with_an_image_the_model_lacks_do_not_count() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    fewer = pycolmap.Reconstruction(rec)
    fewer.deregister_frame(fewer.images[2].frame_id)
    assert agreement(fewer, rots, inl).held == 200 * 10


def test_the_view_graph_hands_on_the_pairs_it_kept(tmp_path) -> None:
    path = tmp_path / "database.db"
    rec = synthetic_database(path, 5, 200)
    report = filter_database(str(path))
    assert not report.dropped and not report.tree_dropped
    assert len(report.kept_rotations) == 10 and set(report.kept_inliers.values()) == {200}
    # the true model holds each kept pair: the names and the rotations' direction are the mapper's
    a = agreement(rec, report.kept_rotations, report.kept_inliers)
    assert a.contradicted == 0 and a.held == 200 * 10
