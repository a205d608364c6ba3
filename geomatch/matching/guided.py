"""Keypoint matching guided by the epipolar geometry: the geometry-aware idea on a detector's points.

The paper re-weights dense matching confidences by their Sampson distance under an F the sparse
anchors initialise. On two overlapping photos of a survey (nadir, the same scale, brought to one
heading) the detector's own points are dense enough to be the cells: with thousands of ALIKED
keypoints per photo, the descriptor similarity of every pair of points is the confidence, and the
Sampson gate keeps only the candidates that lie on each other's epipolar lines. Two passes:

1. seed: mutual nearest neighbours with a ratio test over all points (what COLMAP does with SIFT),
   and a robust F on them; LightGlue is not needed on such pairs (on the drone surveys the seed F
   has more inliers than light LightGlue on the same photos, in less time; the runs:
   docs/benchmarks.md, "Drone surveys beside COLMAP SIFT");
2. guided: the mutual nearest neighbours again, each point choosing only among the points within
   ``tau`` (Sampson, px^2) of its epipolar line, with the ratio test among those candidates; the
   ambiguity a repeated texture makes along the whole image is gone, so several times the seed's
   matches survive.

The (N, M) similarity and Sampson matrices are computed in row blocks bounded in bytes.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..epipolar.geometry import estimate_fundamental, homogeneous, sampson_distance
from ..features.base import SparseFeatures
from ..imageio import image_key
from .config import (
    GUIDED_LIGHTGLUE_POINTS,
    GUIDED_RATIO,
    SEED_RATIO,
    MatcherParts,
    MatchResult,
    StageTimer,
    pair_result,
)

# rows of the (N, M) matrices computed at once, in bytes of float32 per matrix. On the CPU a block
# small enough to stay in cache: the passes over it (similarity, Sampson gate, top two, column
# maxima) then read cached memory, and no temporary is large enough for the allocator to map fresh
# pages for it (docs/benchmarks.md, drone surveys). On a GPU, few large blocks: each is a dozen
# launches.
CPU_BLOCK_BYTES = 2 * 2**20
BLOCK_BYTES = 64 * 2**20
# On a CPU with bfloat16 units (AVX512-BF16, AMX) the similarity blocks are computed from bfloat16
# descriptors (faster than float32, guided or not: docs/benchmarks.md, drone surveys), and each row's best
# LOW_CANDIDATES are ranked again by their float32 similarity: the ratio test and the similarity
# returned are float32's; a column's best is compared in the block's rounding (ties there go to
# the row most similar in float32), so a match can differ only where two rows' similarities to
# one point lie within bfloat16's rounding (~0.002) of each other.
LOW_CANDIDATES = 4
LOW_PRECISION = True


# The guided pass keeps a candidate within tau (10 px^2) of the seed's F; of those, the ones more
# than 2 px (Sampson, at the network's size) off the F the guided matches themselves fit would not
# pass COLMAP's verification (4 px on the photo, ~1.3 px at 640 px on a 2000 px photo) and only make
# its RANSAC long (on the drone surveys a large share of the guided matches were off COLMAP's F:
# docs/benchmarks.md, drone surveys). Passed on: the matches within KEEP_SAMPSON px^2 of it.
KEEP_SAMPSON = 4.0


def low_precision(device: torch.device) -> bool:
    return LOW_PRECISION and device.type == "cpu" and _cpu_bf16()


@functools.cache
def _cpu_bf16() -> bool:
    """Whether the CPU multiplies bfloat16 in hardware (elsewhere torch emulates it, slower than
    float32): the flags Linux reports; other systems keep float32."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    flags = next(
        (line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), []
    )
    return "avx512_bf16" in flags or "amx_bf16" in flags


