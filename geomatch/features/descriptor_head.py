"""Dense head for backbones whose dense branch is a per-pixel descriptor map (DISK, ALIKED)."""

from __future__ import annotations

import torch

from .base import CoarsePair, DenseFeatures, DenseHead, Refined
from .pooling import cell_centres
from .refine import RefineOptions, correlate_window, points_in_cells


class DescriptorHead(DenseHead):
    """Coarse: pooled descriptors, dual-softmax at ``temperature``. Fine: window correlation."""

    def __init__(self, name: str, temperature: float = 0.02, refine: RefineOptions | None = None) -> None:
        self.name = name
        self.temperature = temperature
        self.refine_opts = refine or RefineOptions()

    def coarse_pair(self, a: DenseFeatures, b: DenseFeatures) -> CoarsePair:
        ca, cb = a.coarse, b.coarse
        ga = cell_centres(ca.shape[1], ca.shape[2], a.stride, ca.device)
        gb = cell_centres(cb.shape[1], cb.shape[2], b.stride, cb.device)
        fa = ca.flatten(1).T.contiguous()
        fb = cb.flatten(1).T.contiguous()
        return CoarsePair(fa, fb, ga, gb, self.temperature)

    def refine(
        self,
        a: DenseFeatures,
        b: DenseFeatures,
        pair: CoarsePair,
        idx_a: torch.Tensor,
        idx_b: torch.Tensor,
        fundamental: torch.Tensor | None,
    ) -> Refined:
        opts = self.refine_opts
        heat = a.heatmap if opts.select_in_cell else None
        pts_a = points_in_cells(heat, idx_a, a.coarse.shape[2], a.stride)
        if a.fine is None or b.fine is None:
            conf = torch.ones(idx_a.shape[0], device=pts_a.device)
            return Refined(pts_a, pair.grid_b[idx_b], conf)
        return correlate_window(a.fine, b.fine, pts_a, pair.grid_b[idx_b], opts, fundamental)
