"""DISK (kornia architecture, weights from the installed package): heatmap and dense descriptors."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.feature import DISK
from kornia.feature.disk.detector import heatmap_to_keypoints

from ..weights import load_state_dict
from .base import DenseFeatures, Extractor, ImageFeatures, SparseFeatures
from .pooling import FINE_DTYPE, pool_to_grid


class DiskExtractor(Extractor):
    """One U-Net pass serves both branches: keypoints from the heatmap, the dense map for matching."""

    name = "disk"
    provides_sparse = True
    provides_dense = True

    def __init__(
        self,
        device: torch.device,
        max_keypoints: int = 2048,
        nms_window: int = 5,
        stride: int = 8,
        weights: str | None = None,
    ) -> None:
        net = DISK()
        state = load_state_dict("disk-depth-save.pth", weights)
        net.load_state_dict(state.get("extractor", state))
        self.net = net.eval().to(device)
        self.max_keypoints = max_keypoints
        self.nms_window = nms_window
        self.stride = stride

    @torch.inference_mode()
    def extract(self, image: torch.Tensor, dense: bool = True) -> ImageFeatures:
        heatmaps, descriptors = self.net.heatmap_and_dense_descriptors(image)
        kp = heatmap_to_keypoints(heatmaps, n=self.max_keypoints, window_size=self.nms_window)[0]
        feats = kp.merge_with_descriptors(descriptors[0])
        h, w = image.shape[-2:]
        sparse = SparseFeatures(feats.keypoints.float(), feats.descriptors, feats.detection_scores, (w, h))
        if not dense:
            return ImageFeatures(sparse=sparse)
        maps = DenseFeatures(
            coarse=pool_to_grid(descriptors[0], self.stride),
            fine=F.normalize(descriptors[0], dim=0).to(FINE_DTYPE),
            stride=self.stride,
            image_size=(w, h),
            heatmap=heatmaps[0, 0],
        )
        return ImageFeatures(sparse=sparse, dense=maps)
