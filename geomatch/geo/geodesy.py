"""WGS84 geodetic <-> ECEF <-> local ENU, in numpy.

A drone project spans a few hundred metres, where a local East-North-Up frame tangent to the
ellipsoid at one fix is metric and flat to millimetres, which is what COLMAP's bundle adjustment
and a user's measurements want; ECEF is the global frame that the ENU frame is tied to (its
origin and rotation), so a model can always be put back on the globe. Written out here rather
than taken from pyproj: the formulas are a few lines and the service stays free of PROJ data.
Altitudes are ellipsoidal heights (what the conversion is exact for); EXIF altitudes are
usually above mean sea level, a constant offset over a project's extent that only moves the
ENU origin up or down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WGS84_A = 6378137.0  # semi-major axis, metres
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)  # second eccentricity squared


def geodetic_to_ecef(lat: np.ndarray | float, lon: np.ndarray | float, alt: np.ndarray | float) -> np.ndarray:
    """Degrees, degrees, metres (ellipsoidal) -> (..., 3) ECEF metres."""
    la, lo = np.radians(np.asarray(lat, np.float64)), np.radians(np.asarray(lon, np.float64))
    h = np.asarray(alt, np.float64)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(la) ** 2)
    x = (n + h) * np.cos(la) * np.cos(lo)
    y = (n + h) * np.cos(la) * np.sin(lo)
    z = (n * (1.0 - WGS84_E2) + h) * np.sin(la)
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., 3) ECEF metres -> latitude, longitude (degrees), ellipsoidal height (metres).

    Bowring's closed form followed by two Newton-like refinements: sub-micrometre anywhere near
    the Earth's surface (the round trip the tests hold it to), without an open-ended loop."""
    xyz = np.asarray(xyz, np.float64)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    theta = np.arctan2(z * WGS84_A, p * WGS84_B)
    lat = np.arctan2(
        z + WGS84_EP2 * WGS84_B * np.sin(theta) ** 3, p - WGS84_E2 * WGS84_A * np.cos(theta) ** 3
    )
    for _ in range(2):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = p / np.maximum(np.cos(lat), 1e-300) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    # near the poles cos(lat) vanishes: use the z form of the height there
    cl, sl = np.cos(lat), np.sin(lat)
    h = np.where(
        np.abs(cl) > 1e-3,
        p / np.where(cl == 0, 1.0, cl) - n,
        z / np.where(sl == 0, 1.0, sl) - n * (1.0 - WGS84_E2),
    )
    return np.degrees(lat), np.degrees(lon), h


def enu_rotation(lat: float, lon: float) -> np.ndarray:
    """3x3 rotation taking ECEF directions to East-North-Up at (lat, lon) degrees (rows E, N, U)."""
    la, lo = np.radians(lat), np.radians(lon)
    sl, cl, so, co = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


@dataclass(frozen=True)
class EnuFrame:
    """A local ENU frame tangent at ``origin`` (lat, lon degrees, alt metres); the transform to
    ECEF is ``ecef = R.T @ enu + origin_ecef``, kept so that a model can go back to WGS84."""

    lat: float
    lon: float
    alt: float

    @property
    def origin_ecef(self) -> np.ndarray:
        return geodetic_to_ecef(self.lat, self.lon, self.alt)

    @property
    def rotation(self) -> np.ndarray:
        return enu_rotation(self.lat, self.lon)

    def from_ecef(self, xyz: np.ndarray) -> np.ndarray:
        return (np.asarray(xyz, np.float64) - self.origin_ecef) @ self.rotation.T

    def to_ecef(self, enu: np.ndarray) -> np.ndarray:
        return np.asarray(enu, np.float64) @ self.rotation + self.origin_ecef

    def from_geodetic(
        self, lat: np.ndarray | float, lon: np.ndarray | float, alt: np.ndarray | float
    ) -> np.ndarray:
        return self.from_ecef(geodetic_to_ecef(lat, lon, alt))

    def to_geodetic(self, enu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return ecef_to_geodetic(self.to_ecef(enu))

    def ecef_from_enu_matrix(self) -> list[list[float]]:
        """4x4 homogeneous ENU -> ECEF, for the summary (a reader needs nothing else)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.T
        m[:3, 3] = self.origin_ecef
        return m.tolist()

    def as_dict(self) -> dict[str, float]:
        return {"lat": self.lat, "lon": self.lon, "alt": self.alt}
