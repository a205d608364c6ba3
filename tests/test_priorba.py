"""A georeferenced survey bundle-adjusted with its GPS fixes as priors: the cameras go where the
inlier fixes and the photos agree, a fix the alignment called an outlier pulls nothing, and too
few fixes leave the model as it was."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.geo.georef import Alignment, camera_centres
from geomatch.geo.priorba import MIN_PRIORS, adjust_to_fixes, with_residuals
from geomatch.geo.similarity import Similarity

pytestmark = pytest.mark.unit

WIDTH, HEIGHT, FOCAL = 640, 480, 500.0
NADIR = np.diag([1.0, -1.0, -1.0])  # camera x east, y south, z down: looking straight down


def survey(rows: int = 4, cols: int = 4, height: float = 60.0, seed: int = 0) -> pycolmap.Reconstruction:
    """A nadir grid of cameras over gently rolling ground, every camera observing the points in
    its view (exact projections)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-40.0, 70.0, size=(1500, 2))
    points = np.c_[xy, 2.0 * np.sin(xy[:, 0] / 15.0) + rng.normal(0, 0.5, len(xy))]
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", FOCAL, WIDTH, HEIGHT)
    rec.add_camera_with_trivial_rig(cam)
    tracks: dict[int, list[tuple[int, int]]] = {}
    for r in range(rows):
        for c in range(cols):
            iid = r * cols + c + 1
            centre = np.array([c * 10.0, r * 10.0, height])
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(NADIR), -NADIR @ centre)
            uv, seen = [], []
            for k, p in enumerate(points):
                pc = pose * p
                if pc[2] <= 0:
                    continue
                u = cam.img_from_cam(pc)
                if 0 <= u[0] < WIDTH and 0 <= u[1] < HEIGHT:
                    seen.append(k)
                    uv.append(u)
            im = pycolmap.Image()
            im.name, im.image_id, im.camera_id = f"im{iid:02d}", iid, 1
            im.points2D = pycolmap.Point2DList([pycolmap.Point2D(u) for u in uv])
            rec.add_image_with_trivial_frame(im, pose)
            for j, k in enumerate(seen):
                tracks.setdefault(k, []).append((iid, j))
    for k, obs in tracks.items():
        if len(obs) >= 2:
            track = pycolmap.Track()
            for iid, j in obs:
                track.add_element(iid, j)
            rec.add_point3D(points[k], track)
    return rec


def alignment(names: list[str], inliers: list[bool]) -> Alignment:
    return Alignment(
        Similarity(1.0, np.eye(3), np.zeros(3)),
        np.array(inliers),
        np.zeros(len(names)),
        names=tuple(names),
    )


def test_the_cameras_go_where_the_fixes_say_and_the_photos_keep_their_shape() -> None:
    # every fix 3 m east and 1 m north of where the model has the camera: a shift the photos
    # cannot object to, so the whole model follows the priors
    rec = survey()
    truth = camera_centres(rec)
    enu = {n: c + np.array([3.0, 1.0, 0.0]) for n, c in truth.items()}
    names = sorted(enu)
    report = adjust_to_fixes(rec, enu, alignment(names, [True] * len(names)))
    assert report is not None and report.priors == len(names)
    after = camera_centres(rec)
    assert report.median_before_m == pytest.approx(np.hypot(3.0, 1.0), abs=1e-6)
    assert report.median_after_m < 0.3
    assert max(np.linalg.norm(after[n] - enu[n]) for n in names) < 0.5
    assert rec.compute_mean_reprojection_error() < 0.1


def test_a_fix_the_alignment_called_an_outlier_pulls_nothing() -> None:
    rec = survey()
    truth = camera_centres(rec)
    enu = dict(truth)
    names = sorted(enu)
    wild = names[5]
    enu[wild] = truth[wild] + np.array([40.0, -25.0, 10.0])  # a stale fix
    aligned = alignment(names, [n != wild for n in names])
    report = adjust_to_fixes(rec, enu, aligned)
    assert report is not None and report.priors == len(names) - 1
    after = camera_centres(rec)
    assert np.linalg.norm(after[wild] - truth[wild]) < 0.1
    residuals = with_residuals(rec, enu, aligned).residuals
    assert residuals[names.index(wild)] == pytest.approx(np.linalg.norm(after[wild] - enu[wild]))


def test_too_few_fixes_leave_the_model_as_it_was() -> None:
    rec = survey()
    before = camera_centres(rec)
    names = sorted(before)[: MIN_PRIORS - 1]
    enu = {n: before[n] + np.array([5.0, 0.0, 0.0]) for n in names}
    assert adjust_to_fixes(rec, enu, alignment(names, [True] * len(names))) is None
    after = camera_centres(rec)
    assert all(np.allclose(after[n], before[n]) for n in before)
