"""Where a georeferenced model's coordinates are on the Earth: the frame change the drone tools'
outputs need (a point cloud in absolute projected coordinates, photos on WGS84).

A run's summary says which frame its model is in (``geomatch.geo``): ``ENU`` metres around the
first GPS fix (``origin``), or ``GCP``, the ground control points' metric frame minus
``gcp.origin`` (the points' mean, kept so that float32 viewers keep their precision). Tools such as
WebODM and PDAL want absolute coordinates in a projected system they can name, so this module
gives, for either frame, the projected CRS (the UTM zone of the site for GPS, the GCP file's own
metric frame for GCPs), the model's points in it, the same points on WGS84, and the rotation from
the model's axes to the projected system's (a UTM grid is turned from local east-north by the
meridian convergence, up to a degree or two). A model that is not georeferenced has no frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyproj

from ..geo.geodesy import EnuFrame

WGS84 = pyproj.CRS.from_epsg(4326)


def utm_zone(lat: float, lon: float) -> pyproj.CRS:
    """The WGS84 UTM zone (EPSG 326xx north, 327xx south) holding the point."""
    zone = math.floor((lon + 180.0) / 6.0) % 60 + 1
    return pyproj.CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


@dataclass(frozen=True)
class ModelFrame:
    """A georeferenced model's frame. ``crs``: the projected system of :meth:`to_projected`;
    ``kind``: the summary's ``frame`` (``ENU`` or ``GCP``)."""

    kind: str
    crs: pyproj.CRS
    enu: EnuFrame | None = None  # ENU: the tangent frame at the first fix
    offset: np.ndarray | None = None  # GCP: the model is the metric frame minus this

    def to_projected(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) model coordinates -> absolute (easting, northing, height) in :attr:`crs`;
        heights are ellipsoidal for GPS and as the GCP file gave them for GCPs."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        if self.offset is not None:
            return xyz + self.offset
        assert self.enu is not None
        lat, lon, h = self.enu.to_geodetic(xyz)
        to_crs = pyproj.Transformer.from_crs(WGS84, self.crs, always_xy=True)
        e, n = to_crs.transform(np.asarray(lon), np.asarray(lat))
        return np.column_stack([np.asarray(e, np.float64), np.asarray(n, np.float64), np.asarray(h)])

    def to_wgs84(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) model coordinates -> (longitude, latitude, height) in degrees and metres."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        if self.enu is not None:
            lat, lon, h = self.enu.to_geodetic(xyz)
            return np.column_stack([np.asarray(lon), np.asarray(lat), np.asarray(h)])
        p = self.to_projected(xyz)
        to_wgs = pyproj.Transformer.from_crs(self.crs, WGS84, always_xy=True)
        lon, lat = to_wgs.transform(p[:, 0], p[:, 1])
        return np.column_stack([np.asarray(lon, np.float64), np.asarray(lat, np.float64), p[:, 2]])

    def projected_from_model(self, at: np.ndarray) -> np.ndarray:
        """The rotation (3x3) from the model's axes to the projected system's near ``at`` (a model
        point): identity for GCPs (the model's axes are the frame's), the grid's turn from local
        east-north for GPS, measured from the projection itself (its scale is left out)."""
        if self.offset is not None:
            return np.eye(3)
        at = np.asarray(at, np.float64).reshape(3)
        step = 10.0
        p = self.to_projected(
            np.stack([at, at + np.array([step, 0.0, 0.0]), at + np.array([0.0, step, 0.0])])
        )
        east, north = (p[1, :2] - p[0, :2]), (p[2, :2] - p[0, :2])
        jac = np.column_stack([east, north]) / step
        u, _, vt = np.linalg.svd(jac)
        r2 = u @ vt  # the nearest rotation: the projection's scale factor is not a turn
        out = np.eye(3)
        out[:2, :2] = r2
        return out


def model_frame(summary: Mapping[str, Any]) -> ModelFrame | None:
    """The frame of a run's model from its summary, None when it is not georeferenced."""
    if not summary.get("georeferenced"):
        return None
    kind = summary.get("frame")
    if kind == "ENU" and summary.get("origin"):
        o = summary["origin"]
        enu = EnuFrame(float(o["lat"]), float(o["lon"]), float(o["alt"]))
        return ModelFrame("ENU", utm_zone(enu.lat, enu.lon), enu=enu)
    gcp = summary.get("gcp") or {}
    if kind == "GCP" and gcp.get("frame") and gcp.get("origin") is not None:
        crs = pyproj.CRS.from_user_input(gcp["frame"])
        return ModelFrame("GCP", crs, offset=np.asarray(gcp["origin"], np.float64).reshape(3))
    return None
