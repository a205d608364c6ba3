"""Running the full-resolution end of a convolutional network a few rows at a time.

Why: a backbone's last layers work at the input's full resolution on many channels, and PyTorch
materialises every intermediate of them whole (at 1024 x 768 each 32-channel float map is 100 MB);
those transients, not the features kept afterwards, set a worker's peak memory. Convolutions are
local, so rows [r0, r1) of a stack of them need only the input rows within the stack's halo:
computing the output strip by strip gives the same numbers while holding one strip's
intermediates at a time (small strips also stay in cache, faster than whole maps on the CPU:
docs/benchmarks.md, "A worker's memory on a project").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

Layer = Callable[[torch.Tensor], torch.Tensor]


def _row_pad(layer: Layer) -> int:
    """Rows of zero padding a stride-1 convolution adds above and below (0 for pointwise layers)."""
    if not isinstance(layer, nn.Conv2d):
        return 0
    if layer.stride != (1, 1) or layer.padding_mode != "zeros":
        raise ValueError("row strips support stride-1, zero-padded convolutions only")
    if layer.padding == "same":
        return layer.dilation[0] * (layer.kernel_size[0] - 1) // 2
    if isinstance(layer.padding, str):
        raise ValueError(f"unsupported padding {layer.padding!r}")
    return int(layer.padding[0])


def _col_pad(conv: nn.Conv2d) -> int:
    if conv.padding == "same":
        return conv.dilation[1] * (conv.kernel_size[1] - 1) // 2
    return int(conv.padding[1])


def rows_through(
    layers: Sequence[Layer], source: Callable[[int, int], torch.Tensor], h: int, r0: int, r1: int
) -> torch.Tensor:
    """Rows [r0, r1) of ``layers`` applied in turn to an h-row input of which ``source(a, b)``
    gives rows [a, b). Each convolution's zero padding is added where the image ends, and a
    strip's halo rows stand in for it elsewhere, so the result equals the whole map's rows."""
    halo = sum(_row_pad(layer) for layer in layers)
    a, b = max(0, r0 - halo), min(h, r1 + halo)
    x = source(a, b)
    for layer in layers:
        p = _row_pad(layer)
        if p == 0:
            x = layer(x)
            continue
        assert isinstance(layer, nn.Conv2d)
        top, bottom = (p if a == 0 else 0), (p if b == h else 0)
        x = F.pad(x, (0, 0, top, bottom))
        x = F.conv2d(
            x,
            layer.weight,
            layer.bias,
            padding=(0, _col_pad(layer)),
            dilation=layer.dilation,
            groups=layer.groups,
        )
        a, b = a + p - top, b - p + bottom
    return x[..., r0 - a : r1 - a, :]


def row_strips(h: int, rows: int) -> list[tuple[int, int]]:
    return [(r0, min(h, r0 + rows)) for r0 in range(0, h, rows)]
