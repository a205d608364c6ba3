"""Cameras a georeferenced model puts farther from their own GPS fixes than the fixes' noise allows.

Why: once most cameras of a model agree with their fixes to within the receiver's noise, a camera
tens or hundreds of metres from its fix is evidence of a wrong registration (a pair across two
look-alike fields, a return leg matched to the wrong line), not of a bad fix: a consumer receiver
misses by a few metres, and the chance that an honest fix lies five of its sigmas away is about
one in a hundred thousand. So the fitted noise of the agreeing majority sets a limit, and the
mapping takes out, or places again, every camera beyond it (sfm/leftovers.py), and the summary
and the survey report name each one.

The noise is estimated from the cameras themselves: with horizontal sigma ``s`` and vertical
``GNSS_VERTICAL_FACTOR * s``, a camera's normalised residual sqrt(dE^2 + dN^2 + (dU / 1.5)^2) / s
follows a chi distribution with three degrees of freedom, whose median is CHI3_MEDIAN; the median
over the cameras is robust to a minority of wrong ones (up to half).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pycolmap

from .georef import GNSS_VERTICAL_FACTOR, camera_centres

CHI3_MEDIAN = 1.5382  # median of the chi distribution with 3 degrees of freedom
# a camera more than this many fitted sigmas from its fix contradicts it (an honest fix: ~1e-5)
LIMIT_SIGMAS = 5.0
# the limit never falls below this many metres: with fixes of centimetres (RTK) or a small site,
# the model's own drift of a few decimetres is no evidence of a wrong camera
MIN_LIMIT_M = 2.0
# fewer cameras with a fix than this and their median says too little about the noise
MIN_CAMERAS = 6


@dataclass(frozen=True)
class Offender:
    name: str
    residual_m: float  # 3D distance from the camera centre to its fix


@dataclass(frozen=True)
class GpsCheck:
    """A model's cameras held to their fixes: the noise fitted from all of them, the limit it
    sets, and the cameras beyond it."""

    cameras: int
    sigma_m: float  # horizontal sigma of the fixes, as the cameras' residuals say (vertical x1.5)
    limit_m: float
    offenders: tuple[Offender, ...] = ()
    # what the mapping did with them (sfm/leftovers.py): placed again within the limit, or taken out
    replaced: tuple[Offender, ...] = ()
    taken_out: tuple[Offender, ...] = ()
    # cameras kept beyond the limit: their fix is off the photos' own flight track and the camera
    # is on it (a stale or wild fix, not a wrong registration: off_track)
    wild_fixes: tuple[Offender, ...] = ()
    residuals: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "cameras": self.cameras,
            "sigma_m": round(self.sigma_m, 3),
            "limit_m": round(self.limit_m, 3),
            "found": [{"name": o.name, "residual_m": round(o.residual_m, 2)} for o in self.offenders],
            "placed_again": [{"name": o.name, "residual_m": round(o.residual_m, 2)} for o in self.replaced],
            "taken_out": [{"name": o.name, "residual_m": round(o.residual_m, 2)} for o in self.taken_out],
            "kept_fix_off_track": [
                {"name": o.name, "residual_m": round(o.residual_m, 2)} for o in self.wild_fixes
            ],
        }


def normalised(d: np.ndarray) -> np.ndarray:
    """(N, 3) ENU differences as distances in horizontal-sigma units of one: the vertical counts
    1 / GNSS_VERTICAL_FACTOR as much."""
    d = np.asarray(d, np.float64).reshape(-1, 3)
    return np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + (d[:, 2] / GNSS_VERTICAL_FACTOR) ** 2)


def check(
    rec: pycolmap.Reconstruction,
    enu: Mapping[str, np.ndarray],
    limit_sigmas: float = LIMIT_SIGMAS,
    min_limit_m: float = MIN_LIMIT_M,
) -> GpsCheck | None:
    """The cameras of ``rec`` (already in the fixes' ENU frame) that contradict their fixes; None
    with fewer than MIN_CAMERAS registered images with a finite fix."""
    centres = camera_centres(rec)
    names = sorted(n for n in centres if n in enu and np.isfinite(enu[n]).all())
    if len(names) < MIN_CAMERAS:
        return None
    diff = np.stack([centres[n] - np.asarray(enu[n], np.float64) for n in names])
    if not np.isfinite(diff).all():
        return None
    q = normalised(diff)
    sigma = float(np.median(q)) / CHI3_MEDIAN
    # the limit is in normalised metres; a camera's 3D residual is what a user reads
    limit = max(limit_sigmas * sigma, min_limit_m)
    dist = np.linalg.norm(diff, axis=1)
    beyond_limit = [Offender(n, float(r)) for n, r, qi in zip(names, dist, q, strict=True) if qi > limit]
    wild = [o for o in beyond_limit if off_track(o.name, centres[o.name], enu, limit)]
    offenders = [o for o in beyond_limit if o not in wild]
    return GpsCheck(
        cameras=len(names),
        sigma_m=sigma,
        limit_m=limit,
        offenders=tuple(sorted(offenders, key=lambda o: -o.residual_m)),
        residuals={n: float(r) for n, r in zip(names, dist, strict=True)},
        wild_fixes=tuple(sorted(wild, key=lambda o: -o.residual_m)),
    )


def off_track(name: str, centre: np.ndarray, enu: Mapping[str, np.ndarray], limit_m: float) -> bool:
    """Whether the photo's fix is what is wrong: it lies off the flight track its neighbours in
    capture order draw (file names are a camera's counter) while the camera lies on it. Why: a
    stale fix after take-off or a multipath jump breaks the track, a wrong registration does not
    (its fix is as honest as its neighbours'); the images cannot tell the two apart, the track can.
    The track between the photos before and after is taken as their midpoint, within the limit
    plus half their distance (a turn bends it by less)."""
    ordered = sorted(n for n, e in enu.items() if np.isfinite(e).all())
    i = ordered.index(name) if name in ordered else -1
    if i <= 0 or i >= len(ordered) - 1:
        return False
    before, after = (np.asarray(enu[ordered[j]], np.float64) for j in (i - 1, i + 1))
    middle = (before + after) / 2
    slack = limit_m + 0.5 * float(np.linalg.norm(after[:2] - before[:2]))
    fix_off = normalised(np.asarray(enu[name], np.float64) - middle)[0] > slack
    camera_on = normalised(np.asarray(centre, np.float64) - middle)[0] <= slack
    return bool(fix_off and camera_on)


def beyond(rec: pycolmap.Reconstruction, enu: Mapping[str, np.ndarray], limit_m: float) -> list[Offender]:
    """The registered cameras of ``rec`` farther than ``limit_m`` (normalised as :func:`check`)
    from their fixes: the same limit applied to a model after images were placed again."""
    centres = camera_centres(rec)
    out = []
    for n, c in centres.items():
        if n in enu and np.isfinite(enu[n]).all():
            d = c - np.asarray(enu[n], np.float64)
            if normalised(d)[0] > limit_m:
                out.append(Offender(n, float(np.linalg.norm(d))))
    return sorted(out, key=lambda o: -o.residual_m)
