"""The geometry-aware optimization module (paper section 3.2, defaults from section 3.4).

The N x M confidence matrix is the memory hot spot (1024 px: ~12k cells a side, 150M
entries), so it is never held whole. Two facts make an exact, block-wise version possible:

* min-max normalisation is a positive affine map, so it never changes which entry is a row
  or column maximum; after the first normalisation the matrix minimum is exactly 0, so later
  normalisations are plain divisions by the maximum;
* each iteration multiplies an entry by ``P_d * w`` with ``P_d`` in ``[0.5, sigmoid(tau)]``, so
  over the remaining ``iterations - 1`` rounds two entries' ratio moves by at most
  ``(2 sigmoid(tau)) ** (iterations - 1)``.

Hence only entries within that ratio of their row's or their column's maximum after the first
round can ever be a row or column maximum, i.e. take part in a mutual nearest neighbour. The
first round is streamed over row blocks sized by ``memory_budget_mb``; the remaining rounds
run on that candidate set, which is exact. (Note that ``w`` cancels under min-max
normalisation: it is kept as an option because the paper states it, and its ablation shows
no effect, as expected.)
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from .geometry import SampsonGrid, estimate_fundamental

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeoOptions:
    """Every hyperparameter of the module; defaults are the paper's."""

    tau: float = 10.0  # Sampson threshold, px^2
    iterations: int = 10
    w: float = 1.2
    theta_iter: float = 0.01  # MNN threshold inside the loop
    theta_c: float = 0.2  # final MNN threshold (paper leaves it open; LoFTR's 0.2)
    anchor_min_count: int = 10
    anchor_min_score: float = 0.5
    fallback_fraction: float = 0.5  # "top half" of the initial mutual-NN matches
    use_anchors: bool = True
    f_estimator: str = "magsac"  # magsac | 8point
    f_threshold: float = 1.0  # px, MAGSAC inlier threshold at the network-input scale
    memory_budget_mb: float = 256.0  # working memory of one streamed block
    max_candidates: int = 4_000_000


@dataclass
class CoarseMatches:
    idx_a: torch.Tensor  # (K,) coarse cell ids in A
    idx_b: torch.Tensor  # (K,)
    confidence: torch.Tensor  # (K,)
    fundamental: torch.Tensor | None  # at the network-input scale
    init: str  # anchors | fallback | none | off
    history: list[int] = field(default_factory=list)  # mutual-NN count after each round
    candidates: int = 0


@dataclass
class _Stats:
    row_max: torch.Tensor
    row_arg: torch.Tensor
    col_max: torch.Tensor
    col_arg: torch.Tensor
    minimum: float


class DualSoftmax:
    """P_c = softmax_rows(S) * softmax_cols(S), S = f_a f_b^T / T, served one row block at a time."""

    def __init__(self, fa: torch.Tensor, fb: torch.Tensor, temperature: float, budget_mb: float) -> None:
        self.fa, self.fb = fa.float(), fb.float()
        self.inv_t = 1.0 / temperature
        n, m = fa.shape[0], fb.shape[0]
        temps = 5  # similarity, probabilities, Sampson numerator/denominator, mask
        self.rows = max(1, int(budget_mb * 2**20 / (max(m, 1) * 4 * temps)))
        self.n, self.m = n, m
        dev = self.fa.device
        self.row_lse = torch.empty(n, device=dev)
        self.col_lse = torch.full((m,), -math.inf, device=dev)
        for rows in self.blocks():
            s = self.similarity(rows)
            self.row_lse[rows] = torch.logsumexp(s, dim=1)
            self.col_lse = torch.logaddexp(self.col_lse, torch.logsumexp(s, dim=0))

    def blocks(self) -> list[slice]:
        return [slice(i, min(i + self.rows, self.n)) for i in range(0, self.n, self.rows)]

    def similarity(self, rows: slice) -> torch.Tensor:
        return (self.fa[rows] @ self.fb.T) * self.inv_t

    def block(self, rows: slice) -> torch.Tensor:
        s = self.similarity(rows)
        return torch.exp(2 * s - self.row_lse[rows, None] - self.col_lse[None, :])

    def pairs(self, ia: torch.Tensor, jb: torch.Tensor) -> torch.Tensor:
        s = (self.fa[ia] * self.fb[jb]).sum(-1) * self.inv_t
        return torch.exp(2 * s - self.row_lse[ia] - self.col_lse[jb])


