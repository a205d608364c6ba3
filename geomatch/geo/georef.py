"""Put a reconstruction into the GPS fixes' ENU frame: a robust similarity from camera centres.

SfM fixes the shape up to a similarity; GPS fixes where the cameras are, within metres and with
the odd wild fix (multipath near walls, a stale fix after take-off). So the similarity comes
from RANSAC over minimal 3-centre samples (Umeyama's closed form on each, similarity.py), scored by how many
centres land within ``threshold`` metres of their fix, then Umeyama least squares on the
inliers. Only the shape of the reconstruction and the similarity's 7 parameters come from the
data, so with n fixes of sigma s the centres' error is about s * sqrt(7 / (3 n)) (the
reconstruction averages the GPS noise out instead of taking it on, as pose-prior bundle
adjustment would when its priors are weighted above the image evidence). A drone's metadata
narrows it further: its gimbal's gravity fixes two of the 7 parameters (the tilt), and its
barometric heights above take-off pin the scale, which the fixes' metres over a small site
cannot (fit_with_heights).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .geodesy import EnuFrame
from .gps import GpsFixes
from .similarity import Similarity, umeyama, umeyama_upright, upright_with_heights

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HeightUse:
    images: int  # heights kept (the others lay beyond the gate from the rest: another take-off)
    height_sigma_m: float  # their noise, estimated from the fit (variance components)
    gps_sigma_m: float  # the fixes' horizontal noise, estimated alongside


@dataclass(frozen=True)
class Alignment:
    sim: Similarity
    inliers: np.ndarray  # (N,) bool
    residuals: np.ndarray  # (N,) metres, every correspondence
    up_images: int = 0  # images whose gimbal fixed the model's vertical (0: a free 7-parameter fit)
    heights: HeightUse | None = None  # the barometric heights the fit used, if any
    names: tuple[str, ...] = ()  # the image of each correspondence (residuals, inliers)

    def as_dict(self) -> dict[str, Any]:
        r = self.residuals[self.inliers]
        return {
            "correspondences": len(self.residuals),
            "inliers": int(self.inliers.sum()),
            "rmse_m": float(np.sqrt(np.mean(r**2))) if len(r) else None,
            "median_m": float(np.median(r)) if len(r) else None,
            "max_inlier_m": float(r.max()) if len(r) else None,
            "scale": self.sim.scale,
            "gravity_images": self.up_images,
            "height_images": self.heights.images if self.heights else 0,
            "height_sigma_m": self.heights.height_sigma_m if self.heights else None,
            "gps_sigma_m": self.heights.gps_sigma_m if self.heights else None,
            # per photo: a survey report names the fixes that disagree with the model
            "per_image": [
                {"name": n, "residual_m": round(float(r), 4), "inlier": bool(i)}
                for n, r, i in zip(self.names, self.residuals, self.inliers, strict=True)
            ]
            if len(self.names) == len(self.residuals)
            else [],
        }


GNSS_VERTICAL_FACTOR = 1.5  # consumer GNSS: vertical error about 1.5x the horizontal one
UP_MAX_SPREAD_DEG = 3.0  # gimbal "up"s further than this from the consensus are not trusted
# Barometric heights (DJI RelativeAltitude) next to the fixes: the noise levels the weighting starts
# from (consumer GNSS, a barometer over one flight), re-estimated from the fit's own residuals
PRIOR_GPS_SIGMA_M = 2.0
PRIOR_HEIGHT_SIGMA_M = 0.3
MIN_HEIGHT_SIGMA_M = 0.05  # below what a barometer resolves: keeps a few lucky heights from taking over
MIN_HEIGHTS = 4  # fewer leave too little redundancy to estimate their noise
HEIGHT_GATE_M = 1.5  # a height is dropped beyond max(this, 3 MADs) from the rest (another take-off)


def robust_similarity(
    src: np.ndarray,
    dst: np.ndarray,
    threshold: float = 10.0,
    iterations: int = 500,
    seed: int = 0,
    up: np.ndarray | None = None,
) -> Alignment | None:
    """RANSAC similarity src -> dst; None with fewer than 3 correspondences or when no sample
    spans a plane. ``threshold``: metres in ``dst``; 10 m is about three times the 3D error of
    consumer GNSS (2 m horizontal, 3 m vertical sigma); a tighter one rejects honest fixes and
    makes the fit worse (docs/benchmarks.md, "GPS: georeferencing accuracy").
    ``up``: the world's up in ``src``'s frame, when the cameras' gravity gives it: the fit is then
    upright (similarity.umeyama_upright, vertical residuals weighted by 1 / 1.5^2)."""

    def fit(a: np.ndarray, b: np.ndarray) -> Similarity:
        if up is None:
            return umeyama(a, b)
        return umeyama_upright(a, b, up, 1.0 / GNSS_VERTICAL_FACTOR**2)

    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    # a correspondence that is not finite is never sampled nor an inlier (its residual is NaN,
    # which no threshold passes): one NaN fix in a sample would make the SVD raise and fail the job
    usable = np.flatnonzero(np.isfinite(src).all(1) & np.isfinite(dst).all(1))
    n = len(usable)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    best_cost = np.inf
    samples = [usable] if n == 3 else (rng.choice(usable, 3, replace=False) for _ in range(iterations))
    spread = max(float(np.ptp(src[usable])), 1e-12)
    for idx in samples:
        a = src[idx]
        # a (near-)collinear sample leaves the rotation about its line free
        if np.linalg.norm(np.cross(a[1] - a[0], a[2] - a[0])) < 1e-9 * spread**2:
            continue
        sim = fit(a, dst[idx])
        if not np.isfinite(sim.scale) or sim.scale <= 0:
            continue
        r = np.linalg.norm(sim.apply(src) - dst, axis=1)
        inl = r < threshold
        cost = np.minimum(r[usable], threshold).sum()  # MSAC: the inliers' fit counts, not only their number
        if inl.sum() >= 3 and cost < best_cost:
            best, best_cost = inl, cost
    if best is None:
        return None
    inl = best
    for _ in range(3):  # refit on the inliers until the set settles
        sim = fit(src[inl], dst[inl])
        r = np.linalg.norm(sim.apply(src) - dst, axis=1)
        new = r < threshold
        if new.sum() < 3 or np.array_equal(new, inl):
            break
        inl = new
    sim = fit(src[inl], dst[inl])
    r = np.linalg.norm(sim.apply(src) - dst, axis=1)
    return Alignment(sim, inl, r)


def fit_with_heights(
    src: np.ndarray,
    dst: np.ndarray,
    up: np.ndarray,
    start: Similarity,
    height_src: np.ndarray,
    heights: np.ndarray,
) -> tuple[Similarity, HeightUse] | None:
    """The upright similarity refitted with the drone's barometric heights above take-off
    (similarity.upright_with_heights): their differences over a flight fix the scale to a
    fraction of what GNSS metres can (bench/georef_accuracy.py). Neither noise level is known
    beforehand, so both are estimated from the residuals (Foerstner's variance components,
    iterated), and a height further than the gate from the others (a second flight with its own
    take-off, a stale reading) is dropped. ``start``: the GNSS-only fit, which picks the first
    heights to keep. None when fewer than MIN_HEIGHTS agree."""
    heights, height_src = np.asarray(heights, np.float64), np.asarray(height_src, np.float64)
    finite = np.isfinite(heights) & np.isfinite(height_src).all(1)  # least squares cannot take NaN
    heights, height_src = heights[finite], height_src[finite]
    n, vw = len(src), 1.0 / GNSS_VERTICAL_FACTOR**2

    def predicted(sim: Similarity) -> np.ndarray:
        return sim.apply(height_src)[:, 2]

    # which heights belong is judged once, against the GNSS-only fit and from every height's
    # scatter (median absolute deviation): a gate re-drawn around a fit that follows the kept
    # heights shrinks onto whichever few happen to agree
    r0 = heights - predicted(start)
    dev = np.abs(r0 - np.median(r0))
    keep = dev <= max(HEIGHT_GATE_M, 3 * 1.4826 * float(np.median(dev)))
    if keep.sum() < MIN_HEIGHTS:
        return None
    sg, sh = PRIOR_GPS_SIGMA_M, PRIOR_HEIGHT_SIGMA_M
    for _ in range(30):
        fit = upright_with_heights(src, dst, up, vw, height_src[keep], heights[keep], (sg / sh) ** 2)
        rg = fit.sim.apply(src) - dst
        rh = heights[keep] - (predicted(fit.sim)[keep] - fit.datum)
        red_g, red_h = fit.redundancy[: 3 * n].sum(), fit.redundancy[3 * n :].sum()
        new_sg = np.sqrt(((rg[:, :2] ** 2).sum() + vw * (rg[:, 2] ** 2).sum()) / max(red_g, 1e-9))
        new_sh = max(np.sqrt((rh**2).sum() / max(red_h, 1e-9)), MIN_HEIGHT_SIGMA_M)
        settled = abs(new_sg / sg - 1) < 1e-4 and abs(new_sh / sh - 1) < 1e-4
        sg, sh = float(new_sg), float(new_sh)
        if settled:
            break
    return fit.sim, HeightUse(int(keep.sum()), sh, sg)


def camera_centres(rec: pycolmap.Reconstruction) -> dict[str, np.ndarray]:
    return {
        im.name: np.asarray(im.projection_center(), np.float64) for im in rec.images.values() if im.has_pose
    }


def model_up(rec: pycolmap.Reconstruction, up_cam: Mapping[str, np.ndarray]) -> tuple[np.ndarray, int] | None:
    """The world's up in the model's frame, from the registered images whose gimbal says where
    up is in the camera: each image's up carried into the model by its rotation, averaged over
    those within 3 degrees of the consensus. None unless two or more agree: one gimbal alone is
    not trusted to tilt a whole model."""
    carried = (
        np.asarray(im.cam_from_world().rotation.matrix()).T @ up_cam[im.name]
        for im in rec.images.values()
        if im.has_pose and im.name in up_cam
    )
    ups = [u for u in carried if np.isfinite(u).all()]
    if len(ups) < 2:
        return None
    U = np.stack(ups)
    keep = np.ones(len(U), bool)
    for _ in range(3):
        m = U[keep].mean(0)
        m /= np.linalg.norm(m)
        keep = np.degrees(np.arccos(np.clip(U @ m, -1.0, 1.0))) <= UP_MAX_SPREAD_DEG
        if keep.sum() < 2:
            return None
    m = U[keep].mean(0)
    return m / np.linalg.norm(m), int(keep.sum())


def align(
    rec: pycolmap.Reconstruction,
    enu: Mapping[str, np.ndarray],
    threshold: float = 10.0,
    up_cam: Mapping[str, np.ndarray] | None = None,
    heights: Mapping[str, float] | None = None,
) -> Alignment | None:
    """Estimate the similarity from the registered images that have a fix and apply it to
    ``rec`` in place (every image and point, those without GPS too); None leaves ``rec`` as it
    was (fewer than 3 registered images with a fix). With ``up_cam`` (image name -> up in the
    camera, gps.GpsFixes.up) and two or more registered images agreeing on it, the model's
    vertical comes from gravity and GPS fits the other 5 parameters, which lowers the centres'
    error (docs/benchmarks.md, "GPS: georeferencing accuracy").
    With gravity and ``heights`` (image name -> barometric height above take-off,
    gps.GpsFixes.heights) of MIN_HEIGHTS or more registered images, those refine the fit
    (fit_with_heights), the GNSS inliers staying as RANSAC chose them.

    Fixes, ups and heights that are not finite are left out, and a fit that fails anyway (an
    error of the linear algebra, a similarity that is not finite) leaves ``rec`` as it was, with
    a warning: a model that cannot be georeferenced is still a model, and an SVD error on one
    NaN altitude must not fail the whole reconstruct job."""
    centres = camera_centres(rec)
    names = sorted(n for n in centres if n in enu and np.isfinite(enu[n]).all())
    if len(names) < 3:
        return None
    try:
        result = _fit(centres, names, enu, threshold, rec, up_cam, heights)
    except np.linalg.LinAlgError as e:
        log.warning("georeferencing skipped: the fit failed (%s)", e)
        return None
    if result is None:
        return None
    sim = result.sim
    if not (
        np.isfinite(sim.scale) and sim.scale > 0 and np.isfinite(sim.R).all() and np.isfinite(sim.t).all()
    ):
        log.warning("georeferencing skipped: the fit is not finite (scale %r)", sim.scale)
        return None
    rec.transform(sim.to_pycolmap())
    return result


def _fit(
    centres: Mapping[str, np.ndarray],
    names: list[str],
    enu: Mapping[str, np.ndarray],
    threshold: float,
    rec: pycolmap.Reconstruction,
    up_cam: Mapping[str, np.ndarray] | None,
    heights: Mapping[str, float] | None,
) -> Alignment | None:
    """align's estimate over the registered images ``names`` that have a finite fix."""
    src = np.stack([centres[n] for n in names])
    dst = np.stack([np.asarray(enu[n], np.float64) for n in names])
    gravity = model_up(rec, up_cam) if up_cam else None
    result = robust_similarity(src, dst, threshold, up=gravity[0] if gravity else None)
    if result is None:
        return None
    result = replace(result, names=tuple(names))
    if gravity is not None:
        result = replace(result, up_images=gravity[1])
        known = heights or {}
        named = sorted(n for n in centres if n in known and np.isfinite(known[n]))
        if len(named) >= MIN_HEIGHTS:
            inl = result.inliers
            refined = fit_with_heights(
                src[inl],
                dst[inl],
                gravity[0],
                result.sim,
                np.stack([centres[n] for n in named]),
                np.array([known[n] for n in named]),
            )
            if refined is not None:
                sim, use = refined
                r = np.linalg.norm(sim.apply(src) - dst, axis=1)
                result = replace(result, sim=sim, residuals=r, heights=use)
    return result


