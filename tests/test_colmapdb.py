from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.dbwrite import TILED_MIN_INLIERS, write
from geomatch.metadata import ImageMeta
from geomatch.pairstep import PairMatches
from geomatch.sfm.colmapdb import ColmapDatabase

pytestmark = pytest.mark.unit


def _pair_points(rng: np.random.Generator, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Matches consistent with a real two-view geometry: 3D points seen by two cameras."""
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(4, 8, n)]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = np.array([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0], [-np.sin(0.1), 0, np.cos(0.1)]])
    t = np.array([-0.6, 0.05, 0.1])
    x0 = X @ K.T
    x1 = (X @ R.T + t) @ K.T
    p0, p1 = x0[:, :2] / x0[:, 2:] - 0.5, x1[:, :2] / x1[:, 2:] - 0.5
    # well separated points, so that consolidation (radius 1.5) merges none of them
    keep = [
        i
        for i in range(n)
        if all(min(np.linalg.norm(p0[i] - p0[j]), np.linalg.norm(p1[i] - p1[j])) > 4 for j in range(i))
    ]
    return p0[keep].astype(np.float32), p1[keep].astype(np.float32)


DRONE = ImageMeta(640, 480, "DJI", "FC6310", 500.0, 60.0, -90.0)


def test_round_trip_read_back_with_pycolmap(tmp_path) -> None:
    path = tmp_path / "database.db"
    rng = np.random.default_rng(0)
    k0, k1 = _pair_points(rng)
    with ColmapDatabase(path) as db:
        a = db.add_image("a.jpg", DRONE)
        b = db.add_image("b.jpg", DRONE)
        c = db.add_image("c.png", ImageMeta(640, 480))  # no EXIF: own camera, COLMAP's focal guess
        db.add_image("d.png", ImageMeta(640, 480))
        assert db.add_image("a.jpg", DRONE) == a  # idempotent by name
        w = db.write_pair(a, b, k0, k1, np.linspace(1, 0, len(k0)), 1.5, 1.5)
        assert w.matches == len(k0) and w.inliers >= 0.95 * len(k0)
        again = db.write_pair(a, b, k0 + 3, k1, np.ones(len(k0)), 1.5, 1.5)
        assert again.skipped  # a replayed write changes nothing
        # pair given in the other order: stored with the smaller id first, indices follow
        w2 = db.write_pair(c, a, k1, k0, np.ones(len(k0)), 1.5, 1.5)
        assert w2.matches == len(k0)
    db = pycolmap.Database.open(str(path))
    try:
        cams = {im.name: im.camera_id for im in db.read_all_images()}
        assert cams["a.jpg"] == cams["b.jpg"] != cams["c.png"] != cams["d.png"]
        drone = db.read_camera(cams["a.jpg"])
        assert drone.has_prior_focal_length and drone.focal_length == pytest.approx(500.0)
        other = db.read_camera(cams["c.png"])
        assert not other.has_prior_focal_length and other.focal_length == pytest.approx(1.2 * 640)
        assert db.num_frames() == 4 and db.num_rigs() == 3
        kp_a = db.read_keypoints(a)
        np.testing.assert_allclose(kp_a[:, :2], k0 + 0.5, atol=1e-4)  # COLMAP's pixel-centre convention
        m = db.read_matches(a, b)
        np.testing.assert_allclose(db.read_keypoints(b)[m[:, 1], :2], k1 + 0.5, atol=1e-4)
        # the second pair reused a's keypoints (consolidation): a gained no new keypoints
        assert db.num_keypoints_for_image(a) == len(k0)
        m_ac = db.read_matches(a, c)  # stored (a, c) since a has the smaller id
        pa = kp_a[m_ac[:, 0], :2] - 0.5
        pc = db.read_keypoints(c)[m_ac[:, 1], :2] - 0.5
        j = np.argmin(np.linalg.norm(pa[:, None] - k0[None], axis=2), axis=1)
        np.testing.assert_allclose(pc, k1[j], atol=1e-4)  # c's keypoint is the partner of a's
        tvg = db.read_two_view_geometry(a, b)
        assert len(tvg.inlier_matches) == w.inliers
        assert db.num_verified_image_pairs() == 2
    finally:
        db.close()


def test_device_camera_survives_reopening(tmp_path) -> None:
    path = tmp_path / "database.db"
    with ColmapDatabase(path) as db:
        a = db.add_image("a.jpg", DRONE)
    with ColmapDatabase(path) as db:  # a later run adds an image of the same device
        b = db.add_image("b.jpg", DRONE)
        assert db.db.read_image(a).camera_id == db.db.read_image(b).camera_id
        handheld = ImageMeta(640, 480, "Canon", "EOS", 500.0)  # same intrinsics, other device
        c = db.add_image("c.jpg", handheld)
        assert db.db.read_image(c).camera_id != db.db.read_image(a).camera_id


def test_a_failed_pair_write_leaves_nothing(tmp_path) -> None:
    path = tmp_path / "database.db"
    rng = np.random.default_rng(1)
    k0, k1 = _pair_points(rng)
    with ColmapDatabase(path) as db:
        a = db.add_image("a.jpg", DRONE)
        b = db.add_image("b.jpg", DRONE)
        with pytest.raises(ValueError):
            db.write_pair(a, b, k0, k1[:10], np.ones(len(k0)), 1.5, 1.5)  # mismatched lengths
        assert not db.has_pair(a, b)
        assert db.db.num_keypoints() == 0


def test_a_pair_with_no_matches_counts_as_matched(tmp_path) -> None:
    """A matcher that found nothing answered: a rerun must not match the pair again."""
    path = tmp_path / "database.db"
    empty = np.zeros((0, 2), np.float32)
    with ColmapDatabase(path) as db:
        a = db.add_image("a.jpg", DRONE)
        b = db.add_image("b.jpg", DRONE)
        c = db.add_image("c.jpg", DRONE)
        w = db.write_pair(c, a, empty, empty, np.zeros(0), 1.5, 1.5)
        assert w.matches == 0 and not w.skipped
        assert db.has_pair(a, c) and db.has_pair(c, a)
        assert db.write_pair(a, c, empty, empty, np.zeros(0), 1.5, 1.5).skipped
        assert not db.has_pair(a, b)


def test_verification_gives_the_same_inliers_for_the_same_matches(tmp_path) -> None:
    """COLMAP seeds its RANSAC anew on every call; the database fixes the seed, so writing the same
    matches again keeps the same inliers (noise near the threshold and outliers, where another
    draw moves the count)."""
    rng = np.random.default_rng(0)
    k0, k1 = _pair_points(rng, 400)
    k1 = k1 + rng.normal(0, 2.5, size=k1.shape).astype(np.float32)
    n_out = len(k0) // 3
    k1[:n_out] = rng.uniform([0, 0], [640, 480], size=(n_out, 2)).astype(np.float32)
    inliers = []
    for run in range(6):
        with ColmapDatabase(tmp_path / f"{run}.db") as db:
            a = db.add_image("a.jpg", DRONE)
            b = db.add_image("b.jpg", DRONE)
            inliers.append(db.write_pair(a, b, k0, k1, np.ones(len(k0)), 1.5, 1.5).inliers)
    assert inliers[0] > 0 and len(set(inliers)) == 1, inliers


def test_a_tiled_pair_needs_more_inliers_than_a_plain_one(tmp_path) -> None:
    """A few dozen coherent matches verify a plain pair, but a tiled pair (an aerial image's crops
    against a ground photo, where a few dozen coherent wrong matches are what a pair sharing nothing
    gets) is written without a geometry below dbwrite.TILED_MIN_INLIERS; from it on it verifies."""
    k0, k1 = _pair_points(np.random.default_rng(1), 400)
    few = TILED_MIN_INLIERS - 20
    assert len(k0) > TILED_MIN_INLIERS + 20

    def inliers(n: int, tiled: bool) -> int:
        m = PairMatches(k0[:n], k1[:n], np.ones(n, np.float32), ((640, 480), (640, 480)), tiled)
        with ColmapDatabase(tmp_path / f"{n}_{tiled}.db") as db:
            a, b = db.add_image("a.jpg", DRONE), db.add_image("b.jpg", DRONE)
            return write(db, a, b, m, 1.0, None).inliers

    assert inliers(few, tiled=False) == few
    assert inliers(few, tiled=True) == 0
    assert inliers(TILED_MIN_INLIERS + 20, tiled=True) == TILED_MIN_INLIERS + 20
