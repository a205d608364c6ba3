"""How far an orthophoto's content lies from where it should: patch by patch, the shift that
best aligns it with a reference image of the same grid (the truth of a synthetic scene, rendered
from its ground texture), by phase correlation.

Patches with any transparent pixel, or too little texture to lock onto (a flat colour shifts
freely), give no answer; the shifts are in map pixels, i.e. in GSD.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PATCH = 64
MIN_TEXTURE = 6.0  # grey-level standard deviation below which a patch is skipped
MIN_RESPONSE = 0.1  # phase correlation's peak below which the shift is not trusted


@dataclass(frozen=True)
class Offsets:
    shifts: np.ndarray  # (K, 2) dx, dy in pixels of the map (east, south)
    centres: np.ndarray  # (K, 2) row, col of each patch's centre

    @property
    def errors(self) -> np.ndarray:
        return np.hypot(self.shifts[:, 0], self.shifts[:, 1])

    def summary(self) -> dict[str, float]:
        err = self.errors
        if err.size == 0:
            return {"patches": 0}
        return {
            "patches": int(err.size),
            "median_gsd": float(np.median(err)),
            "p95_gsd": float(np.percentile(err, 95)),
            "max_gsd": float(err.max()),
            "mean_dx": float(np.mean(self.shifts[:, 0])),
            "mean_dy": float(np.mean(self.shifts[:, 1])),
        }


def grey(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(
        cv2.cvtColor(np.ascontiguousarray(rgb[..., :3]).astype(np.uint8), cv2.COLOR_RGB2GRAY), np.float32
    )


def patch_offsets(
    ortho: np.ndarray, truth: np.ndarray, patch: int = PATCH, skip: np.ndarray | None = None
) -> Offsets:
    """Shifts of ``ortho`` (H, W, 4 RGBA) against ``truth`` (H, W, 3) over a lattice of patches;
    ``skip`` (H, W bool) marks pixels a patch must not touch (buildings, on a flat-ground test)."""
    a, b = grey(ortho), grey(truth)
    alpha = ortho[..., 3] > 0
    window = cv2.createHanningWindow((patch, patch), cv2.CV_32F)
    shifts, centres = [], []
    h, w = a.shape
    for r in range(0, h - patch + 1, patch):
        for c in range(0, w - patch + 1, patch):
            sl = np.s_[r : r + patch, c : c + patch]
            if not alpha[sl].all() or (skip is not None and skip[sl].any()):
                continue
            pa, pb = a[sl], b[sl]
            if pb.std() < MIN_TEXTURE or pa.std() < MIN_TEXTURE:
                continue
            (dx, dy), response = cv2.phaseCorrelate(pb, pa, window)
            if response < MIN_RESPONSE:
                continue
            shifts.append((dx, dy))
            centres.append((r + patch / 2, c + patch / 2))
    return Offsets(np.array(shifts, np.float64).reshape(-1, 2), np.array(centres, np.float64).reshape(-1, 2))
