from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from geomatch.metadata import ImageMeta
from geomatch.pipeline.database import TILED_MIN_INLIERS, PairMatches, write
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


def _three_views(rng: np.random.Generator, n: int = 300) -> list[np.ndarray]:
    """One set of 3D points in three cameras, well separated in every view (no consolidation
    between different points at radius 1.5)."""
    X = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(4, 8, n)]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    views = []
    for angle, t in ((0.0, (0, 0, 0)), (0.1, (-0.6, 0.05, 0.1)), (-0.12, (0.7, -0.05, 0.05))):
        R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        x = (X @ R.T + np.asarray(t)) @ K.T
        views.append(x[:, :2] / x[:, 2:] - 0.5)
    keep = [i for i in range(n) if all(min(np.linalg.norm(v[i] - v[j]) for v in views) > 4 for j in range(i))]
    return [v[keep].astype(np.float32) for v in views]


def _shared_view_writes(path, views, prepare_first: bool, jitter: float = 0.0) -> list[np.ndarray]:
    """Pairs (a, b) and (a, c) written one after the other, or both prepared against the empty
    database before either commits (two workers verifying at once); per pair, the keypoint of
    ``a`` each 3D point's match landed on."""
    va, vb, vc = views
    va_c = va + np.random.default_rng(1).normal(0, jitter, va.shape).astype(np.float32) if jitter else va
    scores = np.linspace(1, 0, len(va))
    with ColmapDatabase(path) as db:
        a, b, c = (db.add_image(n, DRONE) for n in ("a.jpg", "b.jpg", "c.jpg"))
        if prepare_first:
            pb = db.prepare_pair(a, b, va, vb, scores, 1.5, 1.5)
            pc = db.prepare_pair(a, c, va_c, vc, scores, 1.5, 1.5)
            wb, wc = db.commit_pair(pb), db.commit_pair(pc)
        else:
            wb = db.write_pair(a, b, va, vb, scores, 1.5, 1.5)
            wc = db.write_pair(a, c, va_c, vc, scores, 1.5, 1.5)
        assert wb.matches == wc.matches == len(va)
        kp_a = db.keypoints(a)
        landed = []
        for other, v in ((b, vb), (c, vc)):
            m = db.db.read_matches(a, other)
            kp_o = db.keypoints(other)
            # the matches in the 3D points' order: by the other image's keypoint position
            order = np.argsort(np.linalg.norm(kp_o[m[:, 1]][:, None] - v[None], axis=2).argmin(1))
            landed.append(m[order, 0])
            tvg = db.db.read_two_view_geometry(a, other)
            inl = {tuple(r) for r in np.asarray(tvg.inlier_matches).tolist()}
            assert len(inl) >= 0.95 * len(va) and inl <= {tuple(r) for r in m.tolist()}
        assert len(kp_a) == len(va)  # one keypoint per point of a, shared by both pairs
    return landed


def test_pairs_verified_at_once_join_their_tracks_as_if_written_in_turn(tmp_path) -> None:
    """Two workers prepare pairs that share an image against the same database; the second to
    commit lands its new keypoints on the ones the first appended, so each 3D point's matches
    in both pairs meet at one keypoint of the shared image (a track), exactly as writes one
    after the other give."""
    views = _three_views(np.random.default_rng(3))
    seq = _shared_view_writes(tmp_path / "seq.db", views, prepare_first=False)
    both = _shared_view_writes(tmp_path / "both.db", views, prepare_first=True)
    assert np.array_equal(both[0], both[1])  # every point's track goes through one keypoint of a
    assert np.array_equal(seq[0], both[0]) and np.array_equal(seq[1], both[1])


def test_rebased_pairs_join_tracks_within_the_snap_radius(tmp_path) -> None:
    """The shared image's points seen by the second pair a fraction of a pixel off (two
    matchers' sub-pixel answers) still join the first pair's keypoints."""
    views = _three_views(np.random.default_rng(4))
    landed = _shared_view_writes(tmp_path / "jit.db", views, prepare_first=True, jitter=0.3)
    assert np.array_equal(landed[0], landed[1])
