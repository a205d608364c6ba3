"""The device-side robust F against OpenCV's MAGSAC++ on synthetic two-view geometry with outliers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geomatch.epipolar.geometry import estimate_fundamental, sampson_distance
from geomatch.epipolar.robust_f import ransac_fundamental

pytestmark = pytest.mark.unit


def _scene(seed: int, n: int = 400, outliers: float = 0.4, noise: float = 0.5):
    """(pa, pb with noise and outliers, exact pa, exact pb, inlier mask) of a 640x480 pair."""
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(4, 12, n)]
    ang = np.radians(rng.uniform(10, 30))
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    t = np.array([-1.5, 0.1, 0.3])

    def project(P: np.ndarray) -> np.ndarray:
        p = P @ K.T
        return p[:, :2] / p[:, 2:]

    a, b = project(X), project(X @ R.T + t)
    inl = rng.uniform(size=n) > outliers
    na = a + rng.normal(0, noise, a.shape)
    nb = b + rng.normal(0, noise, b.shape)
    nb[~inl] = rng.uniform([0, 0], [640, 480], size=(int((~inl).sum()), 2))
    f = lambda x: torch.from_numpy(x).float()  # noqa: E731
    return f(na), f(nb), f(a), f(b), torch.from_numpy(inl)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_as_accurate_as_magsac_and_separates_the_outliers(seed: int) -> None:
    pa, pb, ea, eb, inl = _scene(seed)
    F_t, mask_t = ransac_fundamental(pa, pb, threshold=1.0)
    F_m, _ = estimate_fundamental(pa, pb, "magsac", 1.0)
    assert F_t is not None and mask_t is not None and F_m is not None
    # error of the exact correspondences under each F (px^2): the geometry itself, not the draw
    err_t = float(sampson_distance(F_t, ea[inl], eb[inl]).sqrt().median())
    err_m = float(sampson_distance(F_m, ea[inl], eb[inl]).sqrt().median())
    assert err_t <= max(1.5 * err_m, 0.15), (err_t, err_m)
    recall = float((mask_t & inl).sum() / inl.sum())
    precision = float((mask_t & inl).sum() / mask_t.sum())
    assert recall > 0.85 and precision > 0.95, (recall, precision)


def test_deterministic_per_seed_and_needs_eight_matches() -> None:
    pa, pb, *_ = _scene(5)
    F1, m1 = ransac_fundamental(pa, pb, seed=3)
    F2, m2 = ransac_fundamental(pa, pb, seed=3)
    assert F1 is not None and F2 is not None and m1 is not None and m2 is not None
    assert torch.equal(F1, F2) and torch.equal(m1, m2)
    assert ransac_fundamental(pa[:7], pb[:7]) == (None, None)


def test_auto_picks_opencv_on_the_cpu_and_torch_when_asked() -> None:
    pa, pb, *_ = _scene(6)
    F_auto, _ = estimate_fundamental(pa, pb, "auto", 1.0)
    F_m, _ = estimate_fundamental(pa, pb, "magsac", 1.0)
    F_t, _ = estimate_fundamental(pa, pb, "torch", 1.0)
    assert F_auto is not None and F_m is not None and F_t is not None
    assert torch.allclose(F_auto, F_m)
    assert F_t.device == pa.device and F_t.dtype == pa.dtype
