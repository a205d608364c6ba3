"""Least-squares matching on a package-shipped photo warped by a known homography."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geomatch.eval.homography import apply_h
from geomatch.features.subpixel import SubpixelOptions, neighbour_affine, refine_points
from geomatch.imageio import prepare
from geomatch.synth.photos import warped_pair

pytestmark = pytest.mark.unit


def _setup(seed: int = 3) -> tuple[object, torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
    pair = warped_pair("astronaut", seed=seed, strength=0.15, max_side=512)
    a = prepare(pair.image0, None, torch.device("cpu"))
    b = prepare(pair.image1, None, torch.device("cpu"))
    rng = np.random.default_rng(seed)
    h, w = pair.image0.shape[:2]
    pa = rng.uniform([40, 40], [w - 40, h - 40], size=(400, 2))
    exact = apply_h(pair.H, pa)
    keep = (exact[:, 0] > 30) & (exact[:, 0] < w - 30) & (exact[:, 1] > 30) & (exact[:, 1] < h - 30)
    return a, b, pa[keep], exact[keep], rng


def test_points_move_onto_the_true_position() -> None:
    a, b, pa, exact, rng = _setup()
    noisy = exact + rng.uniform(-1.2, 1.2, size=exact.shape)
    out, moved = refine_points(
        a.tensor, b.tensor, torch.from_numpy(pa).float(), torch.from_numpy(noisy).float()
    )
    before = np.linalg.norm(noisy - exact, axis=1)
    after = np.linalg.norm(out.numpy() - exact, axis=1)
    assert moved.float().mean() > 0.5  # most patches of a photo carry texture
    assert np.median(after[moved.numpy()]) < 0.25 < np.median(before)
    # points it could not refine keep their start exactly
    assert np.array_equal(out.numpy()[~moved.numpy()], noisy.astype(np.float32)[~moved.numpy()])


def test_a_wrong_match_is_not_dragged_elsewhere() -> None:
    """A point 8 px off its match lies beyond max_shift's reach: it must stay where it was, not
    be pulled onto some other texture."""
    a, b, pa, exact, _ = _setup(seed=4)
    far = exact + np.array([8.0, -6.0])
    out, _ = refine_points(a.tensor, b.tensor, torch.from_numpy(pa).float(), torch.from_numpy(far).float())
    err = np.linalg.norm(out.numpy() - far, axis=1)
    assert float(err.max()) <= SubpixelOptions().max_shift + 1e-4
    assert np.linalg.norm(out.numpy() - exact, axis=1).min() > 1.0  # none landed on the truth by chance


def test_flat_patches_are_left_alone() -> None:
    flat = torch.full((1, 3, 120, 160), 0.5)
    pa = torch.tensor([[60.0, 60.0], [80.0, 50.0]])
    pb = pa + 0.7
    out, moved = refine_points(flat, flat, pa, pb)
    assert not moved.any()
    assert torch.equal(out, pb)


def test_neighbour_affine_recovers_a_linear_map() -> None:
    rng = np.random.default_rng(0)
    pa = torch.from_numpy(rng.uniform(0, 200, size=(300, 2))).float()
    m = torch.tensor([[1.1, 0.2], [-0.15, 0.9]])
    pb = pa @ m.T + torch.tensor([5.0, -3.0])
    lin = neighbour_affine(pa, pb, SubpixelOptions())
    assert torch.allclose(lin, m.expand_as(lin), atol=1e-3)
    # too few neighbours: the identity
    lone = neighbour_affine(pa[:3], pb[:3], SubpixelOptions())
    assert torch.equal(lone, torch.eye(2).expand(3, 2, 2))
