"""Which photo sees a place, and how well: the DSM visibility test and the score that picks the
photo an orthophoto pixel comes from.

Visibility: the ray from the ground position up to the camera is walked over the DSM, in steps
of about one DSM cell until it is above the DSM's highest point; a DSM height above the ray (by
more than half a cell, so that a slope under the ray's foot does not hide its own ground) means a
wall or a roof stands between. The score: the ray's angle from the vertical (a nadir view shows
the ground where it is and hides least behind buildings) plus a quarter of the distance from the
principal point as a fraction of the half-diagonal (the lens is sharpest and least distorted near
its centre), lower is better.
"""

from __future__ import annotations

import numpy as np

from .dsm import Dsm
from .photos import in_frame
from .survey import View

MAX_STEPS = 64
RADIAL_WEIGHT = 0.25


def visible(view: View, dsm: Dsm, e: np.ndarray, n: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Whether the camera sees the ground positions (flat arrays, projected) over the DSM."""
    c = view.centre
    dx, dy, dz = c[0] - e, c[1] - n, c[2] - z
    up = dz > 1e-6
    top = float(np.max(dsm.height))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_max = np.where(up, np.clip((top - z) / np.where(up, dz, 1.0), 0.0, 1.0), 0.0)
    reach = t_max * np.hypot(dx, dy)
    # each position's own number of steps (about one per DSM cell), so that its answer does not
    # depend on which other positions are asked with it
    own = np.clip(np.ceil(reach / dsm.cell), 1, MAX_STEPS)
    steps = int(own.max(initial=0.0))
    seen = up.copy()
    tol = 0.5 * dsm.cell
    for k in range(1, steps + 1):
        t = t_max * (np.minimum(k, own) / own)
        ground = dsm.at(e + t * dx, n + t * dy)
        seen &= ~(ground > z + t * dz + tol)
    return seen


def score(view: View, uv: np.ndarray, e: np.ndarray, n: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The off-nadir angle (radians) of the ray to the camera plus the radial term."""
    c = view.centre
    off_nadir = np.arctan2(np.hypot(c[0] - e, c[1] - n), c[2] - z)
    cx, cy = float(view.camera.principal_point_x), float(view.camera.principal_point_y)
    half_diag = 0.5 * float(np.hypot(view.width, view.height))
    radial = np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) / half_diag
    return off_nadir + RADIAL_WEIGHT * radial


def sees(
    view: View, dsm: Dsm, xyz_model: np.ndarray, e: np.ndarray, n: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For flat arrays of ground positions: the COLMAP pixels in ``view``, whether it sees them
    (in its frame, in front, not hidden by the DSM) and their score (inf where unseen)."""
    uv, depth = view.project(xyz_model)
    ok = in_frame(view, uv, depth)
    if ok.any():
        idx = np.flatnonzero(ok)
        ok[idx] = visible(view, dsm, e[idx], n[idx], z[idx])
    s = np.full(len(e), np.inf)
    if ok.any():
        s[ok] = score(view, uv[ok], e[ok], n[ok], z[ok])
    return uv, ok, s
