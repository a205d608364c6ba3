"""A pair found at the network's input size is verified at the precision it was found with: on a
drone's 4000 px original, matches half a network pixel off their true spot (3 photo pixels)
pass COLMAP's verification as they pass it on the 2000 px copy, instead of many of them being
rejected by a threshold of 4 photo pixels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geomatch.metadata import ImageMeta
from geomatch.pipeline.database import PairMatches, verification_error, write
from geomatch.sfm.colmapdb import ColmapDatabase

pytestmark = pytest.mark.unit


def test_the_threshold_follows_the_network_pixel_only_beyond_the_tuned_sizes() -> None:
    assert verification_error(640, 2000, 2000) == 4.0  # the copies every set was tuned on
    assert verification_error(640, 1536, 1024) == 4.0
    assert verification_error(None, 4000, 4000) == 4.0  # matched at full size: COLMAP's own
    assert verification_error(640, 4000, 2250) == pytest.approx(8.0)


def _pair(width: int, height: int, noise_px: float, seed: int = 0) -> PairMatches:
    """Ground points under two nadir views (a shift and a small turn, a depth-varying parallax),
    ``noise_px`` photo pixels of Gaussian noise on the second view's points."""
    rng = np.random.default_rng(seed)
    n = 600
    f = 0.8 * width
    X = np.c_[rng.uniform(-20, 20, n), rng.uniform(-12, 12, n), 40 + rng.uniform(-4, 4, n)]
    c = np.array([width / 2, height / 2])
    a = np.radians(3)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    X1 = X @ R.T + np.array([6.0, 1.0, 0.5])
    k0 = f * X[:, :2] / X[:, 2:] + c
    k1 = f * X1[:, :2] / X1[:, 2:] + c + rng.normal(0, noise_px, (n, 2))
    keep = (k0 > 0).all(1) & (k0 < [width, height]).all(1) & (k1 > 0).all(1) & (k1 < [width, height]).all(1)
    k0, k1 = k0[keep].astype(np.float32), k1[keep].astype(np.float32)
    return PairMatches(k0, k1, np.ones(len(k0), np.float32), ((width, height), (width, height)))


def _inlier_share(tmp_path: Path, name: str, width: int, height: int, noise_px: float) -> float:
    meta = ImageMeta(width, height, "DJI", "FC300S", 0.8 * width, 60.0, -90.0)
    with ColmapDatabase(tmp_path / f"{name}.db") as db:
        ids = [db.add_image(f"{i}.jpg", meta) for i in range(2)]
        m = _pair(width, height, noise_px)
        written = write(db, ids[0], ids[1], m, 0.0, 640)
    return written.inliers / len(m)


def test_an_original_keeps_the_matches_its_half_size_copy_keeps(tmp_path: Path) -> None:
    # half a network pixel of noise on both: 1.6 photo px on the copy, 3.1 on the original
    copy = _inlier_share(tmp_path, "copy", 2000, 1125, 1.6)
    original = _inlier_share(tmp_path, "original", 4000, 2250, 3.1)
    assert copy > 0.85
    assert original > copy - 0.05
