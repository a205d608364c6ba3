"""LightGlue (kornia architecture) with the checkpoints shipped in the installed package.

Attention runs through PyTorch's fused ``scaled_dot_product_attention`` on every device, in fp32.
kornia's ``flash=False`` switches the flash backend off process-wide (``enable_flash_sdp(False)``,
which on the CPU is the only fused kernel) and computes cross-attention with explicit einsums and
two softmaxes over the full N x M matrix. With the fused kernel allowed while LightGlue runs and
cross-attention as two fused calls, the same matches come out faster on the CPU
(bench/lightglue_pruning.py times it). ``match_batch`` runs several pairs a forward pass
(lightglue_batch.py).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import cast

import torch
import torch.nn.functional as F
from kornia.feature import LightGlue
from kornia.feature.lightglue import CrossBlock
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from .base import SparseFeatures, SparseMatch, SparseMatcher
from .lightglue_batch import DEFAULT_BUDGET_BYTES, forward_batch, plan_batches
from .weights import load_state_dict

CHECKPOINTS = {"aliked": "aliked_lightglue.pth", "disk": "disk_lightglue.pth"}


def rename_legacy_keys(state: dict[str, torch.Tensor], n_layers: int) -> dict[str, torch.Tensor]:
    """Released checkpoints name layers ``self_attn.{i}``; kornia nests them in ``transformers.{i}``."""
    out = dict(state)
    for i in range(n_layers):
        for old, new in (
            (f"self_attn.{i}.", f"transformers.{i}.self_attn."),
            (f"cross_attn.{i}.", f"transformers.{i}.cross_attn."),
        ):
            out = {(new + k[len(old) :] if k.startswith(old) else k): v for k, v in out.items()}
    return out


# every backend allowed: PyTorch picks the fastest that supports the inputs (flash on the CPU)
_BACKENDS = [
    SDPBackend.FLASH_ATTENTION,
    SDPBackend.EFFICIENT_ATTENTION,
    SDPBackend.CUDNN_ATTENTION,
    SDPBackend.MATH,
]


class FusedCrossBlock(nn.Module):
    """kornia's ``CrossBlock`` with each direction's attention as one fused call: the same
    weights and arithmetic as its bidirectional einsum path (softmax(q0 k1^T / sqrt(d)) v1 and
    the reverse), without materialising the N x M similarity and its transposed copy."""

    def __init__(self, block: CrossBlock) -> None:
        super().__init__()
        self.block = block

    def forward(
        self, x0: torch.Tensor, x1: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        b = self.block
        qk0, qk1 = b.map_(b.to_qk, x0, x1)
        v0, v1 = b.map_(b.to_v, x0, x1)
        qk0, qk1, v0, v1 = (t.unflatten(-1, (b.heads, -1)).transpose(1, 2) for t in (qk0, qk1, v0, v1))
        mask_t = mask.transpose(-1, -2) if mask is not None else None
        m0 = F.scaled_dot_product_attention(qk0, qk1, v1, attn_mask=mask)
        m1 = F.scaled_dot_product_attention(qk1, qk0, v0, attn_mask=mask_t)
        if mask is not None:
            m0, m1 = m0.nan_to_num(), m1.nan_to_num()
        m0, m1 = b.map_(lambda t: t.transpose(1, 2).flatten(start_dim=-2), m0, m1)
        m0, m1 = b.map_(b.to_out, m0, m1)
        return x0 + b.ffn(torch.cat([x0, m0], -1)), x1 + b.ffn(torch.cat([x1, m1], -1))


class LightGlueMatcher(SparseMatcher):
    def __init__(
        self,
        features: str,
        device: torch.device,
        filter_threshold: float = 0.1,
        depth_confidence: float = -1.0,
        width_confidence: float = -1.0,
        weights: str | None = None,
        fused: bool = True,
    ) -> None:
        """``fused`` False keeps kornia's own attention (for the side-by-side bench and test)."""
        if features not in CHECKPOINTS:
            raise ValueError(f"no LightGlue weights for {features!r}; choose from {sorted(CHECKPOINTS)}")
        self.name = f"{features}+lightglue"
        net = LightGlue(
            None,  # type: ignore[arg-type]  # kornia annotates str, and takes None: no checkpoint download
            input_dim=128,
            descriptor_dim=256,
            flash=False,
            filter_threshold=filter_threshold,
            depth_confidence=depth_confidence,
            width_confidence=width_confidence,
        )
        state = rename_legacy_keys(load_state_dict(CHECKPOINTS[features], weights), net.conf.n_layers)
        result = net.load_state_dict(state, strict=False)
        params = dict(net.named_parameters())
        missing = [k for k in result.missing_keys if k in params]
        if missing:
            raise ValueError(f"LightGlue checkpoint for {features} lacks learned weights: {missing[:5]}")
        self.fused = fused
        if fused:
            for layer in net.transformers:
                # a ModuleList's items and their attributes are typed as any Module (or Tensor)
                layer.cross_attn = FusedCrossBlock(cast(CrossBlock, layer.cross_attn))
        self.net = net.eval().to(device)

    @torch.inference_mode()
    def match(self, a: SparseFeatures, b: SparseFeatures) -> SparseMatch:
        dev = a.keypoints.device
        if a.keypoints.shape[0] == 0 or b.keypoints.shape[0] == 0:
            return _no_matches(dev)
        data = {
            "image0": {
                "keypoints": a.keypoints[None],
                "descriptors": a.descriptors[None],
                "image_size": torch.tensor([a.image_size], device=dev, dtype=torch.float32),
            },
            "image1": {
                "keypoints": b.keypoints[None],
                "descriptors": b.descriptors[None],
                "image_size": torch.tensor([b.image_size], device=dev, dtype=torch.float32),
            },
        }
        with sdpa_kernel(_BACKENDS) if self.fused else contextlib.nullcontext():
            out = self.net(data)
        matches, scores = out["matches"][0], out["scores"][0]
        # with point pruning the assignment covers only the points that survived: not a P_c
        assignment = None
        if self.net.conf.width_confidence <= 0 and "log_assignment" in out:
            na, nb = a.keypoints.shape[0], b.keypoints.shape[0]
            la = out["log_assignment"][0]
            if la.shape == (na + 1, nb + 1):
                assignment = la[:na, :nb].float().exp()
        return SparseMatch(matches[:, 0], matches[:, 1], scores.float(), assignment)

    @property
    def batches(self) -> bool:
        """Whether pairs run batched: only the fixed-depth, fixed-width network does (early exit
        ends a batch at one layer for all its pairs; pruning keeps different points per pair)."""
        return self.net.conf.depth_confidence <= 0 and self.net.conf.width_confidence <= 0

    @torch.inference_mode()
    def match_batch(
        self, pairs: Sequence[tuple[SparseFeatures, SparseFeatures]], budget_bytes: int = DEFAULT_BUDGET_BYTES
    ) -> list[SparseMatch]:
        """``match`` of each pair, in order, several pairs a forward pass.

        The pairs are grouped by size into batches whose padded attention fits ``budget_bytes``
        (``lightglue_batch.plan_batches``) and each batch runs padded and masked
        (``lightglue_batch.forward_batch``): a pair's matches, scores and soft assignment are
        those ``match`` gives it, up to float rounding. With adaptive depth or width
        (``depth_confidence`` or ``width_confidence`` > 0) the pairs run one at a time through
        ``match``; a pair with no keypoints on a side has no matches, as there."""
        if not self.batches:
            return [self.match(a, b) for a, b in pairs]
        out: dict[int, SparseMatch] = {}
        live: list[int] = []
        for i, (a, b) in enumerate(pairs):
            if a.keypoints.shape[0] == 0 or b.keypoints.shape[0] == 0:
                out[i] = _no_matches(a.keypoints.device)
            else:
                live.append(i)
        sizes = [(pairs[i][0].keypoints.shape[0], pairs[i][1].keypoints.shape[0]) for i in live]
        with sdpa_kernel(_BACKENDS) if self.fused else contextlib.nullcontext():
            for batch in plan_batches(sizes, self.net.conf.num_heads, budget_bytes):
                idx = [live[j] for j in batch]
                out.update(zip(idx, forward_batch(self.net, [pairs[i] for i in idx]), strict=True))
        return [out[i] for i in range(len(pairs))]


def _no_matches(device: torch.device) -> SparseMatch:
    empty = torch.empty(0, dtype=torch.long, device=device)
    return SparseMatch(empty, empty, torch.empty(0, device=device))
