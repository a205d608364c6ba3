"""Least-squares similarity between two point sets (Umeyama 1991), in numpy.

Not pycolmap's ``estimate_sim3d``: in pycolmap 4.2 it answers None for three points whenever the
raw target matrix is rank-deficient, e.g. when one target is exactly the origin. The ENU frame
is centred on the project's first fix, so that first fix is always (0, 0, 0), and every
three-fix project then stayed un-georeferenced (tests/test_gps.py, the CI failure of session 9).
Umeyama works on centred coordinates and has no such condition.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap


@dataclass(frozen=True)
class Similarity:
    """dst = scale * R @ src + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, np.float64) @ self.R.T + self.t

    def to_pycolmap(self) -> pycolmap.Sim3d:
        return pycolmap.Sim3d(self.scale, pycolmap.Rotation3d(self.R), self.t.reshape(3, 1))


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity taking ``src`` (N, 3) to ``dst`` (N >= 3); a degenerate
    ``src`` (all points equal) gives a NaN scale, which the callers skip. Collinear sets give
    a valid fit whose rotation about the line is arbitrary: callers that sample triples
    reject those first."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var = (a**2).sum() / len(src)
    if not var > 0:
        return Similarity(float("nan"), np.eye(3), np.zeros(3))
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    s = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2] = -1.0
    R = u @ np.diag(s) @ vt
    scale = float((d * s).sum() / var)
    return Similarity(scale, R, mu_d - scale * R @ mu_s)
