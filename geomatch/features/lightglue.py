"""LightGlue (kornia architecture) with the checkpoints shipped in the installed package."""

from __future__ import annotations

import torch
from kornia.feature import LightGlue

from ..weights import load_state_dict
from .base import SparseFeatures, SparseMatch, SparseMatcher

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


class LightGlueMatcher(SparseMatcher):
    def __init__(
        self,
        features: str,
        device: torch.device,
        filter_threshold: float = 0.1,
        depth_confidence: float = -1.0,
        width_confidence: float = -1.0,
        weights: str | None = None,
    ) -> None:
        if features not in CHECKPOINTS:
            raise ValueError(f"no LightGlue weights for {features!r}; choose from {sorted(CHECKPOINTS)}")
        self.name = f"{features}+lightglue"
        net = LightGlue(
            None,
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
        self.net = net.eval().to(device)

    @torch.inference_mode()
    def match(self, a: SparseFeatures, b: SparseFeatures) -> SparseMatch:
        dev = a.keypoints.device
        if a.keypoints.shape[0] == 0 or b.keypoints.shape[0] == 0:
            empty = torch.empty(0, dtype=torch.long, device=dev)
            return SparseMatch(empty, empty, torch.empty(0, device=dev))
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
