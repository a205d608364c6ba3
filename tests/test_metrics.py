from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.metrics import evaluate, relative_pose_errors
from geomatch.synth import Scene, write_gt


@pytest.fixture(scope="module")
def gt(tmp_path_factory) -> pycolmap.Reconstruction:
    cams = Scene(5).cameras(3, 4, 320, 240)
    d = tmp_path_factory.mktemp("gt")
    write_gt(cams, d)
    return pycolmap.Reconstruction(str(d))


def test_a_similar_copy_scores_perfectly(gt) -> None:
    est = pycolmap.Reconstruction(gt)
    R = pycolmap.Rotation3d(np.array([0.1, -0.3, 0.2, 0.9]) / np.linalg.norm([0.1, -0.3, 0.2, 0.9]))
    est.transform(pycolmap.Sim3d(2.5, R, np.array([3.0, -1.0, 7.0])))  # gauge freedom of SfM
    m = evaluate(est, gt)
    assert m["auc@3"] == pytest.approx(100.0, abs=0.01)  # arccos near 1: ~1e-4 deg of noise
    assert m["aligned"] and m["median_position_error"] < 1e-6 and m["median_rotation_error_deg"] < 1e-4


def test_unregistered_images_count_as_failures(gt) -> None:
    est = pycolmap.Reconstruction(gt)
    name = next(im.name for im in est.images.values())
    est.deregister_frame(next(im.frame_id for im in est.images.values() if im.name == name))
    errs = relative_pose_errors(est, gt)
    n = gt.num_images()
    assert len(errs) == n * (n - 1) // 2 and np.isinf(errs).sum() == n - 1
    assert evaluate(est, gt)["auc@10"] == pytest.approx(100.0 * (1 - (n - 1) / len(errs)), abs=0.01)


def test_a_rotated_camera_is_seen(gt) -> None:
    est = pycolmap.Reconstruction(gt)
    im = next(iter(est.images.values()))
    T = im.cam_from_world()
    bump = pycolmap.Rotation3d(
        np.array([np.sin(np.deg2rad(2.0)), 0, 0, np.cos(np.deg2rad(2.0))])
    )  # 4 deg, xyzw
    est.frame(im.frame_id).rig_from_world = pycolmap.Rigid3d(bump * T.rotation, T.translation)
    errs = relative_pose_errors(est, gt)
    assert np.isclose(np.max(errs), 4.0, atol=1e-3) or np.max(errs) > 4.0
    assert (errs > 3.0).sum() == gt.num_images() - 1
