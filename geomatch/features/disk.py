"""DISK (kornia architecture, weights from the installed package): heatmap and dense descriptors."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.feature import DISK
from kornia.feature.disk.detector import heatmap_to_keypoints

from .base import DenseFeatures, Extractor, ImageFeatures, SparseFeatures
from .disk_strips import disk_maps
from .pooling import FINE_DTYPE
from .weights import load_state_dict


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
        # the U-Net's full-resolution block in row strips: same maps, a fraction of the peak memory
        maps = disk_maps(self.net, image, self.stride, FINE_DTYPE)
        kp = heatmap_to_keypoints(maps.heatmap, n=self.max_keypoints, window_size=self.nms_window)[0]
        x, y = kp.xys.T
        # a keypoint's descriptor is its pixel's normalised descriptor, read from the fine map
        descriptors = F.normalize(maps.fine[:, y, x].T.float(), dim=-1)
        h, w = image.shape[-2:]
        sparse = SparseFeatures(kp.xys.float(), descriptors, kp.detection_logp.float(), (w, h))
        if not dense:
            return ImageFeatures(sparse=sparse)
        dense_maps = DenseFeatures(
            coarse=maps.coarse,
            fine=maps.fine,
            stride=self.stride,
            image_size=(w, h),
            heatmap=maps.heatmap[0, 0],
        )
        return ImageFeatures(sparse=sparse, dense=dense_maps)
