"""A georeferenced model bundle-adjusted with its GPS fixes as position priors.

The similarity of georef.py moves a model into the fixes' frame without changing its shape,
which is right while the shape is better than the fixes. Over a large survey it is not: a nadir
flight of a thousand photos mapped globally bends (a bowl of a few metres over a kilometre, a
degree of camera tilt), and a similarity cannot unbend it. One bundle adjustment with each
camera centre pulled toward its fix (sigma: the fixes' own noise as the alignment estimated it)
lets the images keep every detail and the fixes fix the low frequencies; the fixes the alignment
called outliers (multipath, a stale fix) pull nothing. The priors are weak against thousands of
observations per image, so a well-shaped model barely moves.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pycolmap

from .georef import Alignment, camera_centres

# horizontal sigma (m) of the priors when the alignment did not estimate the fixes' noise (no
# barometric heights): a consumer GNSS receiver's
DEFAULT_SIGMA_M = 2.0
# vertical sigma as a multiple of the horizontal one: GNSS heights are that much worse
VERTICAL_FACTOR = 1.5
# fewer inlier fixes than this and the priors cannot say more than the similarity already did
MIN_PRIORS = 10
# residuals of the reprojections beyond about this many pixels count less (Cauchy)
LOSS_PX = 1.0


@dataclass(frozen=True)
class PriorAdjustment:
    priors: int
    sigma_m: float
    median_before_m: float
    median_after_m: float
    seconds: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "priors": self.priors,
            "sigma_m": round(self.sigma_m, 3),
            "median_before_m": round(self.median_before_m, 4),
            "median_after_m": round(self.median_after_m, 4),
            "seconds": round(self.seconds, 2),
        }


def _median_residual(rec: pycolmap.Reconstruction, enu: Mapping[str, np.ndarray], names: list[str]) -> float:
    centres = camera_centres(rec)
    return float(np.median([np.linalg.norm(centres[n] - enu[n]) for n in names]))


def adjust_to_fixes(
    rec: pycolmap.Reconstruction, enu: Mapping[str, np.ndarray], alignment: Alignment
) -> PriorAdjustment | None:
    """Bundle-adjust ``rec`` (already in the ENU frame of ``enu`` by ``alignment``) in place with
    the alignment's inlier fixes as position priors; None (``rec`` untouched) with fewer than
    MIN_PRIORS of them."""
    by_name = {im.name: iid for iid, im in rec.images.items() if im.has_pose}
    names = [
        n
        for n, inlier in zip(alignment.names, alignment.inliers, strict=True)
        if inlier and n in by_name and np.isfinite(enu[n]).all()
    ]
    if len(names) < MIN_PRIORS:
        return None
    h = alignment.heights
    estimated = h is not None and np.isfinite(h.gps_sigma_m) and h.gps_sigma_m > 0
    sigma = float(h.gps_sigma_m) if h is not None and estimated else DEFAULT_SIGMA_M
    cov = np.diag([sigma**2, sigma**2, (VERTICAL_FACTOR * sigma) ** 2])
    priors = []
    for n in names:
        p = pycolmap.PosePrior()
        p.corr_data_id = rec.images[by_name[n]].data_id
        p.position = np.asarray(enu[n], np.float64).reshape(3, 1)
        p.position_covariance = cov
        p.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        priors.append(p)
    before = _median_residual(rec, enu, names)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = LOSS_PX
    config = pycolmap.BundleAdjustmentConfig()
    for iid in by_name.values():
        config.add_image(iid)
    t0 = time.perf_counter()
    loglevel = int(pycolmap.logging.minloglevel)
    pycolmap.logging.minloglevel = max(loglevel, 2)  # Ceres' report is not the user's business
    try:
        adjuster = pycolmap.create_pose_prior_bundle_adjuster(
            options, pycolmap.PosePriorBundleAdjustmentOptions(), config, priors, rec
        )
        adjuster.solve()
    finally:
        pycolmap.logging.minloglevel = loglevel
    return PriorAdjustment(
        len(names), sigma, before, _median_residual(rec, enu, names), time.perf_counter() - t0
    )


def with_residuals(
    rec: pycolmap.Reconstruction, enu: Mapping[str, np.ndarray], alignment: Alignment
) -> Alignment:
    """``alignment`` with its residuals measured again on ``rec`` (after the adjustment moved the
    cameras); which fixes were inliers stays the alignment's."""
    centres = camera_centres(rec)
    pairs = zip(alignment.names, alignment.residuals, strict=True)
    residuals = np.array([np.linalg.norm(centres[n] - enu[n]) if n in centres else r for n, r in pairs])
    return replace(alignment, residuals=residuals)
