"""A project's GPS fixes as positions in one local ENU frame, and as COLMAP pose priors.

The frame's origin is the first fix in name order (with altitude 0 when that fix has none): a
fixed, reproducible choice, so re-running a project or adding images keeps its frame. Fixes
without altitude are placed at the median altitude of the others (a horizontal prior is still a
prior); when no fix has an altitude the up axis is free and the project is not georeferenced in
height (``has_altitude`` false), which georef.py reports.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..metadata import ImageMeta, camera_from_gimbal, up_in_camera
from .geodesy import EnuFrame


@dataclass(frozen=True)
class GpsFixes:
    frame: EnuFrame
    enu: dict[str, np.ndarray]  # image name -> (3,) ENU metres
    has_altitude: bool
    # image name -> the world's up in that camera's frame, from the gimbal (metadata.up_in_camera);
    # images without a fix count too: gravity constrains the model's rotation wherever it comes from
    up: dict[str, np.ndarray] = field(default_factory=dict)
    # image name -> height above take-off in metres (DJI RelativeAltitude, a barometer): decimetres
    # between the images of one flight, where GNSS altitude is metres; georef.py fits scale to it
    heights: dict[str, float] = field(default_factory=dict)


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def fixes(names: Sequence[str], metas: Mapping[str, ImageMeta]) -> GpsFixes | None:
    """The images' fixes in the ENU frame of the first one; None when no image has GPS. A value
    that is not finite counts as absent: read_metadata already drops those, but an ImageMeta may
    come from elsewhere, and one NaN here made every fix NaN (the median) and the georeferencing's
    SVD fail."""
    located = {
        n: (lat, lon)
        for n in sorted(names)
        if (ll := metas[n].lat_lon) is not None
        and (lat := _finite(ll[0])) is not None
        and (lon := _finite(ll[1])) is not None
    }
    if not located:
        return None
    alt_of = {n: _finite(metas[n].altitude_m) for n in located}
    alts = [a for a in alt_of.values() if a is not None]
    fallback = float(np.median(alts)) if alts else 0.0
    name0, (lat0, lon0) = next(iter(located.items()))
    alt0 = alt_of[name0]
    frame = EnuFrame(float(lat0), float(lon0), float(alt0 if alt0 is not None else fallback))
    enu = {}
    for n, (lat, lon) in located.items():
        alt = alt_of[n]
        enu[n] = frame.from_geodetic(lat, lon, alt if alt is not None else fallback)
    up = {n: u for n in names if (u := up_in_camera(metas[n])) is not None and np.isfinite(u).all()}
    heights = {n: h for n in names if (h := _finite(metas[n].relative_altitude_m)) is not None}
    return GpsFixes(frame, enu, bool(alts), up, heights)


def write_pose_priors(database: Path, ids: Mapping[str, int], gps: GpsFixes, sigma_m: float = 5.0) -> int:
    """Position priors (ENU metres, ``sigma_m`` per axis) for the images with a fix, so that the
    database carries them for COLMAP's own tools (``colmap mapper`` with
    ``use_prior_position``, ``model_aligner``); returns how many were written. An existing prior
    is replaced, so a re-run with other fixes does not keep stale ones."""
    db = pycolmap.Database.open(str(database))
    written = 0
    try:
        existing = {int(p.corr_data_id.id): p for p in db.read_all_pose_priors()}
        with pycolmap.DatabaseTransaction(db):
            for name, pos in gps.enu.items():
                if name not in ids:
                    continue
                image = db.read_image(ids[name])
                prior = pycolmap.PosePrior()
                prior.corr_data_id = image.data_id
                prior.position = np.asarray(pos, np.float64).reshape(3, 1)
                prior.position_covariance = np.eye(3) * sigma_m**2
                prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
                old = existing.get(int(image.image_id))
                if old is not None:
                    prior.pose_prior_id = old.pose_prior_id
                    db.update_pose_prior(prior)
                else:
                    db.write_pose_prior(prior)
                written += 1
    finally:
        db.close()
    return written


MAX_LOOK_FACTOR = 3.0  # an oblique's look point at most this many heights ahead (near-horizontal views)
MIN_TILT_PITCH_DEG = -10.0  # a gimbal pitched above this looks at the horizon: no ground point


def look_point(position: np.ndarray, meta: ImageMeta) -> np.ndarray:
    """Where on the ground an aerial camera looks (east, north), from the gimbal's pitch and yaw
    and the height above take-off in the DJI XMP; the position itself when the metadata does
    not say (no XMP, a ground camera, a view near the horizon). An oblique survey flown in
    alternating directions puts two neighbouring lines' footprints two offsets apart, so
    pairing by position would pair images that see different ground; the look point pairs
    those whose footprints overlap. ``gps:K`` plans by it (pairs.gps_neighbours)."""
    xy = np.asarray(position, np.float64)[:2]
    pitch, yaw, h = meta.gimbal_pitch_deg, meta.gimbal_yaw_deg, meta.relative_altitude_m
    if pitch is None or yaw is None or h is None or h <= 0 or pitch > MIN_TILT_PITCH_DEG:
        return xy
    ahead = min(h * np.tan(np.radians(90.0 + pitch)), MAX_LOOK_FACTOR * h)
    return xy + ahead * np.array([np.sin(np.radians(yaw)), np.cos(np.radians(yaw))])


FALLBACK_HFOV_DEG = 73.0  # a 24 mm-equivalent lens (DJI Mavic / Phantom) when EXIF has no focal length
FOOTPRINT_GRID = (4, 3)  # corner-to-corner samples across and down the image for the footprint's outline


def footprint(position: np.ndarray, meta: ImageMeta) -> np.ndarray | None:
    """The ground an aerial image sees, as a polygon (M, 2) east-north, counter-clockwise: the
    image's outline cast onto flat ground at the take-off height (DJI relative altitude), each
    ray cut at MAX_LOOK_FACTOR heights (an oblique's upper edge reaches the horizon). None when
    the metadata cannot say (no gimbal or altitude, a ground camera)."""
    R = camera_from_gimbal(meta)
    h = meta.relative_altitude_m
    pitch = meta.gimbal_pitch_deg  # set wherever R is: the rotation is the gimbal's
    if R is None or h is None or h <= 0 or pitch is None or pitch > MIN_TILT_PITCH_DEG:
        return None
    w, ht = meta.width, meta.height
    f = meta.focal_px or (w / 2) / np.tan(np.radians(FALLBACK_HFOV_DEG / 2))
    gx, gy = FOOTPRINT_GRID
    us, vs = np.linspace(0, w, gx + 1), np.linspace(0, ht, gy + 1)
    # the outline clockwise in the image (top, right, bottom, left): counter-clockwise on the ground
    # seen from above, since the image's y runs down
    border = (
        [(u, 0.0) for u in us[:-1]]
        + [(w, v) for v in vs[:-1]]
        + [(u, ht) for u in us[::-1][:-1]]
        + [(0.0, v) for v in vs[::-1][:-1]]
    )
    rays = np.array([[(u - w / 2) / f, (v - ht / 2) / f, 1.0] for u, v in border]) @ R  # world
    reach = MAX_LOOK_FACTOR * h
    horizontal = np.linalg.norm(rays[:, :2], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[:, 2] < 0, h / -rays[:, 2], np.inf)
    t = np.minimum(t, reach / np.maximum(horizontal, 1e-12))
    outline = np.asarray(position, np.float64)[:2] + t[:, None] * rays[:, :2]
    x, y = outline[:, 0], outline[:, 1]
    if (x * np.roll(y, -1) - np.roll(x, -1) * y).sum() < 0:  # shoelace: keep counter-clockwise
        outline = outline[::-1]
    return outline


def footprints(gps: GpsFixes, metas: Mapping[str, ImageMeta]) -> dict[str, np.ndarray]:
    """The footprints (above) of the located images whose metadata gives one."""
    out = {}
    for n, p in gps.enu.items():
        fp = footprint(p, metas[n])
        if fp is not None:
            out[n] = fp
    return out


def plan_points(gps: GpsFixes, metas: Mapping[str, ImageMeta]) -> dict[str, np.ndarray]:
    """The east-north point each located image is paired by (its look point)."""
    return {n: look_point(p, metas[n]) for n, p in gps.enu.items()}
