"""Coarse-to-fine refinement by correlation in a small window (LoFTR's fine stage, training-free).

For a coarse match (cell i in A, cell j in B) the point in A is the detector's strongest
response inside cell i (a repeatable, well-localised spot, so the same pixel comes back in
every pair and tracks get long), or the cell centre when there is no heatmap. Its fine
descriptor is correlated with every pixel of a (2r+1)^2 window centred on cell j in B; the
correlation is turned into a distribution by a softmax at a low temperature, optionally
multiplied by an epipolar prior exp(-d_sampson / (2 sigma^2)) under the optimizer's F, and the
point in B is the expectation over the 3x3 neighbourhood of the distribution's peak, which
gives sub-pixel precision without the centre bias of an expectation over the whole window.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..epipolar.geometry import sampson_distance
from .base import Refined


@dataclass(frozen=True)
class RefineOptions:
    radius: int = 7  # window (2r+1)^2 px at the network-input resolution: the 8 px cell +- 3.5 px
    temperature: float = 0.02
    epipolar_sigma: float | None = 2.0  # px; None switches the epipolar prior off
    select_in_cell: bool = True


def points_in_cells(
    heatmap: torch.Tensor | None, idx: torch.Tensor, grid_w: int, stride: int
) -> torch.Tensor:
    """The integer pixel of the strongest heatmap response in each cell ``idx`` (row-major ids)."""
    rows, cols = idx // grid_w, idx % grid_w
    if heatmap is None:
        off = stride // 2
        return torch.stack([cols * stride + off, rows * stride + off], 1).float()
    gh = heatmap.shape[0] // stride
    cells = heatmap[: gh * stride, : grid_w * stride].reshape(gh, stride, grid_w, stride)
    cells = cells.permute(0, 2, 1, 3).reshape(gh * grid_w, stride * stride)
    local = cells[idx].argmax(dim=1)
    return torch.stack([cols * stride + local % stride, rows * stride + local // stride], 1).float()


def correlate_window(
    fine_a: torch.Tensor,
    fine_b: torch.Tensor,
    points_a: torch.Tensor,
    centres_b: torch.Tensor,
    opts: RefineOptions,
    fundamental: torch.Tensor | None = None,
) -> Refined:
    """Sub-pixel points in B for integer ``points_a``; fine maps are (C, H, W) L2-normalised."""
    k = points_a.shape[0]
    dev = fine_a.device
    if k == 0:
        return Refined(points_a, centres_b, torch.empty(0, device=dev))
    _, h, w = fine_b.shape
    r = opts.radius
    side = 2 * r + 1
    xa, ya = points_a[:, 0].long(), points_a[:, 1].long()
    desc_a = fine_a[:, ya, xa].T  # (K, C)
    base = centres_b.round().long()
    off = torch.arange(-r, r + 1, device=dev)
    qy = base[:, 1, None, None] + off[None, :, None]  # (K, side, 1)
    qx = base[:, 0, None, None] + off[None, None, :]  # (K, 1, side)
    qy, qx = torch.broadcast_tensors(qy, qx)
    inside = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
    desc_b = fine_b[:, qy.clamp(0, h - 1), qx.clamp(0, w - 1)]  # (C, K, side, side)
    sim = torch.einsum("kc,ckyx->kyx", desc_a.float(), desc_b.float())
    logits = sim / opts.temperature
    if fundamental is not None and opts.epipolar_sigma is not None:
        q = torch.stack([qx, qy], -1).reshape(-1, 2).float()
        pa = points_a[:, None, :].expand(k, side * side, 2).reshape(-1, 2)
        d = sampson_distance(fundamental, pa, q).reshape(k, side, side)
        logits = logits - d / (2 * opts.epipolar_sigma**2)
    logits = logits.masked_fill(~inside, float("-inf"))
    prob = torch.softmax(logits.reshape(k, -1), dim=1).reshape(k, side, side)
    peak = prob.reshape(k, -1).argmax(dim=1)
    py, px = peak // side, peak % side
    # 3x3 expectation around the peak (clamped inside the window)
    cy, cx = py.clamp(1, side - 2), px.clamp(1, side - 2)
    n3 = torch.arange(-1, 2, device=dev)
    ny = cy[:, None, None] + n3[None, :, None]
    nx = cx[:, None, None] + n3[None, None, :]
    ny, nx = torch.broadcast_tensors(ny, nx)
    kk = torch.arange(k, device=dev)[:, None, None].expand_as(ny)
    p3 = prob[kk, ny, nx]
    mass = p3.sum(dim=(1, 2)).clamp_min(1e-12)
    ey = (p3 * ny).sum(dim=(1, 2)) / mass
    ex = (p3 * nx).sum(dim=(1, 2)) / mass
    points_b = torch.stack([base[:, 0] - r + ex, base[:, 1] - r + ey], 1)
    return Refined(points_a.float(), points_b, mass.clamp(0, 1))
