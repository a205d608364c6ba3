"""Indoor rooms: pairs obey the selection rules, depth and poses agree, pose scoring is exact on truth."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.cli import main
from geomatch.eval.pose import pose_auc, relative_pose_error
from geomatch.synth.indoor import IndoorPair, covisibility, gt_matches, indoor_pairs, no_overlap_pairs

pytestmark = pytest.mark.unit

SMALL = {"width": 160, "height": 120, "supersample": 1}


@pytest.fixture(scope="module")
def pairs() -> list[IndoorPair]:
    return indoor_pairs(seed=0, n_pairs=3, **SMALL)


@pytest.fixture(scope="module")
def empty_pairs() -> list[IndoorPair]:
    return no_overlap_pairs(seed=0, n_pairs=2, **SMALL)


def _grid(p: IndoorPair, step: int = 3) -> np.ndarray:
    h, w = p.depth0.shape
    v, u = np.mgrid[0:h:step, 0:w:step]
    return np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)


def test_deterministic_per_seed(pairs: list[IndoorPair]) -> None:
    again = indoor_pairs(seed=0, n_pairs=1, **SMALL)[0]
    assert again.name == pairs[0].name
    np.testing.assert_array_equal(again.image0, pairs[0].image0)
    np.testing.assert_array_equal(again.depth1, pairs[0].depth1)
    np.testing.assert_allclose(again.R, pairs[0].R)


def test_pairs_meet_the_selection_rules(pairs: list[IndoorPair]) -> None:
    assert len(pairs) == 3
    for p in pairs:
        assert p.image0.shape == (120, 160, 3) and p.image0.dtype == np.uint8
        assert p.depth0.shape == (120, 160) and np.all(np.isfinite(p.depth0)) and p.depth0.min() > 0
        assert 20.0 <= p.rotation_deg <= 70.0
        assert p.covisibility >= 0.10
        assert p.covisibility == pytest.approx(
            covisibility(p.depth0, p.depth1, p.K0, p.K1, p.R, p.t), abs=1e-12
        )
        assert np.linalg.norm(p.t) > 0.3  # a real baseline, not a pure rotation
        # mostly plain surfaces: a large share of the image has almost no local gradient
        grey = p.image0.astype(np.float32).mean(axis=2)
        flat = (np.abs(np.diff(grey, axis=1))[:-1] + np.abs(np.diff(grey, axis=0))[:, :-1]) < 4
        assert flat.mean() > 0.3


def test_no_overlap_pairs_share_nothing(empty_pairs: list[IndoorPair]) -> None:
    assert len(empty_pairs) == 2
    for p in empty_pairs:
        assert covisibility(p.depth0, p.depth1, p.K0, p.K1, p.R, p.t, stride=1) == 0.0
        assert not gt_matches(p, _grid(p, 1))[1].any()


def test_ground_truth_correspondences_agree_with_poses_and_back(pairs: list[IndoorPair]) -> None:
    """Image 0 -> image 1 -> image 0 through depth lands where it started (sub-pixel), and the
    colours at both ends of a correspondence agree: renders, depths and poses are one geometry."""
    for p in pairs:
        pts0 = _grid(p)
        pts1, ok = gt_matches(p, pts0)
        assert ok.sum() > 50
        back = IndoorPair(
            p.name, p.image1, p.image0, p.K1, p.K0, p.R.T, -p.R.T @ p.t, p.depth1, p.depth0, 0, 0
        )
        # back-projecting needs depth at the exact point: use the points that landed on pixel centres
        pts1r = np.round(pts1[ok])
        pts0b, ok_b = gt_matches(back, pts1r)
        assert ok_b.mean() > 0.9
        err = np.linalg.norm(pts0b[ok_b] - pts0[ok][ok_b], axis=1)
        assert np.median(err) < 1.0  # rounding pts1 moves the point by <= 0.7 px in image 1
        c0 = p.image0[pts0[ok, 1].astype(int), pts0[ok, 0].astype(int)].astype(float)
        c1 = p.image1[pts1r[:, 1].astype(int), pts1r[:, 0].astype(int)].astype(float)
        assert np.median(np.abs(c0 - c1)) < 20


def test_pose_error_of_exact_correspondences_is_zero(pairs: list[IndoorPair]) -> None:
    errors = []
    for p in pairs:
        pts0 = _grid(p, 5)
        pts1, ok = gt_matches(p, pts0)
        err_r, err_t = relative_pose_error(pts0[ok], pts1[ok], p.K0, p.K1, p.R, p.t)
        assert err_r < 0.5 and err_t < 0.5, p.name
        errors.append(max(err_r, err_t))
        # the +0.5 convention matters: the same matches half a pixel off give a worse pose
        shifted = relative_pose_error(pts0[ok] + 0.5, pts1[ok], p.K0, p.K1, p.R, p.t)
        assert max(shifted) > 10 * max(err_r, err_t, 1e-4)
        assert relative_pose_error(pts0[ok][:4], pts1[ok][:4], p.K0, p.K1, p.R, p.t) == (np.inf, np.inf)
    assert pose_auc(errors)[0] > 0.9


def test_cli_writes_an_indoor_colmap_model(tmp_path) -> None:
    out = tmp_path / "room"
    rc = main(
        [
            "synth",
            str(out),
            "--kind",
            "indoor",
            "--seed",
            "1",
            "--ground",
            "3",
            "--width",
            "96",
            "--height",
            "72",
        ]
    )
    assert rc == 0
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == ["view_00.png", "view_01.png", "view_02.png"]
    depths = sorted(p.name for p in (out / "depth").iterdir())
    assert depths == ["view_00.npy", "view_01.npy", "view_02.npy"]
    assert np.load(out / "depth" / "view_00.npy").shape == (72, 96)
    rec = pycolmap.Reconstruction(str(out / "gt"))
    assert rec.num_reg_images() == 3
    cam = rec.cameras[1]
    assert (cam.width, cam.height) == (96, 72)
