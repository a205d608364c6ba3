"""Several LightGlue pairs in one forward pass: keypoints and descriptors padded to the batch's
longest side, with masks, so that each pair's matches are the ones it gets on its own.

kornia's ``LightGlue`` batches pairs only when they have the same keypoint counts: it pads with
masks only on its ``torch.compile`` static-length path, and it computes the log assignment over
the whole padded matrix, so padded points would take part in the dual softmax. Here the per-point
layers (input projection, positional encoding, the feed-forward parts) and the attention run
batched, the attention masked so that no real point attends to a padded one, and the last
layer's assignment head, the match filter and the soft assignment run on each pair's own
unpadded slice.

Only the fixed-depth, fixed-width network batches: early exit (``depth_confidence`` > 0) stops a
batch at one layer for all its pairs, and point pruning (``width_confidence`` > 0) keeps a
different number of points in each pair; :meth:`LightGlueMatcher.match_batch` runs such configs
one pair at a time.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from kornia.feature import LightGlue
from kornia.feature.lightglue import filter_matches, normalize_keypoints

from .base import SparseFeatures, SparseMatch


def pair_bytes(n0: int, n1: int, heads: int) -> int:
    """The memory that grows with the square of a pair's keypoint count, padded to ``n0`` x ``n1``:
    the largest attention matrix (fp32, one per head) and the three boolean masks of a layer."""
    side = max(n0, n1)
    return side * side * (4 * heads + 3)


# a batch's default share of memory: 16 pairs at ALIKED's default cap of 2048 keypoints with
# LightGlue's 4 heads (about 1.3 GB)
DEFAULT_BUDGET_BYTES = 16 * pair_bytes(2048, 2048, 4)


def plan_batches(sizes: Sequence[tuple[int, int]], heads: int, budget_bytes: int) -> list[list[int]]:
    """Indices of ``sizes`` (each pair's keypoint counts) grouped into batches whose padded
    attention fits ``budget_bytes``; a pair over the budget on its own runs alone. Pairs are
    taken in order of their longer side, so a batch holds pairs of similar sizes and pads little."""
    if budget_bytes <= 0:
        raise ValueError(f"budget_bytes must be positive, not {budget_bytes}")
    order = sorted(range(len(sizes)), key=lambda i: max(sizes[i]))
    batches: list[list[int]] = []
    current: list[int] = []
    n0 = n1 = 0
    for i in order:
        w0, w1 = max(n0, sizes[i][0]), max(n1, sizes[i][1])
        if current and (len(current) + 1) * pair_bytes(w0, w1, heads) > budget_bytes:
            batches.append(current)
            current = []
            w0, w1 = sizes[i]
        current.append(i)
        n0, n1 = w0, w1
    if current:
        batches.append(current)
    return batches


def _normalized(f: SparseFeatures) -> torch.Tensor:
    """Keypoints as LightGlue's positional encoding takes them, with kornia's range check as a
    ValueError: a keypoint outside its image means features and size do not belong together."""
    size = torch.tensor([f.image_size], device=f.keypoints.device, dtype=torch.float32)
    kpts = normalize_keypoints(f.keypoints[None], size)[0]
    if not bool(((kpts >= -1) & (kpts <= 1)).all()):
        raise ValueError(f"keypoints lie outside their image of size (W, H) = {f.image_size}")
    return kpts


def _padded(
    feats: Sequence[SparseFeatures], input_dim: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One side of the batch: normalised keypoints (B, L, 2) and descriptors (B, L, D), zero past
    each image's count (finite: a padded value must not turn the masked attention into NaN), and
    the mask of real points (B, 1, L, 1), shaped so that kornia's ``masked_forward`` builds
    (B, 1, L, L) and (B, 1, L0, L1) masks that broadcast over the heads."""
    for f in feats:
        if f.descriptors.shape[-1] != input_dim:
            raise ValueError(
                f"descriptors of dimension {f.descriptors.shape[-1]}; LightGlue takes {input_dim}"
            )
    first = feats[0].descriptors
    length = max(f.keypoints.shape[0] for f in feats)
    kpts = torch.zeros(len(feats), length, 2, device=first.device, dtype=feats[0].keypoints.dtype)
    desc = torch.zeros(len(feats), length, input_dim, device=first.device, dtype=first.dtype)
    mask = torch.zeros(len(feats), 1, length, 1, device=first.device, dtype=torch.bool)
    for k, f in enumerate(feats):
        n = f.keypoints.shape[0]
        kpts[k, :n] = _normalized(f)
        desc[k, :n] = f.descriptors
        mask[k, 0, :n] = True
    return kpts, desc, mask


def forward_batch(
    net: LightGlue, pairs: Sequence[tuple[SparseFeatures, SparseFeatures]]
) -> list[SparseMatch]:
    """One forward pass over ``pairs`` (none empty) of a LightGlue that neither exits early nor
    prunes points; each result as ``LightGlueMatcher.match`` gives it, soft assignment included."""
    conf = net.conf
    if conf.depth_confidence > 0 or conf.width_confidence > 0:
        raise ValueError("a LightGlue with adaptive depth or width runs one pair at a time (match)")
    kpts0, desc0, mask0 = _padded([a for a, _ in pairs], conf.input_dim)
    kpts1, desc1, mask1 = _padded([b for _, b in pairs], conf.input_dim)
    desc0, desc1 = net.input_proj(desc0), net.input_proj(desc1)
    pe_dtype = net.posenc.Wr.weight.dtype
    enc0, enc1 = net.posenc(kpts0.to(pe_dtype)), net.posenc(kpts1.to(pe_dtype))
    # pairs of equal counts need no mask: the unmasked attention is the fused kernel's fast path
    masks = (mask0, mask1) if not (bool(mask0.all()) and bool(mask1.all())) else (None, None)
    for layer in net.transformers:
        desc0, desc1 = layer(desc0, desc1, enc0, enc1, mask0=masks[0], mask1=masks[1])
    head = net.log_assignment[conf.n_layers - 1]
    out = []
    for k, (a, b) in enumerate(pairs):
        na, nb = a.keypoints.shape[0], b.keypoints.shape[0]
        scores, _ = head(desc0[k : k + 1, :na], desc1[k : k + 1, :nb])
        m0, _, mscores0, _ = filter_matches(scores, conf.filter_threshold)
        valid = m0[0] > -1
        assignment = scores[0, :na, :nb].float().exp()
        out.append(SparseMatch(torch.where(valid)[0], m0[0][valid], mscores0[0][valid].float(), assignment))
    return out