def mutual_ratio(
    da: torch.Tensor,
    db: torch.Tensor,
    ratio: float,
    gate: tuple[torch.Tensor, torch.Tensor, torch.Tensor, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ia, ib, similarity) of the mutual nearest neighbours by cosine similarity of the
    L2-normalised descriptors ``da`` (N, D) and ``db`` (M, D), kept where a point's second best
    similarity is below ``ratio`` times its best (the ratio test, on similarities). With ``gate``
    = (F, ka, kb, tau) a candidate pair counts only when its Sampson distance under F (x_b^T F x_a
    = 0, points ``ka`` (N, 2) and ``kb`` (M, 2)) is at most ``tau`` px^2."""
    n, m = da.shape[0], db.shape[0]
    if n < 2 or m < 2:
        empty = torch.zeros(0, dtype=torch.long, device=da.device)
        return empty, empty, torch.zeros(0, device=da.device)
    da, db = da.float(), db.float()
    low = low_precision(da.device)
    if low:
        da_low, db_low = da.bfloat16(), db.bfloat16()
    best_b = torch.empty(n, dtype=torch.long, device=da.device)
    s1 = torch.empty(n, device=da.device)
    s2 = torch.empty(n, device=da.device)
    s1_block = s1  # a row's best as the block holds it, which the columns' best are compared with
    if low:
        s1_block = torch.empty(n, device=da.device)
    # each column's best similarity only, not where it is: on the CPU an argmax down the columns
    # costs many times the max (amax) of the same values; a row's best is mutual when it equals its
    # column's best
    col_best = torch.full((m,), -2.0, device=da.device)
    if gate is not None:
        F, ka, kb, tau = gate
        F = F.to(device=ka.device, dtype=torch.float32)
        lines = homogeneous(ka.float()) @ F.T  # (N, 3) epipolar lines in B
        xb = homogeneous(kb.float())
        ftxb = xb @ F  # (M, 3)
        den_b = ftxb[:, 0] ** 2 + ftxb[:, 1] ** 2
    block_bytes = CPU_BLOCK_BYTES if da.device.type == "cpu" else BLOCK_BYTES
    step = max(1, block_bytes // max(4 * m, 1))
    k = min(LOW_CANDIDATES, m)
    for r0 in range(0, n, step):
        r1 = min(n, r0 + step)
        s = (da_low[r0:r1] @ db_low.T).float() if low else da[r0:r1] @ db.T
        if gate is not None:
            la = lines[r0:r1]
            num = (la @ xb.T).square_()
            den = (la[:, 0:1] ** 2 + la[:, 1:2] ** 2) + den_b[None]
            s.masked_fill_(num > tau * den, -1.0)
        if low:
            # the block's best few by the rounded similarities, ranked again by the exact ones
            cand = s.topk(k, dim=1)
            exact = torch.einsum("rd,rkd->rk", da[r0:r1], db[cand.indices])
            exact = torch.where(cand.values <= -1.0, -1.0, exact)  # gated out stays out
            top = exact.topk(2, dim=1)
            best = cand.indices.gather(1, top.indices[:, :1]).squeeze(1)
            best_b[r0:r1], s1[r0:r1], s2[r0:r1] = best, top.values[:, 0], top.values[:, 1]
            s1_block[r0:r1] = s.gather(1, best[:, None]).squeeze(1)
        else:
            top = s.topk(2, dim=1)
            best_b[r0:r1], s1[r0:r1], s2[r0:r1] = top.indices[:, 0], top.values[:, 0], top.values[:, 1]
        col_best = torch.maximum(col_best, s.amax(dim=0))
    rows = torch.arange(n, device=da.device)
    keep = (s1_block >= col_best[best_b]) & (s1 > 0) & (s2 < ratio * s1)
    ia = rows[keep]
    ib = best_b[ia]
    sk = s1[keep]
    # rows that take one column (tied for its best, or within the rounding of the low-precision
    # product): the most similar keeps it, the first of exact ties, as an argmax would give it
    first = torch.ones_like(ib, dtype=torch.bool)
    if ib.numel() > 1:
        by_sim = torch.argsort(-sk, stable=True)
        order = by_sim[torch.argsort(ib[by_sim], stable=True)]
        dup = torch.zeros_like(first)
        dup[order[1:]] = ib[order[1:]] == ib[order[:-1]]
        first = ~dup
    return ia[first], ib[first], sk[first]


def strongest(f: SparseFeatures | None, n: int) -> SparseFeatures:
    """``f``'s ``n`` highest-scoring keypoints (all of them when there are no more)."""
    assert f is not None
    if f.keypoints.shape[0] <= n:
        return f
    idx = torch.topk(f.scores, n).indices
    return SparseFeatures(f.keypoints[idx], f.descriptors[idx], f.scores[idx], f.image_size)


def seed(
    matcher: MatcherParts, key0: str, key1: str, sa: SparseFeatures, sb: SparseFeatures, lightglue: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, int, str]:
    """The guided matcher's seed: (inliers in A, inliers in B, F, how many, which seed): mutual
    nearest neighbours with the ratio test, and where they fit fewer than ``anchors_suffice``
    inliers (and ``lightglue``) LightGlue on each photo's 1024 strongest points, the better.
    Only the F's inliers come back: on a weak pair they are its answer, and the rest (most of
    the matches of photos that share little) cost COLMAP's verification its longest RANSAC."""
    cfg = matcher.config

    def fit(
        pa: torch.Tensor, pb: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, int]:
        F, mask = estimate_fundamental(pa, pb, cfg.geo.f_estimator, cfg.geo.f_threshold)
        if mask is None:
            return pa[:0], pb[:0], F, 0
        return pa[mask], pb[mask], F, int(mask.sum())

    ia, ib, _ = mutual_ratio(sa.descriptors, sb.descriptors, SEED_RATIO)
    pa, pb, F, n = fit(sa.keypoints[ia].float(), sb.keypoints[ib].float())
    if n >= cfg.anchors_suffice or not lightglue:
        return pa, pb, F, n, "nn"
    a, b = strongest(sa, GUIDED_LIGHTGLUE_POINTS), strongest(sb, GUIDED_LIGHTGLUE_POINTS)
    lg = matcher.match_anchors(key0, key1, a, b)
    qa, qb, F2, n2 = fit(a.keypoints[lg.idx_a].float(), b.keypoints[lg.idx_b].float())
    return (qa, qb, F2, n2, "lightglue") if n2 > n else (pa, pb, F, n, "nn")


@torch.inference_mode()
def seed_inliers(matcher: MatcherParts, image0: np.ndarray, image1: np.ndarray) -> int:
    """The inliers of the mutual-nearest-neighbour seed's F alone (no LightGlue): a cheap,
    sharp rank of a pair's quarter turns (a wrong turn fits a handful)."""
    key0, key1 = image_key(image0), image_key(image1)
    sa = matcher.features(image0, key0)[matcher.config.sparse].sparse
    sb = matcher.features(image1, key1)[matcher.config.sparse].sparse
    assert sa is not None and sb is not None
    return seed(matcher, key0, key1, sa, sb, lightglue=False)[3]


@torch.inference_mode()
def match_guided(matcher: MatcherParts, image0: np.ndarray, image1: np.ndarray) -> MatchResult:
    """The pair by the two passes above: a seed F, then the matches its epipolar lines guide.
    ``stats["f_inliers"]`` is the seed's: below ``anchors_suffice`` the seed's matches are the
    answer (no guided pass), and the caller decides whether the full method runs."""
    cfg = matcher.config
    timer = StageTimer(matcher.device)
    key0, key1 = image_key(image0), image_key(image1)
    with timer("features0"):
        sa = matcher.features(image0, key0)[cfg.sparse].sparse
    with timer("features1"):
        sb = matcher.features(image1, key1)[cfg.sparse].sparse
    assert sa is not None and sb is not None
    prep0, prep1 = matcher.prepared(image0, key0), matcher.prepared(image1, key1)
    with timer("seed"):
        pa, pb, F, n, how = seed(matcher, key0, key1, sa, sb, lightglue=True)
    stats: dict[str, Any] = {"f_inliers": n, "seed": how}
    if F is None or n < cfg.anchors_suffice:
        return pair_result(cfg.method, (pa, pb, torch.ones(pa.shape[0])), F, (prep0, prep1), stats, timer)
    with timer("guided"):
        ia, ib, sim = mutual_ratio(
            sa.descriptors, sb.descriptors, GUIDED_RATIO, (F, sa.keypoints, sb.keypoints, cfg.geo.tau)
        )
        ga, gb = sa.keypoints[ia].float(), sb.keypoints[ib].float()
    with timer("merge"):
        F_guided, inl = estimate_fundamental(ga, gb, cfg.geo.f_estimator, cfg.geo.f_threshold)
    stats["guided"] = int(ia.numel())
    if F_guided is not None and inl is not None and int(inl.sum()) >= cfg.anchors_suffice:
        # only the matches near the guided F go on (KEEP_SAMPSON)
        near = sampson_distance(F_guided.to(ga), ga, gb) <= KEEP_SAMPSON
        ga, gb, sim = ga[near], gb[near], sim[near]
    F_out = F if F_guided is None else F_guided
    return pair_result(cfg.method, (ga, gb, sim), F_out, (prep0, prep1), stats, timer)
