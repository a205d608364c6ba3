"""Air-to-ground tiling (paper section 4.1).

An aerial image sees the ground scene at a fraction of the scale a ground camera does; shrunk
to the network's working size its detail is lost. Matching its four quadrants and a centre crop
separately, each at the working size, gives the networks that detail back. Matches of the five
crops are mapped back to the aerial image's full-resolution frame and merged: two matches whose
endpoints fall in the same ``dedup_px`` cell in both images are one match (the first, i.e. the
higher-scoring, is kept), so the overlap of the centre crop with the quadrants adds no duplicates.
Only the crops where a cheap probe finds the overlap are matched (:func:`select_crops`; the probe
itself runs in geomatch.matching.probes.tile_crops).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from ..epipolar.geometry import fundamental_from_matches


@dataclass(frozen=True)
class Crop:
    """A window of the full image; crop pixel (u, v) is full pixel (u + x0, v + y0)."""

    name: str
    x0: int
    y0: int
    width: int
    height: int

    def cut(self, image: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(image[self.y0 : self.y0 + self.height, self.x0 : self.x0 + self.width])

    def to_full(self, points: np.ndarray) -> np.ndarray:
        """Crop pixels -> full-image pixels. Pixel centres are at integers in both frames, so a
        crop is a pure integer shift and the round trip is exact."""
        return np.asarray(points, dtype=np.float64) + np.array([self.x0, self.y0], dtype=np.float64)

    def from_full(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) - np.array([self.x0, self.y0], dtype=np.float64)

    def contains(self, points: np.ndarray) -> np.ndarray:
        p = self.from_full(points)
        return (
            (p[:, 0] >= -0.5)
            & (p[:, 1] >= -0.5)
            & (p[:, 0] < self.width - 0.5)
            & (p[:, 1] < self.height - 0.5)
        )


def five_crops(width: int, height: int) -> list[Crop]:
    """The four quadrants and a centre crop of the same half-size."""
    hw, hh = (width + 1) // 2, (height + 1) // 2  # odd sizes: quadrants overlap by a pixel, no gap
    return [
        Crop("top_left", 0, 0, hw, hh),
        Crop("top_right", width - hw, 0, hw, hh),
        Crop("bottom_left", 0, height - hh, hw, hh),
        Crop("bottom_right", width - hw, height - hh, hw, hh),
        Crop("centre", (width - hw) // 2, (height - hh) // 2, hw, hh),
    ]


# crop selection from the cheap probe's matches (``select_crops``): below this many F-consistent
# probe matches the probe cannot tell where the overlap is and every crop is matched (a tiled
# pair reaches that only with MatcherConfig.tile_min_probe off: by default such a pair matches no
# crop); otherwise crops are taken, the one holding most uncovered probe matches first, until
# they hold ``SELECT_COVERAGE`` of them
SELECT_MIN_PROBE = 24
SELECT_COVERAGE = 0.9


def select_crops(
    crops: Sequence[Crop],
    points: np.ndarray,
    min_probe: int = SELECT_MIN_PROBE,
    coverage: float = SELECT_COVERAGE,
) -> list[Crop]:
    """The crops worth matching, given where the aerial image's probe matches lie (full frame).

    Why: a ground camera sees a part of the site, so most of an aerial image's crops hold little
    of it; each crop costs a full-strength LightGlue call, the optimizer and the refinement, so
    matching all five makes a tiled pair many times a plain one (docs/benchmarks.md, "What tiling
    costs"). Greedy set cover keeps
    the matched crops few and still covers where the overlap is. Order is the crops' own.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if len(pts) < min_probe:
        return list(crops)
    inside = np.stack([c.contains(pts) for c in crops])  # (crops, points)
    covered = np.zeros(len(pts), bool)
    chosen: set[int] = set()
    while covered.mean() < coverage:
        gain = (inside & ~covered).sum(1)
        best = int(np.argmax(gain))
        if gain[best] == 0:
            break
        chosen.add(best)
        covered |= inside[best]
    return [c for i, c in enumerate(crops) if i in chosen]


class _PairResult(Protocol):
    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray


class _PairMatcher(Protocol):
    def match(self, image0: np.ndarray, image1: np.ndarray) -> _PairResult: ...


@dataclass
class TiledMatches:
    keypoints0: np.ndarray  # (N, 2) in the FIRST image's full frame
    keypoints1: np.ndarray
    scores: np.ndarray
    per_crop: dict[str, int]  # matches each crop contributed before merging

    def __len__(self) -> int:
        return int(self.keypoints0.shape[0])

    @cached_property
    def F(self) -> np.ndarray:
        """x1^T F x0 = 0 over the merged matches (zeros when it cannot be fitted); fitted on first
        use only, since the pipeline verifies pairs in the database writer instead."""
        return fundamental_from_matches(self.keypoints0, self.keypoints1)


def merge_matches(
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], dedup_px: float = 2.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate, sort by score, drop a match whose endpoint in either image lands in a
    ``dedup_px`` cell an earlier (better) match already used."""
    if not parts:
        z = np.zeros((0, 2), np.float32)
        return z, z.copy(), np.zeros(0, np.float32)
    k0 = np.concatenate([p[0] for p in parts]).astype(np.float64)
    k1 = np.concatenate([p[1] for p in parts]).astype(np.float64)
    sc = np.concatenate([p[2] for p in parts]).astype(np.float32)
    order = np.argsort(-sc, kind="stable")
    k0, k1, sc = k0[order], k1[order], sc[order]
    keep = np.ones(len(sc), bool)
    for pts in (k0, k1):
        cells = np.floor(pts / dedup_px).astype(np.int64)
        idx = np.flatnonzero(keep)
        _, first = np.unique(cells[idx], axis=0, return_index=True)
        mask = np.zeros(len(sc), bool)
        mask[idx[first]] = True
        keep &= mask
    return k0[keep].astype(np.float32), k1[keep].astype(np.float32), sc[keep]


def match_tiled(
    matcher: _PairMatcher,
    aerial: np.ndarray,
    other: np.ndarray,
    aerial_first: bool = True,
    dedup_px: float = 2.0,
    crops: Sequence[Crop] | None = None,
    min_crop_matches: int = 0,
) -> TiledMatches:
    """Match the aerial image's crops (``crops``, default the five) against ``other`` and merge in
    the full frame; a crop with fewer than ``min_crop_matches`` matches adds none (``per_crop``
    still counts them).

    ``aerial_first`` keeps the caller's pair order: keypoints0 belong to the first image of the
    pair as the caller named it.
    """
    h, w = aerial.shape[:2]
    parts = []
    per_crop: dict[str, int] = {}
    for crop in five_crops(w, h) if crops is None else crops:
        r = matcher.match(crop.cut(aerial), other)
        per_crop[crop.name] = len(r.scores)
        if len(r.scores) < min_crop_matches:
            continue
        parts.append((crop.to_full(r.keypoints0), np.asarray(r.keypoints1, np.float64), r.scores))
    ka, ko, sc = merge_matches(parts, dedup_px)
    k0, k1 = (ka, ko) if aerial_first else (ko, ka)
    return TiledMatches(k0, k1, sc, per_crop)
