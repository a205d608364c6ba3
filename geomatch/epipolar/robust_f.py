"""A fundamental matrix robust to outliers, computed on the tensors' device.

Why: the optimizer fits F once per round. OpenCV's MAGSAC++ runs on the host, so on a GPU every
round would copy the matches to the host and wait for the device, and those waits would dominate
a ``geo`` pair's optimizer. Here every step is a batched tensor operation with
no host synchronisation (no ``.item()``, no data-dependent shapes):

1. ``hypotheses`` minimal samples of 8 matches, drawn by a seeded generator on the device;
2. each sample's normalised 8-point F (one batched SVD), rank 2 enforced (a second batched SVD);
3. every hypothesis scored on every match by the truncated Sampson cost (MSAC);
4. local optimisation of the best: ``lo_steps`` rounds of weighted 8-point on all matches with
   Tukey weights that reach 0 at ``lo_scale`` times the threshold (a smooth stand-in for
   MAGSAC's marginalisation over thresholds: weights cut at the threshold itself leave the noisy
   true matches out and the fit about twice as far from the truth), each kept only while the
   truncated cost at that wider scale falls.

On the CPU OpenCV's MAGSAC++ stays the default (``f_estimator="auto"``): this module is the
CUDA path. Its accuracy against MAGSAC++ is a test (tests/test_robust_f.py).
"""

from __future__ import annotations

import torch

MIN_POINTS = 8  # geometry.MIN_POINTS; not imported, geometry dispatches to this module


def homogeneous(points: torch.Tensor) -> torch.Tensor:
    return torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)


def _normalise(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Hartley normalisation without host synchronisation: (homogeneous normalised points, T)."""
    mean = points.mean(0)
    scale = (2.0**0.5) / (points - mean).norm(dim=1).mean().clamp_min(1e-9)
    zero, one = torch.zeros_like(scale), torch.ones_like(scale)
    T = torch.stack(
        [
            torch.stack([scale, zero, -scale * mean[0]]),
            torch.stack([zero, scale, -scale * mean[1]]),
            torch.stack([zero, zero, one]),
        ]
    )
    return homogeneous(points) @ T.T, T


def _solve(xa: torch.Tensor, xb: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Batched (weighted) 8-point on normalised points: xa, xb (B, K, 3) -> F (B, 3, 3), rank 2."""
    A = (xb[..., :, None] * xa[..., None, :]).reshape(*xa.shape[:-1], 9)
    if weights is not None:
        A = A * weights[..., None]
    # the null vector of A: the eigenvector of A^T A with the smallest eigenvalue (9 x 9, batched)
    _, vecs = torch.linalg.eigh(A.transpose(-1, -2) @ A)
    F = vecs[..., 0].reshape(*A.shape[:-2], 3, 3)
    U, S, Vh = torch.linalg.svd(F)
    S = torch.stack([S[..., 0], S[..., 1], torch.zeros_like(S[..., 2])], -1)
    return U @ torch.diag_embed(S) @ Vh


def _sampson(F: torch.Tensor, xa: torch.Tensor, xb: torch.Tensor) -> torch.Tensor:
    """Squared Sampson distances (B, N) of N homogeneous matches under B matrices F (B, 3, 3)."""
    Fxa = xa @ F.transpose(-1, -2)  # (B, N, 3)
    Ftxb = xb @ F  # (B, N, 3)
    num = (xb * Fxa).sum(-1) ** 2
    den = Fxa[..., 0] ** 2 + Fxa[..., 1] ** 2 + Ftxb[..., 0] ** 2 + Ftxb[..., 1] ** 2
    return num / den.clamp_min(1e-12)


def ransac_fundamental(
    pa: torch.Tensor,
    pb: torch.Tensor,
    threshold: float = 1.0,
    hypotheses: int = 1024,
    lo_steps: int = 4,
    lo_scale: float = 3.0,
    seed: int = 0,
    chunk: int = 256,
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(F with x_b^T F x_a = 0, unit norm; inlier mask at ``threshold`` px), or (None, None) with
    fewer than 8 matches. Deterministic for a given ``seed`` and device."""
    n = pa.shape[0]
    if n < MIN_POINTS:
        return None, None
    dtype = torch.float64 if pa.device.type == "cpu" else torch.float32
    a, b = pa.to(dtype), pb.to(dtype)
    xa, Ta = _normalise(a)
    xb, Tb = _normalise(b)
    ha, hb = homogeneous(a), homogeneous(b)
    thr2 = float(threshold) ** 2
    gen = torch.Generator(device=pa.device)
    gen.manual_seed(seed)
    # 8 distinct indices per sample: the first 8 of a random permutation's keys
    keys = torch.rand(hypotheses, n, generator=gen, device=pa.device)
    idx = keys.topk(MIN_POINTS, dim=1).indices  # (H, 8)
    best_F = None
    best_cost = None
    for s in range(0, hypotheses, chunk):
        sel = idx[s : s + chunk]
        Fn = _solve(xa[sel], xb[sel])  # (c, 3, 3) in normalised coordinates
        F = Tb.T @ Fn @ Ta  # to pixels
        d = _sampson(F, ha[None], hb[None])  # (c, N)
        cost = d.clamp(max=thr2).sum(1)
        cost = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, float("inf")))
        k = cost.argmin()
        if best_F is None or best_cost is None:
            best_F, best_cost = F[k], cost[k]
        else:
            better = cost[k] < best_cost
            best_F = torch.where(better, F[k], best_F)
            best_cost = torch.where(better, cost[k], best_cost)
    assert best_F is not None
    wide2 = thr2 * lo_scale**2
    lo_cost = _sampson(best_F[None], ha[None], hb[None])[0].clamp(max=wide2).sum()
    for _ in range(lo_steps):
        d = _sampson(best_F[None], ha[None], hb[None])[0]
        w = (1.0 - d / wide2).clamp(min=0.0) ** 2
        F = Tb.T @ _solve(xa[None], xb[None], w[None])[0] @ Ta
        cost = _sampson(F[None], ha[None], hb[None])[0].clamp(max=wide2).sum()
        better = torch.isfinite(cost) & (cost < lo_cost)
        best_F = torch.where(better, F, best_F)
        lo_cost = torch.where(better, cost, lo_cost)
    mask = _sampson(best_F[None], ha[None], hb[None])[0] <= thr2
    F = best_F / best_F.norm()
    return F.to(pa.dtype), mask
