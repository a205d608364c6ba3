"""Epipolar geometry used by the optimizer: Sampson distance and fundamental-matrix estimation.

The Sampson distance here is the paper's eq. 1, i.e. the *squared* first-order geometric
error in pixels^2, the same quantity as pycolmap's ``compute_squared_sampson_error``. The
paper's tau = 10 therefore allows about 3 px of error.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import torch

log = logging.getLogger(__name__)

MIN_POINTS = 8


def homogeneous(points: torch.Tensor) -> torch.Tensor:
    return torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)


def sampson_distance(fundamental: torch.Tensor, pa: torch.Tensor, pb: torch.Tensor) -> torch.Tensor:
    """Sampson distance of corresponding rows of ``pa`` (K, 2) and ``pb`` (K, 2) under F (x_b^T F x_a = 0)."""
    F = fundamental.to(pa.dtype)
    xa, xb = homogeneous(pa), homogeneous(pb)
    Fxa = xa @ F.T  # (K, 3)
    Ftxb = xb @ F  # (K, 3)
    num = (xb * Fxa).sum(-1) ** 2
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    return num / den.clamp_min(1e-12)


class SampsonGrid:
    """Sampson distance between any point of A and any point of B, from per-point terms.

    The epipolar lines and the denominators are computed once per point, so evaluating many
    (i, j) candidate pairs costs a few element-wise operations each.
    """

    def __init__(self, fundamental: torch.Tensor, pa: torch.Tensor, pb: torch.Tensor) -> None:
        F = fundamental.to(device=pa.device, dtype=pa.dtype)
        self.Fxa = homogeneous(pa) @ F.T  # (N, 3): epipolar lines in B
        self.xb = homogeneous(pb)  # (M, 3)
        Ftxb = self.xb @ F  # (M, 3)
        self.den_a = self.Fxa[:, 0] ** 2 + self.Fxa[:, 1] ** 2
        self.den_b = Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2

    def pairs(self, ia: torch.Tensor, jb: torch.Tensor) -> torch.Tensor:
        num = (self.Fxa[ia] * self.xb[jb]).sum(-1) ** 2
        return num / (self.den_a[ia] + self.den_b[jb]).clamp_min(1e-12)


def _hartley(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mean = points.mean(0)
    dist = (points - mean).norm(dim=1).mean().clamp_min(1e-9)
    s = np.sqrt(2.0) / dist
    T = torch.zeros(3, 3, dtype=points.dtype, device=points.device)
    T[0, 0] = T[1, 1] = s
    T[0, 2], T[1, 2] = -s * mean[0], -s * mean[1]
    T[2, 2] = 1.0
    return homogeneous(points) @ T.T, T


def eight_point(pa: torch.Tensor, pb: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Normalised (Hartley) 8-point algorithm, optionally weighted, rank 2 enforced."""
    if pa.shape[0] < MIN_POINTS:
        raise ValueError(f"the 8-point algorithm needs at least {MIN_POINTS} matches, got {pa.shape[0]}")
    pa64, pb64 = pa.double(), pb.double()
    xa, Ta = _hartley(pa64)
    xb, Tb = _hartley(pb64)
    A = (xb[:, :, None] * xa[:, None, :]).reshape(-1, 9)
    if weights is not None:
        A = A * weights.double()[:, None]
    _, _, Vh = torch.linalg.svd(A)
    F = Vh[-1].reshape(3, 3)
    U, S, Vh = torch.linalg.svd(F)
    S = torch.diag(torch.stack([S[0], S[1], torch.zeros_like(S[2])]))
    F = Tb.T @ (U @ S @ Vh) @ Ta
    return (F / F.norm()).to(pa.dtype)


def estimate_fundamental(
    pa: torch.Tensor,
    pb: torch.Tensor,
    method: str = "magsac",
    threshold: float = 1.0,
    confidence: float = 0.9999,
    max_iters: int = 10000,
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """F with x_b^T F x_a = 0 and the inlier mask, or (None, None) with fewer than 8 matches.

    ``magsac`` wraps OpenCV's USAC MAGSAC++ around the minimal solver and finishes with a
    least-squares fit on the inliers; ``torch`` is :mod:`geomatch.epipolar.robust_f` on the tensors' own
    device (no host round trip); ``auto`` is ``torch`` for CUDA tensors and ``magsac`` otherwise;
    ``8point`` is the plain normalised 8-point fit on all matches.
    """
    n = pa.shape[0]
    if n < MIN_POINTS:
        return None, None
    if method == "auto":
        method = "torch" if pa.device.type == "cuda" else "magsac"
    if method == "torch":
        from .robust_f import ransac_fundamental

        return ransac_fundamental(pa, pb, threshold)
    if method == "8point":
        return eight_point(pa, pb), torch.ones(n, dtype=torch.bool, device=pa.device)
    if method != "magsac":
        raise ValueError(f"unknown fundamental-matrix estimator {method!r} (auto, magsac, torch, 8point)")
    a = pa.detach().double().cpu().numpy()
    b = pb.detach().double().cpu().numpy()
    try:
        F, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold, confidence, max_iters)
    except cv2.error:  # OpenCV asserts on some degenerate inputs (all points on a line, duplicates)
        F, mask = None, None
    if F is None or F.shape != (3, 3) or mask is None or int(mask.sum()) < MIN_POINTS:
        log.debug("MAGSAC failed on %d matches; falling back to the 8-point fit", n)
        return eight_point(pa, pb), torch.ones(n, dtype=torch.bool, device=pa.device)
    Ft = torch.from_numpy(F / np.linalg.norm(F)).to(device=pa.device, dtype=pa.dtype)
    return Ft, torch.from_numpy(mask.ravel() > 0).to(pa.device)


def skew(t: np.ndarray) -> np.ndarray:
    """[t]x, the cross product as a matrix: E = [t]x R is the essential matrix of a relative pose
    (R, t), which is how two posed cameras are held to their pair's matches."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]], np.float64)


def scale_fundamental(fundamental: np.ndarray, to_a: np.ndarray, to_b: np.ndarray) -> np.ndarray:
    """F in new frames, given 3x3 maps ``to_a``/``to_b`` from the new frames into F's frames."""
    F = to_b.T @ fundamental @ to_a
    return F / np.linalg.norm(F)


def fundamental_from_matches(pa: np.ndarray, pb: np.ndarray, threshold: float = 1.0) -> np.ndarray:
    """MAGSAC++ F of numpy matches (x_b^T F x_a = 0); zeros when fewer than 8 matches."""
    if len(pa) < MIN_POINTS:
        return np.zeros((3, 3))
    F, _ = estimate_fundamental(
        torch.from_numpy(np.asarray(pa, np.float64)),
        torch.from_numpy(np.asarray(pb, np.float64)),
        "magsac",
        threshold,
    )
    return np.zeros((3, 3)) if F is None else F.double().numpy()
