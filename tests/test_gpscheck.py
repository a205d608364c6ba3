"""Cameras held to their GPS fixes: on COLMAP's synthetic dataset with fixes of known noise, the
cameras within the noise are left alone, a camera the model puts far from its fix is found, placed
again from the model's points by the mapper's continuation, and a camera whose fix disagrees with
every pose the images allow is taken out of the model and named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.geo.georef import camera_centres
from geomatch.geo.gpscheck import check, off_track
from geomatch.sfm.leftovers import Continuation, hold_to_fixes
from geomatch.sfm.mapping import incremental_options

from .colmap_synthetic import synthetic_database

pytestmark = pytest.mark.unit

FRAMES = 8
NOISE = 0.02  # the fixes' noise, in the dataset's units (its cameras lie a few units apart)


def _fixes(rec: pycolmap.Reconstruction, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: c + rng.normal(0.0, NOISE, 3) for n, c in sorted(camera_centres(rec).items())}


def _moved(rec: pycolmap.Reconstruction, image_id: int, shift: np.ndarray) -> pycolmap.Reconstruction:
    """The camera's centre moved by ``shift`` with its rotation kept: a wrong registration."""
    out = pycolmap.Reconstruction(rec)
    im = out.images[image_id]
    pose = im.cam_from_world()
    R = pose.rotation.matrix()
    t = np.asarray(pose.translation) - R @ shift
    out.frames[im.frame_id].set_cam_from_world(im.camera_id, pycolmap.Rigid3d(pose.rotation, t))
    return out


def _continuation(tmp_path: Path, db: Path) -> Continuation:
    images = tmp_path / "images"
    images.mkdir(exist_ok=True)
    return Continuation(db, images, incremental_options(FRAMES, 3, 15, 0), FRAMES)


def test_cameras_within_the_fixes_noise_are_left_alone(tmp_path: Path) -> None:
    rec = synthetic_database(tmp_path / "database.db", FRAMES, 300)
    found = check(rec, _fixes(rec), min_limit_m=0.0)
    assert found is not None and found.offenders == ()
    # the noise is estimated from the cameras themselves, within a factor of two of the truth
    assert 0.5 * NOISE < found.sigma_m < 2 * NOISE


def test_a_camera_far_from_its_fix_is_found_by_name() -> None:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, FRAMES, 100
    rec = pycolmap.synthesize_dataset(opts)
    fixes = _fixes(rec)
    bad = _moved(rec, 4, np.array([0.0, 40 * NOISE, 0.0]))
    found = check(bad, fixes, min_limit_m=0.0)
    assert found is not None and [o.name for o in found.offenders] == [rec.images[4].name]
    # the metres floor keeps a model whose fixes are centimetres from judging its own drift
    assert check(bad, fixes, min_limit_m=10.0).offenders == ()  # type: ignore[union-attr]


def test_a_misplaced_camera_is_placed_again_from_the_model(tmp_path: Path) -> None:
    db = tmp_path / "database.db"
    rec = synthetic_database(db, FRAMES, 300)
    fixes = _fixes(rec)
    bad = _moved(rec, 4, np.array([0.5, 0.0, 0.3]))
    found = check(bad, fixes, min_limit_m=0.0)
    assert found is not None and found.offenders
    held, result = hold_to_fixes(bad, fixes, found, _continuation(tmp_path, db), tmp_path / "work")
    name = rec.images[4].name
    assert [o.name for o in result.replaced] == [name] and result.taken_out == ()
    assert held.num_reg_images() == FRAMES
    centre = held.find_image_with_name(name).projection_center()
    assert np.linalg.norm(centre - rec.images[4].projection_center()) < 5 * NOISE


def test_a_camera_that_cannot_meet_its_fix_is_taken_out(tmp_path: Path) -> None:
    db = tmp_path / "database.db"
    rec = synthetic_database(db, FRAMES, 300)
    fixes = _fixes(rec)
    name = rec.images[2].name
    # the images place this camera where it is; its fix says half a unit away: it cannot be both
    fixes[name] = fixes[name] + np.array([0.0, 0.5, 0.0])
    found = check(rec, fixes, min_limit_m=0.0)
    assert found is not None and [o.name for o in found.offenders] == [name]
    held, result = hold_to_fixes(rec, fixes, found, _continuation(tmp_path, db), tmp_path / "work")
    assert [o.name for o in result.taken_out] == [name] and result.replaced == ()
    assert held.num_reg_images() == FRAMES - 1
    assert name not in {im.name for im in held.images.values() if im.has_pose}


def _track(n: int = 9, spacing: float = 30.0) -> dict[str, np.ndarray]:
    """Fixes along a straight line flown east, one photo every ``spacing`` metres."""
    return {f"IMG_{i:04d}.JPG": np.array([i * spacing, 0.0, 100.0]) for i in range(n)}


def test_a_stale_fix_off_the_flight_track_is_told_from_a_wrong_camera() -> None:
    fixes = _track()
    true_centre = fixes["IMG_0004.JPG"].copy()
    # the fix jumped 120 m north (a stale fix); the camera stays on the track: the fix is wrong
    fixes["IMG_0004.JPG"] = true_centre + np.array([0.0, 120.0, 0.0])
    assert off_track("IMG_0004.JPG", true_centre, fixes, 5.0)
    # an honest fix and a camera the model put 120 m away: the camera is wrong
    honest = _track()
    assert not off_track("IMG_0004.JPG", true_centre + np.array([0.0, 120.0, 0.0]), honest, 5.0)
    # the first and last photos have no track on both sides to be judged by
    fixes["IMG_0000.JPG"] = fixes["IMG_0000.JPG"] + np.array([0.0, 120.0, 0.0])
    assert not off_track("IMG_0000.JPG", honest["IMG_0000.JPG"], fixes, 5.0)


def test_a_photo_in_a_banked_turn_is_on_its_track() -> None:
    # a 60 m turn photographed every 50 m: the midpoint of its neighbours is 20 m inside the arc
    r, step = 60.0, 50.0 / 60.0
    fixes = {
        f"IMG_{i:04d}.JPG": np.array([r * np.cos(i * step), r * np.sin(i * step), 100.0]) for i in range(5)
    }
    assert not off_track("IMG_0002.JPG", fixes["IMG_0002.JPG"], fixes, 5.0)
