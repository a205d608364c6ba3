"""Where a camera of a georeferenced model is on the globe, and which way it looks.

A georeferenced model is in ENU metres around the project's origin (gps.py, georef.py), so a
camera centre goes to WGS84 through that frame. The heading is the compass direction of the
camera's optical axis projected on the horizontal plane (clockwise from north, 0-360), what a
map marker's arrow shows; for a camera looking straight down it is undefined, and the roll of
the image's top edge is used instead (where the top of the photo points), since a nadir drone
photo's "heading" in every tool is the direction of its top edge.
"""

from __future__ import annotations

import math

import numpy as np

from .geodesy import EnuFrame

# below this horizontal share of the optical axis (about 84 degrees down) the axis' azimuth is
# noise: the image's up direction decides the heading instead
NADIR_HORIZONTAL = 0.1


def azimuth_deg(direction_enu: np.ndarray) -> float:
    """Clockwise from north, in [0, 360), of a direction's horizontal part."""
    east, north = float(direction_enu[0]), float(direction_enu[1])
    return math.degrees(math.atan2(east, north)) % 360.0


def heading_deg(world_from_cam_rotation: np.ndarray) -> float:
    """The heading of a camera whose rotation (camera -> ENU) is given: its optical axis (+z in
    COLMAP's camera frame), or, looking nearly straight down, the top of its image (-y)."""
    R = np.asarray(world_from_cam_rotation, np.float64)
    axis = R[:, 2]
    if math.hypot(axis[0], axis[1]) >= NADIR_HORIZONTAL:
        return azimuth_deg(axis)
    return azimuth_deg(-R[:, 1])


def wgs84(frame: EnuFrame, centre_enu: np.ndarray, world_from_cam_rotation: np.ndarray) -> dict[str, float]:
    """``{"lat", "lon", "alt", "heading_deg"}`` of a camera of a model in ``frame``'s ENU metres
    (altitude ellipsoidal, as the frame's)."""
    lat, lon, alt = frame.to_geodetic(np.asarray(centre_enu, np.float64).reshape(3))
    return {
        "lat": float(lat),
        "lon": float(lon),
        "alt": float(alt),
        "heading_deg": heading_deg(world_from_cam_rotation),
    }
