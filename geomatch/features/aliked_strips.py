"""ALIKED's dense map and score map without its full-resolution transients.

Why: kornia's ``ALIKED.extract_dense_map`` keeps the four upsampled 32-channel maps, their
concatenation and the normalised copy alive at once: ~1.3 GB above the networks for one image at
1024 x 768, the largest transient of a worker once DISK runs in strips. Here the upsampled parts
are written into one preallocated map, the score head runs in row strips
(:func:`~geomatch.features.strips.rows_through`) and the map is normalised in place, strip by
strip: same numbers, about half the peak.
"""

from __future__ import annotations

import torch
from kornia.feature import ALIKED
from kornia.feature.aliked.aliked import InputPadder

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
