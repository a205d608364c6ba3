"""The dense branch of one pair, on the network inputs' pixels: candidate cells, matched by mutual
nearest neighbours or by the geometry-aware rounds (geomatch.matching.optimizer), then refined
where the cells are coarser than the keypoints; and the merge of the anchors and the dense matches
into one set without duplicates (:func:`merge_parts`)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from ..features.base import DenseHead, ImageFeatures, SparseFeatures, SparseMatch
from .config import MatcherConfig, StageTimer
from .optimizer import Assignment, dense_mutual_nn, first_unique, geometry_aware_matching, mutual_nn, optimise


def from_maps(
    cfg: MatcherConfig,
    head: DenseHead,
    f0: dict[str, ImageFeatures],
    f1: dict[str, ImageFeatures],
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
    stats: dict[str, Any],
    timer: StageTimer,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Detector-free branch on per-image dense maps: coarse cells, rounds, window refinement."""
    da, db = f0[cfg.dense].dense, f1[cfg.dense].dense
    assert da is not None and db is not None
    F_prior = None
    with timer("dense_coarse"):
        pair = head.coarse_pair(da, db)
    stats["coarse_cells"] = (int(pair.feats_a.shape[0]), int(pair.feats_b.shape[0]))
    if not cfg.flags.optimise:
        with timer("dense_coarse"):
            ci, cj, conf = dense_mutual_nn(
                pair.feats_a, pair.feats_b, pair.temperature, cfg.geo.theta_c, cfg.geo.memory_budget_mb
            )
    else:
        geo = cfg.geo if cfg.flags.anchor_init else replace(cfg.geo, use_anchors=False)
        with timer("optimizer"):
            cm = geometry_aware_matching(
                pair.feats_a, pair.feats_b, pair.grid_a, pair.grid_b, pair.temperature, anchors, geo
            )
        ci, cj, conf = cm.idx_a, cm.idx_b, cm.confidence
        # the refinement's epipolar prior needs a precise F: the anchors' (keypoint
        # precision), not a fit on 8-px cell centres
        if cm.init == "anchors":
            F_prior = cm.initial_fundamental
        stats.update(init=cm.init, history=cm.history, candidates=cm.candidates, refits=cm.refits_accepted)
    stats["coarse_matches"] = int(ci.numel())
    with timer("refine"):
        ref = head.refine(da, db, pair, ci, cj, F_prior)
    return ref.points_a, ref.points_b, conf.float()


def from_assignment(
    cfg: MatcherConfig,
    device: torch.device,
    lg: SparseMatch,
    sa: SparseFeatures | None,
    sb: SparseFeatures | None,
    anchors: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
    stats: dict[str, Any],
    timer: StageTimer,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keypoints as cells: LightGlue's soft assignment over every keypoint is P_c. The rounds
    recover matches LightGlue was unsure of (repeated patterns, weak texture) that the
    geometry confirms, at keypoint precision, so there is nothing to refine."""
    assert sa is not None and sb is not None
    if lg.assignment is None:
        if sa.keypoints.shape[0] and sb.keypoints.shape[0]:
            raise ValueError(
                "dense='lightglue' needs LightGlue's full soft assignment: "
                "set lightglue_width_confidence=-1 (no point pruning)"
            )
        z = torch.zeros(0, 2, device=device)
        return z, z.clone(), torch.zeros(0, device=device)
    source = Assignment(lg.assignment)
    ga, gb = sa.keypoints.float(), sb.keypoints.float()
    stats["coarse_cells"] = (source.n, source.m)
    with timer("optimizer"):
        if not cfg.flags.optimise:
            ci, cj, conf = mutual_nn(source, cfg.geo.theta_c)
        else:
            geo = cfg.geo if cfg.flags.anchor_init else replace(cfg.geo, use_anchors=False)
            cm = optimise(source, ga, gb, anchors, geo, geo.f_threshold)
            ci, cj, conf = cm.idx_a, cm.idx_b, cm.confidence
            stats.update(
                init=cm.init, history=cm.history, candidates=cm.candidates, refits=cm.refits_accepted
            )
    stats["coarse_matches"] = int(ci.numel())
    return ga[ci], gb[cj], conf.float()


def merge_parts(
    parts_a: list[torch.Tensor],
    parts_b: list[torch.Tensor],
    parts_s: list[torch.Tensor],
    radius: float,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Concatenate in priority order; a later match whose point in A or in B falls in an
    already-used ``radius`` cell is a duplicate of an earlier one and is dropped."""
    if not parts_a:
        z = torch.zeros(0, 2, device=device)
        return z, z.clone(), torch.zeros(0, device=device)
    pa, pb, ps = torch.cat(parts_a), torch.cat(parts_b), torch.cat(parts_s)
    if len(parts_a) == 1 or radius <= 0 or pa.shape[0] == 0:
        return pa, pb, ps
    keep = torch.arange(pa.shape[0], device=pa.device)
    for pts in (pa, pb):
        q = torch.floor(pts[keep] / radius).long()
        _, first = first_unique(q[:, 0] * 1_000_003 + q[:, 1])
        keep = keep[torch.sort(first).values]
    return pa[keep], pb[keep], ps[keep]
