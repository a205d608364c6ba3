"""The row-strip forms of the backbones' full-resolution ends give the networks' own maps."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from kornia.feature.disk.detector import heatmap_to_keypoints
from torch import nn

from geomatch.features.aliked import AlikedExtractor
from geomatch.features.aliked_strips import aliked_maps, sddh_descriptors
from geomatch.features.disk import DiskExtractor
from geomatch.features.disk_strips import disk_maps
from geomatch.features.pooling import pool_to_grid
from geomatch.features.strips import row_strips, rows_through
from geomatch.synth.photos import photo

CPU = torch.device("cpu")


def _image(h: int, w: int) -> torch.Tensor:
    img = torch.from_numpy(photo("astronaut")[:h, :w].copy()).permute(2, 0, 1)[None].float() / 255
    assert img.shape[-2:] == (h, w)
    return img


@pytest.mark.unit
@pytest.mark.parametrize("rows", [1, 8, 13, 100])
def test_rows_through_equals_the_whole_stack(rows: int) -> None:
    torch.manual_seed(0)
    stack = nn.Sequential(
        nn.Conv2d(5, 6, 1),
        nn.SELU(),
        nn.Conv2d(6, 4, 3, padding=1),
        nn.PReLU(4),
        nn.Conv2d(4, 3, 5, padding="same"),
        nn.Conv2d(3, 2, 3, padding=2, dilation=2),
    ).eval()
    x = torch.randn(1, 5, 37, 21)
    with torch.inference_mode():
        whole = stack(x)
        parts = [
            rows_through(list(stack), lambda a, b: x[..., a:b, :], 37, r0, r1)
            for r0, r1 in row_strips(37, rows)
        ]
    assert torch.allclose(torch.cat(parts, dim=2), whole, atol=1e-5)


@pytest.mark.unit
def test_rows_through_refuses_strided_convolutions() -> None:
    with pytest.raises(ValueError, match="stride-1"):
        rows_through(
            [nn.Conv2d(1, 1, 3, stride=2, padding=1)], lambda a, b: torch.zeros(1, 1, b - a, 4), 8, 0, 8
        )


@pytest.mark.nets
@torch.inference_mode()
def test_disk_maps_equal_the_unet_outputs() -> None:
    ext = DiskExtractor(CPU)
    img = _image(176, 208)  # 11 and 13 coarse cells: strips end mid-image
    maps = disk_maps(ext.net, img, stride=8, rows=32)
    heat, desc = ext.net.heatmap_and_dense_descriptors(img)
    assert torch.allclose(maps.heatmap, heat, atol=1e-3 * heat.abs().max().item())
    assert torch.allclose(maps.coarse, pool_to_grid(desc[0], 8), atol=1e-4)
    assert torch.allclose(maps.fine.float(), F.normalize(desc[0], dim=0), atol=2e-3)
    # and so the keypoints and their descriptors, as the extractor returns them
    feats = ext.extract(img)
    ref = heatmap_to_keypoints(heat, n=ext.max_keypoints, window_size=ext.nms_window)[0]
    ref = ref.merge_with_descriptors(desc[0])
    assert torch.equal(feats.sparse.keypoints, ref.keypoints.float())
    assert torch.allclose(feats.sparse.descriptors, ref.descriptors, atol=2e-3)


@pytest.mark.nets
@torch.inference_mode()
@pytest.mark.parametrize("size", [(160, 224), (176, 208)])  # the second is padded to 32 inside ALIKED
def test_aliked_maps_equal_extract_dense_map(size: tuple[int, int]) -> None:
    net = AlikedExtractor(CPU).net
    img = _image(*size)
    fmap, score = aliked_maps(net, img, rows=24)
    ref_fmap, ref_score = net.extract_dense_map(img)
    assert fmap.shape == ref_fmap.shape and score.shape == ref_score.shape
    assert torch.allclose(fmap, ref_fmap, atol=1e-5)
    assert torch.allclose(score, ref_score, atol=1e-5)


@pytest.mark.nets
@torch.inference_mode()
@pytest.mark.parametrize("parts", [1, 2, 3])
def test_descriptors_sampled_in_parts_equal_the_deformable_head(parts: int) -> None:
    net = AlikedExtractor(CPU, max_keypoints=500).net
    img = _image(176, 208)
    fmap, score = aliked_maps(net, img)
    kpts, _, _ = net.dkd(score)
    assert len(kpts[0]) > 100
    ref, _ = net.desc_head(fmap, kpts)
    got = sddh_descriptors(net.desc_head, fmap, kpts[0], parts=parts)
    assert torch.equal(got, ref[0])  # the same samples, only spread over the cores