Value = Callable[[slice, torch.Tensor], torch.Tensor]


def _identity(rows: slice, p: torch.Tensor) -> torch.Tensor:
    return p


def _stream_stats(ds: DualSoftmax, value: Value) -> _Stats:
    dev = ds.fa.device
    row_max = torch.empty(ds.n, device=dev)
    row_arg = torch.empty(ds.n, dtype=torch.long, device=dev)
    col_max = torch.full((ds.m,), -math.inf, device=dev)
    col_arg = torch.zeros(ds.m, dtype=torch.long, device=dev)
    minimum = math.inf
    for rows in ds.blocks():
        v = value(rows, ds.block(rows))
        row_max[rows], row_arg[rows] = v.max(dim=1)
        bmax, barg = v.max(dim=0)
        better = bmax > col_max
        col_max = torch.where(better, bmax, col_max)
        col_arg = torch.where(better, barg + rows.start, col_arg)
        minimum = min(minimum, float(v.min()))
    return _Stats(row_max, row_arg, col_max, col_arg, minimum)


def _mutual(stats: _Stats, threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    ia = torch.arange(stats.row_max.shape[0], device=stats.row_max.device)
    keep = (stats.col_arg[stats.row_arg] == ia) & (stats.row_max >= threshold)
    return ia[keep], stats.row_arg[keep], stats.row_max[keep]


def _mutual_sparse(
    ci: torch.Tensor, cj: torch.Tensor, val: torch.Tensor, n: int, m: int, threshold: float
) -> torch.Tensor:
    """Indices of candidate entries that are the maximum of both their row and their column."""
    rmax = torch.full((n,), -math.inf, device=val.device).scatter_reduce(0, ci, val, "amax")
    cmax = torch.full((m,), -math.inf, device=val.device).scatter_reduce(0, cj, val, "amax")
    keep = (val == rmax[ci]) & (val == cmax[cj]) & (val >= threshold)
    sel = keep.nonzero().squeeze(1)
    # exact ties would give one cell two partners: keep the first per row and per column
    if sel.numel():
        _, first_row = _first_unique(ci[sel])
        sel = sel[first_row]
        _, first_col = _first_unique(cj[sel])
        sel = sel[first_col]
    return sel


def _first_unique(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    uniq, inverse = torch.unique(x, return_inverse=True)
    pos = torch.arange(x.numel(), device=x.device)
    first = torch.full((uniq.numel(),), x.numel(), dtype=torch.long, device=x.device)
    first = first.scatter_reduce(0, inverse, pos, "amin")
    return uniq, first


def dense_mutual_nn(
    fa: torch.Tensor, fb: torch.Tensor, temperature: float, threshold: float, budget_mb: float = 256.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Plain detector-free coarse matching: mutual nearest neighbours of P_c above ``threshold``."""
    ds = DualSoftmax(fa, fb, temperature, budget_mb)
    return _mutual(_stream_stats(ds, _identity), threshold)


def geometric_confidence(d: torch.Tensor, tau: float) -> torch.Tensor:
    """P_d = sigmoid(relu(tau - d)): 0.5 beyond the threshold, towards 1 on the epipolar line."""
    return torch.sigmoid(torch.relu(tau - d))


def initial_fundamental(
    grid_a: torch.Tensor,
    grid_b: torch.Tensor,
    initial: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
    opts: GeoOptions,
) -> tuple[torch.Tensor | None, str]:
    """The paper's rule: >= anchor_min_count anchors scoring > anchor_min_score, else top half of M_c."""
    if opts.use_anchors and anchors is not None:
        pa, pb, score = anchors
        good = score > opts.anchor_min_score
        if int(good.sum()) >= opts.anchor_min_count:
            F, _ = estimate_fundamental(pa[good], pb[good], opts.f_estimator, opts.f_threshold)
            if F is not None:
                return F, "anchors"
    ia, jb, conf = initial
    k = int(math.ceil(ia.numel() * opts.fallback_fraction))
    if k < 8:
        return None, "none"
    top = torch.argsort(conf, descending=True)[:k]
    F, _ = estimate_fundamental(grid_a[ia[top]], grid_b[jb[top]], opts.f_estimator, opts.f_threshold)
    return F, ("fallback" if F is not None else "none")


def geometry_aware_matching(
    fa: torch.Tensor,
    fb: torch.Tensor,
    grid_a: torch.Tensor,
    grid_b: torch.Tensor,
    temperature: float,
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    opts: GeoOptions | None = None,
) -> CoarseMatches:
    """Coarse matches re-weighted by epipolar consistency.

    ``anchors`` are (points_a, points_b, scores) from the detector-based matcher, in the same
    pixel frame as the grid cell centres ``grid_a`` (N, 2) and ``grid_b`` (M, 2).
    """
    opts = opts or GeoOptions()
    ds = DualSoftmax(fa, fb, temperature, opts.memory_budget_mb)
    stats0 = _stream_stats(ds, _identity)
    initial = _mutual(stats0, opts.theta_iter)
    F, init = initial_fundamental(grid_a, grid_b, initial, anchors, opts)
    if F is None or opts.iterations <= 0:
        ia, jb, conf = _mutual(stats0, opts.theta_c)
        return CoarseMatches(ia, jb, conf, F, init if F is None else "off", [int(initial[0].numel())])

    tau = opts.tau
    sampson = SampsonGrid(F, grid_a.float(), grid_b.float())

    def first_round(rows: slice, p: torch.Tensor) -> torch.Tensor:
        return p * geometric_confidence(sampson.block(rows), tau) * opts.w

    stats1 = _stream_stats(ds, first_round)
    m1, big = stats1.minimum, float(stats1.row_max.max())
    ratio = 2.0 * torch.sigmoid(torch.tensor(max(tau, 0.0))).item()
    rho = ratio ** -(opts.iterations - 1)
    ci, cj, val = _candidates(ds, first_round, stats1, m1, rho, opts.max_candidates)
    val = (val - m1) / max(big - m1, 1e-30)

    history: list[int] = []
    n, m = ds.n, ds.m
    for it in range(opts.iterations):
        if it > 0:
            d = SampsonGrid(F, grid_a.float(), grid_b.float()).pairs(ci, cj)
            val = val * geometric_confidence(d, tau) * opts.w
            val = val / val.max().clamp_min(1e-30)  # the matrix minimum is 0 from round 1 on
        sel = _mutual_sparse(ci, cj, val, n, m, opts.theta_iter)
        history.append(int(sel.numel()))
        F_new, _ = estimate_fundamental(
            grid_a[ci[sel]], grid_b[cj[sel]], opts.f_estimator, opts.f_threshold
        )
        if F_new is not None:
            F = F_new
    sel = _mutual_sparse(ci, cj, val, n, m, opts.theta_c)
    return CoarseMatches(ci[sel], cj[sel], val[sel], F, init, history, int(ci.numel()))


def _candidates(
    ds: DualSoftmax, value: Value, stats: _Stats, m1: float, rho: float, cap: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    while True:
        row_floor = m1 + (stats.row_max - m1) * rho
        col_floor = m1 + (stats.col_max - m1) * rho
        parts_i, parts_j, parts_v = [], [], []
        total = 0
        for rows in ds.blocks():
            v = value(rows, ds.block(rows))
            keep = (v >= row_floor[rows, None]) | (v >= col_floor[None, :])
            i, j = keep.nonzero(as_tuple=True)
            total += i.numel()
            if total > cap:
                break
            parts_i.append(i + rows.start)
            parts_j.append(j)
            parts_v.append(v[i, j])
        if total <= cap:
            return torch.cat(parts_i), torch.cat(parts_j), torch.cat(parts_v)
        log.warning("more than %d candidate entries; tightening the ratio bound (no longer exact)", cap)
        rho = min(1.0, rho * 8)
