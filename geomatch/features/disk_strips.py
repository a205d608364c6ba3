"""DISK's U-Net with its full-resolution last block run in row strips.

Why: the last up-block works at the input's full resolution on 80 channels in and 129 out, and
PyTorch materialises its upsampled input, the concatenation, the instance norm, the PReLU and the
convolution's output whole: for one image, the largest single term of a worker's peak memory
(docs/benchmarks.md, "A worker's memory on a project"). Row strips give
the same numbers (the block is a per-channel affine map, a PReLU and a 5 x 5 convolution, so only
the instance norm's statistics are global, and those are accumulated over the strips first) while
holding one strip at a time, and the strip's output goes straight into what the matcher keeps: the
heatmap, the pooled coarse map and the normalised half-precision fine map. The raw 128-channel
full-resolution descriptor map never exists whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from kornia.feature import DISK

from .strips import row_strips, rows_through

STRIP_ROWS = 32  # a multiple of the coarse stride; small strips stay in cache, faster than whole maps


@dataclass
class DiskMaps:
    heatmap: torch.Tensor  # (1, 1, H, W) detector logits
    coarse: torch.Tensor  # (C, H / stride, W / stride) pooled, L2-normalised
    fine: torch.Tensor  # (C, H, W) L2-normalised per pixel, in ``fine_dtype``


def _upsample_rows(bot: torch.Tensor, r0: int, r1: int) -> torch.Tensor:
    """Rows [r0, r1) of ``interpolate(bot, scale_factor=2, bilinear, align_corners=False)``,
    computed from the few source rows they depend on (two spare rows each side make the clamping
    at the slice's edges irrelevant; at the image's edges it is the same clamping as the whole)."""
    h = bot.shape[-2]
    s0, s1 = max(0, r0 // 2 - 2), min(h, (r1 + 1) // 2 + 2)
    up = F.interpolate(bot[..., s0:s1, :], scale_factor=2, mode="bilinear", align_corners=False)
    return up[..., r0 - 2 * s0 : r1 - 2 * s0, :]


def _block_input(bot: torch.Tensor, hor: torch.Tensor, r0: int, r1: int) -> torch.Tensor:
    return torch.cat([_upsample_rows(bot, r0, r1), hor[..., r0:r1, :]], dim=1)


def disk_maps(
    net: DISK,
    image: torch.Tensor,
    stride: int,
    fine_dtype: torch.dtype = torch.float16,
    rows: int = STRIP_ROWS,
) -> DiskMaps:
    """The maps :class:`~geomatch.features.disk.DiskExtractor` keeps, for a (1, 3, H, W) image."""
    unet: Any = net.unet  # kornia types it as any Module; DISK() builds its Unet, read layer by layer
    if image.shape[0] != 1:
        raise ValueError("disk_maps takes one image at a time")
    if rows % stride:
        raise ValueError(f"strip rows ({rows}) must be a multiple of the stride ({stride})")
    features = [image]
    for layer in unet.path_down:
        features.append(layer(features[-1]))
    bot = features[-1]
    skips = features[-2::-1][: len(unet.path_up)]  # the input image is no skip
    for layer, f_hor in zip(unet.path_up[:-1], skips[:-1], strict=True):
        bot = layer(bot, f_hor)
    hor = skips[-1]
    del features, skips
    last = unet.path_up[-1]
    norm, gate, _, conv = last.conv  # InstanceNorm2d (no affine, no running stats), PReLU, -, Conv2d
    if not isinstance(norm, torch.nn.InstanceNorm2d) or norm.affine or norm.track_running_stats:
        raise TypeError("disk_maps expects DISK's U-Net: instance norm without affine or running stats")
    _, _, h, w = hor.shape

    # the instance norm's per-channel statistics over the whole block input: the skip's directly,
    # the upsampled part's from per-strip means and variances (combined exactly, in float64)
    hor_var, hor_mean = torch.var_mean(hor[0], dim=(1, 2), correction=0)
    means, variances, counts = [], [], []
    for r0, r1 in row_strips(h, rows):
        v, m = torch.var_mean(_upsample_rows(bot, r0, r1)[0], dim=(1, 2), correction=0)
        means.append(m.double())
        variances.append(v.double())
        counts.append(float(r1 - r0))
    weight = torch.tensor(counts, dtype=torch.float64, device=image.device)[:, None] / h
    m_strips, v_strips = torch.stack(means), torch.stack(variances)
    bot_mean = (weight * m_strips).sum(0)
    bot_var = (weight * (v_strips + (m_strips - bot_mean).square())).sum(0)
    mean = torch.cat([bot_mean.float(), hor_mean])
    var = torch.cat([bot_var.float(), hor_var])
    scale = (var + norm.eps).rsqrt().view(1, -1, 1, 1)
    shift = mean.view(1, -1, 1, 1)

    desc_dim = net.desc_dim
    heatmap = torch.empty(1, 1, h, w, device=image.device)
    coarse = torch.empty(desc_dim, h // stride, w // stride, device=image.device)
    fine = torch.empty(desc_dim, h, w, dtype=fine_dtype, device=image.device)
    layers = [lambda x: (x - shift) * scale, gate, conv]
    for r0, r1 in row_strips(h, rows):
        out = rows_through(layers, lambda a, b: _block_input(bot, hor, a, b), h, r0, r1)
        desc = out[0, :desc_dim]
        heatmap[0, 0, r0:r1] = out[0, desc_dim]
        coarse[:, r0 // stride : r1 // stride] = F.avg_pool2d(desc[None], stride, stride)[0]
        fine[:, r0:r1] = F.normalize(desc, dim=0).to(fine_dtype)
    return DiskMaps(heatmap, F.normalize(coarse, dim=0), fine)
