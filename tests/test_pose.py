"""Pose scoring over several RANSAC orderings: the draw is measured apart from the matches."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.eval.pose import auc_over_runs, pose_auc, relative_pose_error, shuffled_errors
from geomatch.synth.camera import Camera, look_at

pytestmark = pytest.mark.unit


def _pair(noise_px: float, outliers: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    X = rng.uniform([-3, -2, 6], [3, 2, 10], (300, 3))
    cams = []
    for c in (np.array([0.0, 0, 0]), np.array([1.5, 0.2, 0.5])):
        R, t = look_at(c, np.array([0.0, 0, 8]), up=np.array([0.0, -1, 0]))
        cams.append(Camera("c", K, R, t, 640, 480, False))
    k0, _ = cams[0].project(X)
    k1, _ = cams[1].project(X)
    k1 = k1 + rng.normal(0, noise_px, k1.shape)
    bad = rng.random(len(k1)) < outliers
    k1[bad] = rng.uniform([0, 0], [640, 480], (int(bad.sum()), 2))
    R_rel = cams[1].R @ cams[0].R.T
    t_rel = cams[1].t - R_rel @ cams[0].t
    return k0, k1, K, R_rel, t_rel


def test_first_run_is_the_given_order_and_later_runs_redraw() -> None:
    k0, k1, K, R, t = _pair(noise_px=1.0, outliers=0.4)
    seen: list[np.ndarray] = []

    def error(a: np.ndarray, b: np.ndarray) -> float:
        seen.append(a.copy())
        return max(relative_pose_error(a, b, K, K, R, t))

    errs = shuffled_errors(k0, k1, error, runs=4, seed=3)
    assert len(errs) == 4 and len(seen) == 4
    np.testing.assert_array_equal(seen[0], k0)
    # every run sees the same matches, in another order
    for s in seen[1:]:
        assert not np.array_equal(s, k0)
        np.testing.assert_array_equal(np.sort(s, axis=0), np.sort(k0, axis=0))
    assert errs[0] == max(relative_pose_error(k0, k1, K, K, R, t))
    # noisy matches with many outliers: the orderings do not all give the same error
    assert len(set(errs)) > 1
    assert shuffled_errors(k0, k1, error, runs=4, seed=3) == errs  # seeded


def test_auc_over_runs_is_the_mean_and_spread_of_per_run_aucs() -> None:
    errors = np.array([[1.0, 30.0], [4.0, 4.0], [np.inf, 2.0]])  # 3 pairs, 2 runs
    mean, sd = auc_over_runs(errors)
    runs = np.array([pose_auc(errors[:, 0]), pose_auc(errors[:, 1])])
    np.testing.assert_allclose(mean, runs.mean(0))
    np.testing.assert_allclose(sd, runs.std(0))
    assert np.all(sd > 0)
    one_run, zero = auc_over_runs([[1.0], [4.0], [np.inf]])
    np.testing.assert_allclose(one_run, pose_auc([1.0, 4.0, np.inf]))
    np.testing.assert_allclose(zero, 0.0)
