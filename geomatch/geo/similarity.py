"""Least-squares similarity between two point sets (Umeyama 1991), in numpy.

Not pycolmap's ``estimate_sim3d``: in pycolmap 4.2 it answers None for three points whenever the
raw target matrix is rank-deficient, e.g. when one target is exactly the origin. The ENU frame
is centred on the project's first fix, so that first fix is always (0, 0, 0), and every
three-fix project would stay un-georeferenced (tests/test_gps.py).
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


def _no_fit() -> Similarity:
    """What the fits answer when there is none to give: a NaN scale, which every caller checks."""
    return Similarity(float("nan"), np.eye(3), np.zeros(3))


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity taking ``src`` (N, 3) to ``dst`` (N >= 3); a degenerate
    ``src`` (all points equal) gives a NaN scale, which the callers skip, and so do points that
    are not finite. Collinear sets give
    a valid fit whose rotation about the line is arbitrary: callers that sample triples
    reject those first."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        return _no_fit()  # LAPACK's SVD does not converge on NaN or infinity: it raises
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var = (a**2).sum() / len(src)
    if not var > 0:
        return _no_fit()
    try:
        u, d, vt = np.linalg.svd(b.T @ a / len(src))
    except np.linalg.LinAlgError:
        return _no_fit()
    s = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2] = -1.0
    R = u @ np.diag(s) @ vt
    scale = float((d * s).sum() / var)
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def umeyama_upright(src: np.ndarray, dst: np.ndarray, up: np.ndarray, vertical_weight: float) -> Similarity:
    """Least-squares similarity whose rotation takes ``up`` (a unit vector in ``src``'s frame) to
    +z of ``dst``: only the turn about the vertical, the scale and the translation are fitted
    (5 parameters, not 7), and vertical residuals weigh ``vertical_weight`` (1 / variance ratio)
    against horizontal ones. Closed form: the best turn does not depend on the scale (2D
    Procrustes), and the weighted cost is then a quadratic in the scale."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if not (np.isfinite(src).all() and np.isfinite(dst).all() and np.isfinite(up).all()):
        return _no_fit()
    Ru, Rz = _upright_rotations(src, dst, up)
    A = src @ Ru.T
    A -= A.mean(0)
    B = dst - dst.mean(0)
    rotated = A @ Rz.T
    denom = (A[:, :2] ** 2).sum() + vertical_weight * (A[:, 2] ** 2).sum()
    if not denom > 0:
        return _no_fit()
    scale = float(((rotated[:, :2] * B[:, :2]).sum() + vertical_weight * (A[:, 2] * B[:, 2]).sum()) / denom)
    R = Rz @ Ru
    return Similarity(scale, R, dst.mean(0) - scale * R @ src.mean(0))


@dataclass(frozen=True)
class HeightFit:
    """An upright similarity fitted to positions and to heights above an unknown datum."""

    sim: Similarity
    datum: float  # h = (sim.apply(x))_z - datum: the heights' zero in dst's vertical
    redundancy: np.ndarray  # (3 N + M,) each observation's share of the redundancy (1 - leverage)


def upright_with_heights(
    src: np.ndarray,
    dst: np.ndarray,
    up: np.ndarray,
    vertical_weight: float,
    height_src: np.ndarray,
    heights: np.ndarray,
    height_weight: float,
) -> HeightFit:
    """As umeyama_upright, plus heights ``heights`` (M,) of the points ``height_src`` (M, 3) above
    a datum of unknown level, weighing ``height_weight`` against a horizontal residual: a drone's
    barometric heights above take-off differ by metres over a flight known to decimetres, a
    scale that GNSS's metres cannot give. The turn still comes from the horizontal Procrustes
    (the only term that depends on it); scale, translation and datum are then one weighted
    linear least squares. The redundancies let the caller estimate both noise levels."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    Ru, Rz = _upright_rotations(src, dst, up)
    R = Rz @ Ru
    p = src @ R.T
    ph = np.asarray(height_src, np.float64) @ R.T
    n, m = len(src), len(ph)
    M = np.zeros((3 * n + m, 5))
    M[0 : 3 * n : 3, 0], M[0 : 3 * n : 3, 1] = p[:, 0], 1.0
    M[1 : 3 * n : 3, 0], M[1 : 3 * n : 3, 2] = p[:, 1], 1.0
    M[2 : 3 * n : 3, 0], M[2 : 3 * n : 3, 3] = p[:, 2], 1.0
    M[3 * n :, 0], M[3 * n :, 3], M[3 * n :, 4] = ph[:, 2], 1.0, -1.0
    y = np.concatenate([dst.reshape(-1), np.asarray(heights, np.float64)])
    w = np.concatenate([np.tile([1.0, 1.0, vertical_weight], n), np.full(m, height_weight)])
    Mw = M * np.sqrt(w)[:, None]
    x, *_ = np.linalg.lstsq(Mw, y * np.sqrt(w), rcond=None)
    leverage = np.einsum("ij,ji->i", Mw, np.linalg.pinv(Mw.T @ Mw) @ Mw.T)
    return HeightFit(Similarity(float(x[0]), R, x[1:4].copy()), float(x[4]), 1.0 - leverage)


def _upright_rotations(src: np.ndarray, dst: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tilt taking ``up`` to +z, and the turn about +z that best lines the tilted, centred
    ``src`` up with the centred ``dst`` east and north (2D Procrustes)."""
    Ru = _rotation_between(np.asarray(up, np.float64), np.array([0.0, 0.0, 1.0]))
    A = src @ Ru.T
    A, B = A - A.mean(0), dst - dst.mean(0)
    theta = np.arctan2((A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]).sum(), (A[:, :2] * B[:, :2]).sum())
    c, s = np.cos(theta), np.sin(theta)
    return Ru, np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` to unit vector ``v`` (Rodrigues)."""
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis, c = np.cross(u, v), float(u @ v)
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis normal to u
        n = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        n /= np.linalg.norm(n)
        return 2.0 * np.outer(n, n) - np.eye(3)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)
