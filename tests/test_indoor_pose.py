"""`geo` against its own anchors on rendered indoor pairs: real networks, exact ground truth.

The pairs come from a seed outside the benchmark's tuning (0-2) and test (100-102) splits. Pose
errors are the median over RANSAC orderings (one ordering's draw moves a pair by degrees).
"""

from __future__ import annotations

import numpy as np
import pytest

from geomatch import Matcher
from geomatch.eval.pose import relative_pose_error, shuffled_errors
from geomatch.synth.indoor import IndoorPair, gt_matches, indoor_pairs

pytestmark = pytest.mark.nets

SEED = 7


@pytest.fixture(scope="module")
def pairs() -> list[IndoorPair]:
    return indoor_pairs(seed=SEED, n_pairs=3)


def _score(m: Matcher, p: IndoorPair) -> tuple[float, np.ndarray]:
    """(median pose error over 5 orderings in degrees, ground-truth errors of the correct matches)."""
    r = m.match(p.image0, p.image1)
    errs = shuffled_errors(
        r.keypoints0,
        r.keypoints1,
        lambda a, b: max(relative_pose_error(a, b, p.K0, p.K1, p.R, p.t)),
        runs=5,
    )
    proj, ok = gt_matches(p, r.keypoints0.astype(np.float64))
    d = np.linalg.norm(proj - r.keypoints1, axis=1)
    return float(np.median(errs)), d[ok & (d < 3)]


def test_geo_pose_is_no_worse_than_its_anchors_and_its_points_are_more_precise(
    matcher: Matcher, pairs: list[IndoorPair]
) -> None:
    sparse = matcher.derive(method="sparse", resize=640)
    # the full method on every pair: these rendered pairs' anchors are strong, and by default geo
    # answers such a pair with the anchors alone (no rounds, no least-squares step)
    geo = matcher.derive(method="geo", resize=640, anchors_suffice=0)
    pose_s, pose_g, near_s, near_g = [], [], [], []
    for p in pairs:
        es, ds = _score(sparse, p)
        eg, dg = _score(geo, p)
        pose_s.append(es)
        pose_g.append(eg)
        near_s.append(ds)
        near_g.append(dg)
    ds, dg = np.concatenate(near_s), np.concatenate(near_g)
    # least-squares matching puts the correct matches' points nearer the truth
    assert np.median(dg) < 0.75 * np.median(ds), (np.median(dg), np.median(ds))
    assert len(dg) >= 0.9 * len(ds)  # and not by dropping the hard ones
    # pose: no worse pair by pair, within the draw of 5 orderings (0.5 deg)
    for p, es, eg in zip(pairs, pose_s, pose_g, strict=True):
        assert eg <= es + 0.5, (p.name, eg, es)
