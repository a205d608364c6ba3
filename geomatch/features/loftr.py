"""LoFTR (kornia architecture) from a checkpoint file: no LoFTR weights ship in any package here.

The coarse tokens after LoFTR's coarse transformer (pair-dependent: it cross-attends) feed the
same geometry-aware optimizer as every other dense backbone; LoFTR's own learned fine stage
refines the selected coarse matches. Per-image CNN features are extracted once and cached.
"""

from __future__ import annotations

import os
from typing import Any

import torch
import torch.nn.functional as F
from kornia.feature import LoFTR

from .base import CoarsePair, DenseFeatures, DenseHead, Extractor, ImageFeatures, Refined
from .pooling import cell_centres
from .weights import weight_path

DEFAULT_FILE = "loftr_outdoor.ckpt"
ENV_FILE = "GEOMATCH_LOFTR_WEIGHTS"


def load_loftr(weights: str | os.PathLike[str] | None = None) -> LoFTR:
    """Build LoFTR and load a checkpoint: ``weights``, $GEOMATCH_LOFTR_WEIGHTS, or the weights folder."""
    explicit = weights if weights is not None else (os.environ.get(ENV_FILE) or None)  # "" = unset
    path = weight_path(DEFAULT_FILE, explicit)
    ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    state = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        raise ValueError(f"{path} does not hold a LoFTR state dict")
    net = LoFTR(pretrained=None)
    net.load_state_dict(state)
    return net.eval()


class LoftrExtractor(Extractor):
    name = "loftr"
    provides_dense = True

    def __init__(self, device: torch.device, weights: str | None = None) -> None:
        self.net = load_loftr(weights).to(device)
        self.stride = int(self.net.config["resolution"][0])

    @torch.inference_mode()
    def extract(self, image: torch.Tensor, dense: bool = True) -> ImageFeatures:
        gray = (0.299 * image[:, 0] + 0.587 * image[:, 1] + 0.114 * image[:, 2])[:, None]
        feats = self.net.extract_features(gray)
        h, w = image.shape[-2:]
        maps = DenseFeatures(
            coarse=feats["coarse"][0], fine=feats["fine"][0], stride=self.stride, image_size=(w, h)
        )
        return ImageFeatures(dense=maps)


class LoftrHead(DenseHead):
    name = "loftr"

    def __init__(self, extractor: LoftrExtractor) -> None:
        self.net = extractor.net
        self.temperature = float(self.net.config["match_coarse"]["dsmax_temperature"])

    @torch.inference_mode()
    def coarse_pair(self, a: DenseFeatures, b: DenseFeatures) -> CoarsePair:
        t0 = a.coarse.flatten(1).T[None].contiguous()
        t1 = b.coarse.flatten(1).T[None].contiguous()
        t0, t1 = self.net.loftr_coarse(t0, t1, None, None)
        c = t0.shape[-1]
        # LoFTR's kornia frame: coarse cell (x, y) sits on reference pixel 8x, i.e. 8x - 0.5 here
        ga = cell_centres(a.coarse.shape[1], a.coarse.shape[2], a.stride, t0.device, offset=-0.5)
        gb = cell_centres(b.coarse.shape[1], b.coarse.shape[2], b.stride, t1.device, offset=-0.5)
        return CoarsePair(t0[0] / c**0.5, t1[0] / c**0.5, ga, gb, self.temperature, {"tokens": (t0, t1)})

    @torch.inference_mode()
    def refine(
        self,
        a: DenseFeatures,
        b: DenseFeatures,
        pair: CoarsePair,
        idx_a: torch.Tensor,
        idx_b: torch.Tensor,
        fundamental: torch.Tensor | None,
    ) -> Refined:
        stride_c, stride_f = (int(s) for s in self.net.config["resolution"])
        t0, t1 = pair.context["tokens"]
        if a.fine is None or b.fine is None:
            raise ValueError("LoFTR's fine stage needs both images' fine maps (LoftrExtractor keeps them)")
        data: dict[str, Any] = {  # kornia's fine stage reads its inputs here and writes its answer
            "b_ids": torch.zeros_like(idx_a),
            "i_ids": idx_a,
            "j_ids": idx_b,
            "stride_c": stride_c,
            "stride_f": stride_f,
            "mkpts0_c": pair.grid_a[idx_a] + 0.5,
            "mkpts1_c": pair.grid_b[idx_b] + 0.5,
            "mconf": torch.ones(idx_a.shape[0], device=idx_a.device),
        }
        f0, f1 = self.net.fine_preprocess(a.fine[None], b.fine[None], t0, t1, data)
        if f0.shape[0]:
            f0, f1 = self.net.loftr_fine(f0, f1)
        self.net.fine_matching(f0, f1, data)
        std = data["expec_f"][:, 2] if data["expec_f"].shape[0] else torch.zeros(0, device=idx_a.device)
        conf = F.relu(1.0 - std)
        return Refined(data["mkpts0_f"] - 0.5, data["mkpts1_f"] - 0.5, conf)
