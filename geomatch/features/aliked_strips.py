"""ALIKED's dense map and score map without its full-resolution transients.

Why: kornia's ``ALIKED.extract_dense_map`` keeps the four upsampled 32-channel maps, their
concatenation and the normalised copy alive at once, the largest transient of a worker whose
DISK runs in strips. Here the upsampled parts are written into one preallocated map, the score head
runs in row strips (:func:`~geomatch.features.strips.rows_through`) and the map is normalised in
place, strip by strip: same numbers, a lower peak (docs/benchmarks.md, "A worker's memory on a
project").
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.feature import ALIKED
from kornia.feature.aliked.aliked import SDDH, InputPadder

from .strips import row_strips, rows_through

STRIP_ROWS = 32


def aliked_maps(
    net: ALIKED, image: torch.Tensor, rows: int = STRIP_ROWS
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(feature_map, score_map)`` as ``net.extract_dense_map(image)`` returns them."""
    padder = InputPadder(image.shape[-2], image.shape[-1], 2**5)
    image = padder.pad(image)
    x1 = net.block1(image)
    x2 = net.block2(net.pool2(x1))
    x3 = net.block3(net.pool4(x2))
    x4 = net.block4(net.pool4(x3))
    b, _, h, w = image.shape
    q = net.conv1.out_channels
    fmap = torch.empty(b, 4 * q, h, w, device=image.device, dtype=x1.dtype)
    fmap[:, :q] = net.gate(net.conv1(x1))
    del x1
    parts = ((x2, net.conv2, net.upsample2), (x3, net.conv3, net.upsample8), (x4, net.conv4, net.upsample32))
    for i, (x, conv, up) in enumerate(parts, start=1):
        fmap[:, i * q : (i + 1) * q] = up(net.gate(conv(x)))
    del parts, x2, x3, x4
    score = torch.empty(b, 1, h, w, device=image.device, dtype=fmap.dtype)
    head = list(net.score_head)
    for r0, r1 in row_strips(h, rows):
        score[..., r0:r1, :] = torch.sigmoid(rows_through(head, lambda a, c: fmap[..., a:c, :], h, r0, r1))
    for r0, r1 in row_strips(h, rows):  # F.normalize's arithmetic, in place
        strip = fmap[..., r0:r1, :]
        strip.div_(strip.norm(p=2, dim=1, keepdim=True).clamp_min(1e-12))
    return padder.unpad(fmap), padder.unpad(score)


def sddh_descriptors(
    head: SDDH, feature_map: torch.Tensor, keypoints: torch.Tensor, parts: int = 2
) -> torch.Tensor:
    """``head(feature_map, [keypoints])[0][0]``: ALIKED's deformable descriptors of one image.

    Why not the head itself: on the CPU PyTorch's ``grid_sample`` spreads its work over the batch
    only, so sampling 4096 points x 16 positions from one 128-channel map runs on one core. Here
    the sample positions are cut into ``parts`` batch entries over the same map (expanded, not
    copied): every sample is computed as the head computes it, so the descriptors are equal, on
    ``parts`` cores."""
    x = feature_map[0]
    c, h, w = x.shape
    wh = torch.tensor([[w - 1, h - 1]], device=x.device, dtype=torch.promote_types(x.dtype, torch.float32))
    kpts_wh = (keypoints / 2 + 0.5) * wh
    n = len(keypoints)
    if head.kernel_size > 1:
        patch = head.get_patches_func(x, kpts_wh.long(), head.kernel_size)
    else:
        k = kpts_wh.long()
        patch = x[:, k[:, 1], k[:, 0]].permute(1, 0).reshape(n, c, 1, 1)
    offset = head.offset_conv(patch).clamp(-max(h, w) / 4.0, max(h, w) / 4.0)
    mask_w = None
    if head.mask:
        offset = offset[:, :, 0, 0].view(n, 3, head.n_pos).permute(0, 2, 1)
        mask_w = torch.sigmoid(offset[:, :, -1])
        offset = offset[:, :, :-1]
    else:
        offset = offset[:, :, 0, 0].view(n, 2, head.n_pos).permute(0, 2, 1)
    pos = 2.0 * (kpts_wh.unsqueeze(1) + offset) / wh[None] - 1
    grid = pos.reshape(n * head.n_pos, 2).to(x.dtype)
    total = n * head.n_pos
    parts = max(1, min(parts, total))
    if x.device.type != "cpu" or total % parts:
        parts = 1  # a GPU spreads one sample grid over its cores already
    sampled = F.grid_sample(
        x.unsqueeze(0).expand(parts, -1, -1, -1),
        grid.reshape(parts, total // parts, 1, 2),
        "bilinear",
        align_corners=True,
    )  # (parts, C, total / parts, 1)
    features = sampled.permute(1, 0, 2, 3).reshape(c, n, head.n_pos, 1).permute(1, 0, 2, 3)
    if mask_w is not None:
        features = torch.einsum("ncpo,np->ncpo", features, mask_w)
    features = torch.selu_(head.sf_conv(features)).squeeze(-1)
    if not head.conv2d:
        descs = torch.einsum("ncp,pcd->nd", features, head.agg_weights)
    else:
        descs = head.convM(features.reshape(n, -1)[:, :, None, None]).squeeze(-1).squeeze(-1)
    return F.normalize(descs, p=2.0, dim=1)
