from __future__ import annotations

import numpy as np
import pycolmap
import pytest
import torch

from geomatch.epipolar.geometry import SampsonGrid, eight_point, estimate_fundamental, sampson_distance

pytestmark = pytest.mark.unit


def two_view(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of a non-planar scene seen by two cameras, and the true F (x1^T F x0 = 0)."""
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 9, n)]
    ang = 0.15
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    t = np.array([-1.0, 0.1, 0.2])
    x0 = (X @ K.T)[:, :2] / X[:, 2:3]
    Xc = X @ R.T + t
    x1 = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    return x0, x1, F / np.linalg.norm(F)


def test_sampson_matches_pycolmap_on_random_data() -> None:
    rng = np.random.default_rng(3)
    F = rng.normal(size=(3, 3))
    pa = rng.uniform(0, 640, size=(200, 2))
    pb = rng.uniform(0, 480, size=(200, 2))
    ours = sampson_distance(torch.from_numpy(F), torch.from_numpy(pa), torch.from_numpy(pb)).numpy()
    theirs = np.asarray(pycolmap.compute_squared_sampson_error(pa, pb, F))
    np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-9)


def test_sampson_grid_equals_pairwise() -> None:
    rng = np.random.default_rng(4)
    F = torch.from_numpy(rng.normal(size=(3, 3)))
    pa = torch.from_numpy(rng.uniform(0, 100, size=(30, 2)))
    pb = torch.from_numpy(rng.uniform(0, 100, size=(40, 2)))
    ia, jb = torch.meshgrid(torch.arange(30), torch.arange(40), indexing="ij")
    ia, jb = ia.flatten(), jb.flatten()
    np.testing.assert_allclose(
        SampsonGrid(F, pa, pb).pairs(ia, jb).numpy(), sampson_distance(F, pa[ia], pb[jb])
    )


@pytest.mark.parametrize("method", ["8point", "magsac"])
def test_fundamental_estimators_recover_true_geometry(method: str) -> None:
    x0, x1, F_true = two_view(100)
    F, inliers = estimate_fundamental(torch.from_numpy(x0), torch.from_numpy(x1), method)
    assert F is not None and inliers is not None
    d = sampson_distance(F, torch.from_numpy(x0), torch.from_numpy(x1))
    assert float(d.max()) < 1e-3
    # and it is the true F up to scale and sign
    Fn = F.numpy() / np.linalg.norm(F.numpy())
    assert min(np.abs(Fn - F_true).max(), np.abs(Fn + F_true).max()) < 1e-3


def test_eight_point_needs_eight_matches() -> None:
    x0, x1, _ = two_view(7)
    assert estimate_fundamental(torch.from_numpy(x0), torch.from_numpy(x1)) == (None, None)
    with pytest.raises(ValueError, match="at least 8"):
        eight_point(torch.from_numpy(x0), torch.from_numpy(x1))


def test_degenerate_input_does_not_raise() -> None:
    """OpenCV's USAC asserts on some degenerate sets (seen on tiny crops' matches): fall back, never crash."""
    import torch

    from geomatch.epipolar.geometry import estimate_fundamental

    pa = torch.tensor([[float(i), 2.0 * i] for i in range(12)], dtype=torch.float64)  # collinear
    F, mask = estimate_fundamental(pa, pa.clone(), "magsac", 1.0)
    assert F is not None and mask is not None