def summary_fields(gps: GpsFixes | None, alignment: Alignment | None) -> dict[str, Any]:
    """What summary.json says about the frame: ``georeferenced`` always; the frame, its origin,
    the ENU -> ECEF transform and the alignment's residuals when the model is in it."""
    out: dict[str, Any] = {"georeferenced": alignment is not None}
    if gps is None:
        out["gps_images"] = 0
        return out
    out["gps_images"] = len(gps.enu)
    if alignment is None:
        return out
    out.update(
        frame="ENU",
        origin=gps.frame.as_dict(),
        ecef_from_enu=gps.frame.ecef_from_enu_matrix(),
        vertical="ellipsoidal" if gps.has_altitude else "free (no fix had an altitude)",
        alignment=alignment.as_dict(),
    )
    return out


def ply_origin_comment(path: Path, frame: EnuFrame) -> None:
    """Insert ``comment origin LAT LON ALT`` (and the frame) into a PLY header: the file alone
    then says where its ENU metres are."""
    data = path.read_bytes()
    first = data.index(b"\n", data.index(b"format")) + 1
    comment = (
        f"comment frame ENU metres\ncomment origin {frame.lat:.9f} {frame.lon:.9f} {frame.alt:.4f}\n"
    ).encode("ascii")
    path.write_bytes(data[:first] + comment + data[first:])


def errors_against(rec: pycolmap.Reconstruction, truth: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """How far a georeferenced model's camera centres are from the true positions (``truth``:
    name -> ENU metres in the model's frame), with no further alignment: what a user measuring
    in the model gets. ``scale_error``: |s - 1| of the least-squares similarity model -> truth
    (a model at true scale needs none)."""
    centres = camera_centres(rec)
    names = sorted(n for n in centres if n in truth)
    if not names:
        return {"images": 0}
    src = np.stack([centres[n] for n in names])
    dst = np.stack([np.asarray(truth[n], np.float64) for n in names])
    err = np.linalg.norm(src - dst, axis=1)
    out: dict[str, Any] = {
        "images": len(names),
        "mean_m": float(err.mean()),
        "median_m": float(np.median(err)),
        "max_m": float(err.max()),
        "per_image_m": {n: float(e) for n, e in zip(names, err, strict=True)},
    }
    if len(names) >= 3:
        out["scale_error"] = abs(umeyama(src, dst).scale - 1.0)
    return out
