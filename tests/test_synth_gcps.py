"""A synthetic scene's ground control points are clicked where the cameras truly see them: on
the ground, inside the image, never behind a building, so that a GCP test judges the model and
not its own test data."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.geo.gcpfile import read_gcp_file
from geomatch.synth.aerial import Scene
from geomatch.synth.gcps import CRS, OFFSET, scene_gcps, visible

pytestmark = pytest.mark.unit


def test_each_click_is_the_true_projection_of_its_point_and_the_file_reads_back() -> None:
    scene = Scene(1)
    cams = scene.cameras(2, 4, 640, 480)
    text, truth = scene_gcps(scene, cams, 5, seed=0)
    assert text.splitlines()[0] == CRS and len(truth) == 5
    g = read_gcp_file(text, {c.name: (c.width, c.height) for c in cams})
    assert g.problems == [] and sorted(g.points) == sorted(truth)
    by_name = {c.name: c for c in cams}
    for name, p in g.points.items():
        X = np.asarray(truth[name]) - OFFSET
        assert X[2] == 0.0 and len(p.observations) >= 2
        for o in p.observations:
            uv, depth = by_name[o.image].project(X[None])
            assert depth[0] > 0 and np.allclose(uv[0], o.pixel, atol=1e-3)


def test_a_point_behind_a_building_is_not_clicked() -> None:
    scene = Scene(1)
    cases = 0
    for cam in (c for c in scene.cameras(2, 4, 640, 480) if not c.aerial):
        for box in scene.boxes:
            centre = (box.lo[:2] + box.hi[:2]) / 2
            away = (centre - cam.centre[:2]) / np.linalg.norm(centre - cam.centre[:2])
            # the ground just beyond the building, on the camera's line through its middle
            behind = np.append(centre + away * (np.linalg.norm(box.hi[:2] - box.lo[:2]) / 2 + 0.5), 0.0)
            uv, depth = cam.project(behind[None])
            inside = 8 <= uv[0, 0] <= cam.width - 9 and 8 <= uv[0, 1] <= cam.height - 9
            if depth[0] > 0 and inside:  # in the picture, so only the building can hide it
                cases += 1
                assert visible(scene, cam, behind) is None, (cam.name, box)
    assert cases >= 3
    # the same camera does click open ground in its picture
    assert scene_gcps(scene, scene.cameras(2, 4, 640, 480), 3, seed=0)[1]


def test_survey_noise_moves_the_coordinates_not_the_clicks() -> None:
    scene = Scene(1)
    cams = scene.cameras(2, 4, 640, 480)
    exact, truth = scene_gcps(scene, cams, 4, seed=0)
    noisy, truth2 = scene_gcps(scene, cams, 4, seed=0, noise_m=0.05)
    assert truth == truth2
    pix = [ln.split()[3:] for ln in exact.splitlines()[1:]]
    assert pix == [ln.split()[3:] for ln in noisy.splitlines()[1:]]
    assert exact != noisy
