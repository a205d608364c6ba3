"""The geometry-aware optimization module (paper section 3.2, defaults from section 3.4).

The N x M confidence matrix is the memory hot spot (1024 px: ~9-12k cells a side, ~100M
entries), so it is never held whole. Two facts bound the work:

* min-max normalisation is a positive affine map, so it never changes which entry is a row or
  column maximum; after the first normalisation the matrix minimum is exactly 0, so later
  normalisations are plain divisions by the maximum;
* each round multiplies an entry by ``P_d * w`` with ``P_d`` in ``[0.5, sigmoid(tau)]``, so over
  ``iterations`` rounds two entries' ratio moves by at most ``(2 sigmoid(tau)) ** iterations``.

Hence only entries of P_c within that ratio of their row's or their column's maximum can ever
take part in a mutual nearest neighbour. One streamed pass over row blocks (sized by
``memory_budget_mb``) computes the dual-softmax normalisers, a second one the row and column
maxima and, per row and per column, the ``candidates_per_line`` largest entries; the rounds then
run on the candidates within the bound. The result equals the full-matrix computation unless a
row or column has more than ``candidates_per_line`` entries within the bound (a flat, ambiguous
line), where the weakest are dropped. (``w`` cancels under min-max normalisation: it is kept as an
option because the paper states it; its ablation shows no effect, as expected.)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch

from ..epipolar.geometry import SampsonGrid, estimate_fundamental, sampson_distance
from ..options import DEFAULTS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeoOptions:
    """Every hyperparameter of the module; defaults are the paper's."""

    tau: float = DEFAULTS["tau"]  # Sampson threshold, px^2
    iterations: int = DEFAULTS["iterations"]
    w: float = DEFAULTS["w"]
    theta_iter: float = DEFAULTS["theta_iter"]  # MNN threshold inside the loop
    theta_c: float = DEFAULTS["theta_c"]  # final MNN threshold (paper leaves it open; LoFTR's 0.2)
    anchor_min_count: int = 10
    anchor_min_score: float = 0.5
    fallback_fraction: float = 0.5  # "top half" of the initial mutual-NN matches
    use_anchors: bool = True
    f_estimator: str = "auto"  # auto (torch on CUDA, magsac otherwise) | magsac | torch | 8point
    f_threshold: float = 1.0  # px, MAGSAC threshold for the anchors (keypoint precision)
    f_threshold_coarse: float = 3.0  # px, MAGSAC threshold on coarse cell centres (~sqrt(tau))
    memory_budget_mb: float = DEFAULTS["memory_budget_mb"]  # working memory of one streamed block
    candidates_per_line: int = 32  # entries kept per row and per column of the confidence matrix
    # Anchored rounds (this project's reading; False is the paper's rule: F refitted on the
    # round's mutual-NN cells alone and always accepted). With anchors, a round's F is refitted on
    # the anchors' inliers and the round's matches jointly, and accepted only while the anchors'
    # truncated Sampson cost stays within (1 + anchor_slack) of the anchors' own fit: bad coarse
    # matches can then never drag F off the keypoint-precise geometry of the anchors.
    anchored: bool = True
    anchor_slack: float = 0.05
    stop_when_stable: bool = True  # end the rounds once F and the match set stop changing


@dataclass
class CoarseMatches:
    idx_a: torch.Tensor  # (K,) coarse cell ids in A
    idx_b: torch.Tensor  # (K,)
    confidence: torch.Tensor  # (K,)
    fundamental: torch.Tensor | None  # at the network-input scale
    init: str  # anchors | fallback | none | off
    history: list[int] = field(default_factory=list)  # mutual-NN count after each round
    candidates: int = 0
    initial_fundamental: torch.Tensor | None = (
        None  # F0; from keypoint-precise anchors when init == "anchors"
    )
    refits_accepted: int = 0  # rounds whose refitted F was kept


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
        self.device = self.fa.device
        temps = 5  # similarity, probabilities, Sampson numerator/denominator, mask
        self.rows = max(1, int(budget_mb * 2**20 / (max(m, 1) * 4 * temps)))
        self.n, self.m = n, m
        dev = self.device
        self.row_lse = torch.empty(n, device=dev)
        self.col_lse = torch.full((m,), -math.inf, device=dev)
        # when the whole similarity matrix fits the budget it is computed once and kept
        self._full: torch.Tensor | None = None
        for rows in self.blocks():
            s = self.similarity(rows)
            if rows.stop - rows.start == n:
                self._full = s
            self.row_lse[rows] = torch.logsumexp(s, dim=1)
            self.col_lse = torch.logaddexp(self.col_lse, torch.logsumexp(s, dim=0))

    def blocks(self) -> list[slice]:
        return [slice(i, min(i + self.rows, self.n)) for i in range(0, self.n, self.rows)]

    def similarity(self, rows: slice) -> torch.Tensor:
        return (self.fa[rows] @ self.fb.T).mul_(self.inv_t)

    def block(self, rows: slice) -> torch.Tensor:
        """P0 for a row block: a fresh tensor the caller may modify."""
        s = self._full.clone() if self._full is not None else self.similarity(rows)
        return s.mul_(2).sub_(self.row_lse[rows, None]).sub_(self.col_lse[None, :]).exp_()


