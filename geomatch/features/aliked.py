"""ALIKED (kornia architecture, weights from the installed package): keypoints and a dense map."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.feature import ALIKED

from .aliked_strips import aliked_maps, sddh_descriptors
from .base import DenseFeatures, Extractor, ImageFeatures, SparseFeatures
from .pooling import FINE_DTYPE, pool_to_grid
from .weights import load_state_dict


class AlikedExtractor(Extractor):
    """One pass gives both branches: keypoints + descriptors, and the 128-d dense feature map."""

    name = "aliked"
    provides_sparse = True
    provides_dense = True

    def __init__(
        self,
        device: torch.device,
        model: str = "aliked-n16",
        max_keypoints: int = 2048,
        detection_threshold: float = 0.0,
        stride: int = 8,
        weights: str | None = None,
    ) -> None:
        net = ALIKED(model, max_num_keypoints=max_keypoints, detection_threshold=detection_threshold)
        missing = net.load_state_dict(load_state_dict(f"{model}.pth", weights), strict=False).missing_keys
        if any(not k.startswith("dkd.") for k in missing):  # dkd holds derived buffers only
            raise ValueError(f"{model} checkpoint is missing learned weights: {missing[:5]}")
        self.net = net.eval().to(device)
        self.stride = stride

    @torch.inference_mode()
    def extract(self, image: torch.Tensor, dense: bool = True) -> ImageFeatures:
        net = self.net
        # the full-resolution head in row strips: same maps, about half the peak memory
        feature_map, score_map = aliked_maps(net, image)
        kpts_n, scores, _ = net.dkd(score_map)
        descriptors = sddh_descriptors(net.desc_head, feature_map, kpts_n[0])
        h, w = image.shape[-2:]
        wh = torch.tensor([w - 1, h - 1], device=image.device, dtype=torch.float32)
        keypoints = wh * (kpts_n[0] + 1) / 2.0  # align_corners frame: pixel centres at integers
        sparse = SparseFeatures(keypoints, F.normalize(descriptors, dim=-1), scores[0], (w, h))
        if not dense:
            return ImageFeatures(sparse=sparse)
        fmap = feature_map[0]
        maps = DenseFeatures(
            coarse=pool_to_grid(fmap, self.stride),
            fine=fmap.to(FINE_DTYPE),
            stride=self.stride,
            image_size=(w, h),
            heatmap=score_map[0, 0],
        )
        return ImageFeatures(sparse=sparse, dense=maps)
