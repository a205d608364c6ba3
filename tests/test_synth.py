"""Synthetic scenes: renders are real perspective views consistent with the ground-truth poses."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.synth.aerial import Scene, covisibility, write_scene

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(seed=3)


def test_views_agree_through_the_ground_truth_geometry(scene: Scene) -> None:
    """A pixel of one view, lifted to 3D by its depth and projected into another view where it is
    visible (depth test), lands on the same colour: poses, intrinsics and renders agree."""
    cams = scene.cameras(2, 4, 200, 150)
    renders = {c.name: scene.render(c, supersample=1) for c in cams}
    checked = 0
    for a in cams:
        img_a, depth_a = renders[a.name]
        v, u = np.mgrid[0:150:3, 0:200:3]
        d = depth_a[v, u]
        ok = np.isfinite(d)
        pix = np.stack([u[ok] + 0.5, v[ok] + 0.5, np.ones(ok.sum())], 1)
        X = (pix @ np.linalg.inv(a.K).T * d[ok, None] - a.t) @ a.R  # world points
        for b in cams:
            if b is a:
                continue
            img_b, depth_b = renders[b.name]
            uv, z = b.project(X)
            ub, vb = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            inside = (z > 0) & (ub >= 0) & (ub < 200) & (vb >= 0) & (vb < 150)
            vis = inside.copy()
            vis[inside] = np.abs(depth_b[vb[inside], ub[inside]] - z[inside]) < 0.01 * z[inside]
            if vis.sum() < 50:
                continue
            ca = img_a[v[ok][vis], u[ok][vis]].astype(float)
            cb = img_b[vb[vis], ub[vis]].astype(float)
            assert np.median(np.abs(ca - cb)) < 25, (a.name, b.name)
            checked += 1
    assert checked >= 6


def test_scene_files_and_colmap_model(tmp_path) -> None:
    cams = write_scene(tmp_path, n_aerial=2, n_ground=3, seed=1, size=(160, 120))
    names = sorted(p.name for p in (tmp_path / "images").iterdir())
    assert names == sorted(c.name for c in cams) and len(names) == 5
    assert (tmp_path / "aerial.txt").read_text().split() == ["aerial_00.png", "aerial_01.png"]
    rec = pycolmap.Reconstruction(str(tmp_path / "gt"))
    assert rec.num_images() == 5
    by_name = {im.name: im for im in rec.images.values()}
    for c in cams:
        pose = by_name[c.name].cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), c.R, atol=1e-9)
        np.testing.assert_allclose(np.asarray(pose.translation), c.t, atol=1e-6)
        cam = rec.cameras[by_name[c.name].camera_id]
        assert (cam.width, cam.height) == (160, 120)
    aerial = [c for c in cams if c.aerial]
    ground = [c for c in cams if not c.aerial]
    assert all(c.centre[2] >= 10 for c in aerial)  # a drone's height, and what the XMP rule reads
    assert all(1.5 <= c.centre[2] <= 2.0 for c in ground)
    # ground cameras look near-horizontally: the optical axis within 20 degrees of the horizon
    assert all(abs(np.degrees(np.arcsin(c.R[2, 2]))) < 20 for c in ground)


def test_covisibility_ground_truth(scene: Scene) -> None:
    cams = scene.cameras(2, 4, 200, 150)
    cov = covisibility(scene, cams, scale=0.5)
    assert cov.shape == (6, 6) and np.allclose(np.diag(cov), 1.0)
    assert ((cov >= 0) & (cov <= 1)).all()
    ground = [i for i, c in enumerate(cams) if not c.aerial]
    aerial = [i for i, c in enumerate(cams) if c.aerial]
    # the drone's low oblique sees the walls the ground cameras see; neighbours on the walk
    # overlap, the two ends of a 90-degree walk hardly do
    assert max(min(cov[a, g], cov[g, a]) for g in ground for a in aerial) > 0.2
    assert min(cov[ground[0], ground[1]], cov[ground[1], ground[0]]) > 0.2
    assert max(cov[ground[0], ground[-1]], cov[ground[-1], ground[0]]) < 0.1