class Assignment:
    """A precomputed P_c (N x M) served like :class:`DualSoftmax`: e.g. LightGlue's soft assignment
    over keypoints, whose rows and columns are keypoints instead of coarse cells."""

    def __init__(self, p: torch.Tensor) -> None:
        self.p = p.float()
        self.n, self.m = p.shape
        self.device = p.device

    def blocks(self) -> list[slice]:
        return [slice(0, self.n)] if self.n else []

    def block(self, rows: slice) -> torch.Tensor:
        return self.p[rows].clone()


Source = DualSoftmax | Assignment


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
        _, first_row = first_unique(ci[sel])
        sel = sel[first_row]
        _, first_col = first_unique(cj[sel])
        sel = sel[first_col]
    return sel


def first_unique(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The unique values of ``x`` and, for each, the position of its first occurrence."""
    uniq, inverse = torch.unique(x, return_inverse=True)
    pos = torch.arange(x.numel(), device=x.device)
    first = torch.full((uniq.numel(),), x.numel(), dtype=torch.long, device=x.device)
    first = first.scatter_reduce(0, inverse, pos, "amin")
    return uniq, first


def dense_mutual_nn(
    fa: torch.Tensor, fb: torch.Tensor, temperature: float, threshold: float, budget_mb: float = 256.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Plain detector-free coarse matching: mutual nearest neighbours of P_c above ``threshold``."""
    return mutual_nn(DualSoftmax(fa, fb, temperature, budget_mb), threshold)


def mutual_nn(source: Source, threshold: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual nearest neighbours of any P_c source above ``threshold``."""
    return _mutual(_stream_stats_topk(source, 1)[0], threshold)


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
    k = math.ceil(ia.numel() * opts.fallback_fraction)
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
    """Coarse matches of two feature sets (dual-softmax P_c) re-weighted by epipolar consistency.

    ``anchors`` are (points_a, points_b, scores) from the detector-based matcher, in the same
    pixel frame as the grid cell centres ``grid_a`` (N, 2) and ``grid_b`` (M, 2).
    """
    opts = opts or GeoOptions()
    source = DualSoftmax(fa, fb, temperature, opts.memory_budget_mb)
    return optimise(source, grid_a, grid_b, anchors, opts, opts.f_threshold_coarse)


def optimise(
    source: Source,
    grid_a: torch.Tensor,
    grid_b: torch.Tensor,
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
    opts: GeoOptions,
    cell_threshold: float,
) -> CoarseMatches:
    """The rounds on any P_c source; ``cell_threshold`` (px) is the robust F threshold suited to
    the precision of the cell positions (coarse cell centres: a few px; keypoints: about 1)."""
    k_line = max(1, opts.candidates_per_line)
    stats0, top = _stream_stats_topk(source, k_line)
    initial = _mutual(stats0, opts.theta_iter)
    F, init = initial_fundamental(grid_a, grid_b, initial, anchors, opts)
    F0 = F
    if F is None or opts.iterations <= 0:
        ia, jb, conf = _mutual(stats0, opts.theta_c)
        return CoarseMatches(ia, jb, conf, F, init if F is None else "off", [int(initial[0].numel())], 0, F0)

    tau = opts.tau
    ratio = 2.0 * torch.sigmoid(torch.tensor(max(tau, 0.0))).item()
    ci, cj, p0 = _candidates(stats0, top, ratio**-opts.iterations, source.m)
    ga, gb = grid_a.float(), grid_b.float()
    # the first round's matrix minimum is at least P_d's floor (0.5) times min(P0): below 1e-30 in
    # practice, so using that bound instead of the exact minimum changes no ranking
    floor = 0.5 * opts.w * stats0.minimum
    guard = _AnchorGuard.build(F, anchors, opts) if opts.anchored and init == "anchors" else None

    history: list[int] = []
    accepted = 0
    n, m = source.n, source.m
    val = p0
    previous: torch.Tensor | None = None
    for it in range(opts.iterations):
        d = SampsonGrid(F, ga, gb).pairs(ci, cj)
        val = val * geometric_confidence(d, tau) * opts.w
        if it == 0:
            val = (val - floor) / (val.max() - floor).clamp_min(1e-30)
        else:
            val = val / val.max().clamp_min(1e-30)  # the matrix minimum is 0 from round 1 on
        sel = _mutual_sparse(ci, cj, val, n, m, opts.theta_iter)
        history.append(int(sel.numel()))
        if guard is None:
            F_new, _ = estimate_fundamental(ga[ci[sel]], gb[cj[sel]], opts.f_estimator, cell_threshold)
            if F_new is not None:
                F = F_new
                accepted += 1
            continue
        if opts.stop_when_stable and previous is not None and torch.equal(previous, sel):
            break
        previous = sel
        F_new, _ = estimate_fundamental(
            torch.cat([guard.pa, ga[ci[sel]]]),
            torch.cat([guard.pb, gb[cj[sel]]]),
            opts.f_estimator,
            cell_threshold,
        )
        if F_new is not None and guard.accepts(F_new):
            F = F_new
            accepted += 1
    sel = _mutual_sparse(ci, cj, val, n, m, opts.theta_c)
    return CoarseMatches(ci[sel], cj[sel], val[sel], F, init, history, int(ci.numel()), F0, accepted)


@dataclass
class _AnchorGuard:
    """The anchors' verdict on a candidate F: its truncated (MSAC) Sampson cost over the anchors
    must stay within ``1 + slack`` of the cost of the anchors' own fit."""

    pa: torch.Tensor  # anchor inliers of the initial F: always part of a refit
    pb: torch.Tensor
    all_a: torch.Tensor
    all_b: torch.Tensor
    tau: float
    limit: float

    @staticmethod
    def build(
        F0: torch.Tensor, anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None, opts: GeoOptions
    ) -> _AnchorGuard | None:
        if anchors is None or anchors[0].shape[0] == 0:
            return None
        pa, pb = anchors[0].float(), anchors[1].float()
        d = sampson_distance(F0.to(pa.device, pa.dtype), pa, pb)
        inl = d <= opts.tau
        cost = float(d.clamp(max=opts.tau).sum())
        return _AnchorGuard(pa[inl], pb[inl], pa, pb, opts.tau, cost * (1.0 + opts.anchor_slack))

    def cost(self, F: torch.Tensor) -> float:
        d = sampson_distance(F.to(self.all_a.device, self.all_a.dtype), self.all_a, self.all_b)
        return float(d.clamp(max=self.tau).sum())

    def accepts(self, F: torch.Tensor) -> bool:
        return self.cost(F) <= self.limit


def _stream_stats_topk(ds: Source, k: int) -> tuple[_Stats, dict[str, torch.Tensor]]:
    """Row/column maxima of P0 plus each row's and each column's k largest entries, one pass."""
    dev = ds.device
    kr = min(k, ds.m)
    row_max = torch.empty(ds.n, device=dev)
    row_arg = torch.empty(ds.n, dtype=torch.long, device=dev)
    row_top_v = torch.empty(ds.n, kr, device=dev)
    row_top_j = torch.empty(ds.n, kr, dtype=torch.long, device=dev)
    col_top_v = torch.empty(0, ds.m, device=dev)
    col_top_i = torch.empty(0, ds.m, dtype=torch.long, device=dev)
    minimum = math.inf
    for rows in ds.blocks():
        p = ds.block(rows)
        v, j = p.topk(kr, dim=1)
        row_top_v[rows], row_top_j[rows] = v, j
        row_max[rows], row_arg[rows] = v[:, 0], j[:, 0]
        kc = min(k, p.shape[0])
        cv, ci = p.topk(kc, dim=0)
        col_top_v = torch.cat([col_top_v, cv])
        col_top_i = torch.cat([col_top_i, ci + rows.start])
        if col_top_v.shape[0] > k:
            keep_v, order = col_top_v.topk(k, dim=0)
            col_top_v, col_top_i = keep_v, col_top_i.gather(0, order)
        minimum = min(minimum, float(p.min()))
    col_max, pos = col_top_v.max(dim=0)
    col_arg = col_top_i.gather(0, pos[None])[0]
    stats = _Stats(row_max, row_arg, col_max, col_arg, minimum)
    return stats, {"row_v": row_top_v, "row_j": row_top_j, "col_v": col_top_v, "col_i": col_top_i}


def _candidates(
    stats: _Stats, top: dict[str, torch.Tensor], rho: float, m: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entries that can still become a row or column maximum within the remaining rounds."""
    rv, rj = top["row_v"], top["row_j"]
    rkeep = rv >= stats.row_max[:, None] * rho
    ri = torch.arange(rv.shape[0], device=rv.device)[:, None].expand_as(rj)[rkeep]
    cv, cidx = top["col_v"], top["col_i"]
    ckeep = cv >= stats.col_max[None, :] * rho
    cj = torch.arange(cv.shape[1], device=cv.device)[None, :].expand_as(cidx)[ckeep]
    keys = torch.cat([ri * m + rj[rkeep], cidx[ckeep] * m + cj])
    values = torch.cat([rv[rkeep], cv[ckeep]])
    keys, first = first_unique(keys)
    return keys // m, keys % m, values[first]
