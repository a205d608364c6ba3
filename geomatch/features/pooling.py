"""From full-resolution descriptor maps to the coarse 1/8 grid."""

from __future__ import annotations

import torch
import torch.nn.functional as F

# Full-resolution fine maps are stored in half precision (they are the bulk of a cached image's
# memory); correlation upcasts the few windows it reads.
FINE_DTYPE = torch.float16


def pool_to_grid(fmap: torch.Tensor, stride: int) -> torch.Tensor:
    """Average-pool (C, H, W) over stride x stride cells and L2-normalise: (C, H // s, W // s)."""
    pooled = F.avg_pool2d(fmap[None].float(), kernel_size=stride, stride=stride)[0]
    return F.normalize(pooled, dim=0)


def cell_centres(
    h: int, w: int, stride: int, device: torch.device, offset: float | None = None
) -> torch.Tensor:
    """Centres of an h x w grid of stride-pixel cells, row-major, in pixel-centre-integer coordinates."""
    off = (stride - 1) / 2.0 if offset is None else offset
    ys, xs = torch.meshgrid(
        torch.arange(h, device=device, dtype=torch.float32),
        torch.arange(w, device=device, dtype=torch.float32),
        indexing="ij",
    )
    return torch.stack([xs.flatten() * stride + off, ys.flatten() * stride + off], dim=1)
