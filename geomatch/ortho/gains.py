"""Exposure balanced between photos: one gain per photo and colour channel, so that a seam
between a photo taken into the sun and one taken away from it does not show as a step.

The gains are Brown and Lowe's (Automatic Panoramic Image Stitching, 2007), as OpenCV's
GainCompensator solves them: over every pair of photos that see the same ground, the mean of
each over what both see should agree after the gains, with each gain held near 1 (so the map
keeps the photos' overall brightness):

    e = sum_ij N_ij ((g_i I_ij - g_j I_ji)^2 / sigma_n^2 + (1 - g_i)^2 / sigma_g^2)

``N_ij`` counts the ground samples both see and ``I_ij`` is photo i's mean over them, read from
thumbnails at sample positions spread over the DSM (visibility as for the mosaic).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from .dsm import Dsm
from .photos import PhotoCache, to_pixels
from .sight import sees
from .survey import Survey

SIGMA_N = 10.0  # intensity noise, 0-255
SIGMA_G = 0.1  # how far a gain may stray from 1 before it costs as much as a mismatch
MAX_SAMPLES = 40_000
THUMB_SIDE = 256
GAIN_RANGE = (0.5, 2.0)


def sample_positions(dsm: Dsm, max_samples: int = MAX_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Positions on a regular lattice over the DSM's valid area, at most about ``max_samples``."""
    g = dsm.grid
    area = float(dsm.valid.sum()) * g.res**2
    step = max(g.res, float(np.sqrt(area / max_samples)))
    k = max(1, round(step / g.res))
    e, n = g.centres(0, g.height, 0, g.width, step=k)
    inside = dsm.valid[::k, ::k][: e.shape[0], : e.shape[1]]
    return e[inside], n[inside]


def solve_gains(counts: np.ndarray, means: np.ndarray) -> np.ndarray:
    """Gains (P) from the pair counts N (P x P) and means I (P x P, I[i, j]: photo i's mean over
    what i and j both see)."""
    p = len(counts)
    alpha, beta = 1.0 / SIGMA_N**2, 1.0 / SIGMA_G**2
    a = np.zeros((p, p))
    b = np.zeros(p)
    for i in range(p):
        b[i] = beta * counts[i].sum()
        a[i, i] = beta * counts[i].sum()
        for j in np.flatnonzero(counts[i]):
            if j == i:
                continue
            a[i, i] += 2 * alpha * means[i, j] ** 2 * counts[i, j]
            a[i, j] -= 2 * alpha * means[i, j] * means[j, i] * counts[i, j]
    lonely = a.diagonal() == 0  # a photo that sees no sample keeps its exposure
    a[lonely, lonely] = 1.0
    b[lonely] = 1.0
    return np.clip(np.linalg.solve(a, b), *GAIN_RANGE)


def exposure_gains(survey: Survey, dsm: Dsm, photos: PhotoCache) -> np.ndarray:
    """(P, 3) gains, one row per view of ``survey``."""
    views = survey.views
    e, n = sample_positions(dsm)
    if len(e) == 0 or len(views) < 2:
        return np.ones((len(views), 3))
    z = dsm.at(e, n)
    xyz = survey.model_from_projected(np.column_stack([e, n, z]))
    rows, cols, vals = [], [], []
    for p, view in enumerate(views):
        uv, ok, _ = sees(view, dsm, xyz, e, n, z)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        thumb = photos.get(view, THUMB_SIDE / max(view.width, view.height))
        x, y = to_pixels(view, thumb, uv[idx])
        xi = np.clip(np.rint(x).astype(np.int64), 0, thumb.shape[1] - 1)
        yi = np.clip(np.rint(y).astype(np.int64), 0, thumb.shape[0] - 1)
        rows.append(idx)
        cols.append(np.full(idx.size, p))
        vals.append(thumb[yi, xi].astype(np.float64))
    if not rows:
        return np.ones((len(views), 3))
    r, c = np.concatenate(rows), np.concatenate(cols)
    v = np.concatenate(vals)
    shape = (len(e), len(views))
    seen = sparse.csr_matrix((np.ones(len(r)), (r, c)), shape=shape)
    counts = np.asarray((seen.T @ seen).todense())
    gains = np.ones((len(views), 3))
    for ch in range(3):
        value = sparse.csr_matrix((v[:, ch], (r, c)), shape=shape)
        sums = np.asarray((value.T @ seen).todense())  # [i, j]: i's values where i and j see
        with np.errstate(divide="ignore", invalid="ignore"):
            means = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
        gains[:, ch] = solve_gains(counts, means)
    return gains
